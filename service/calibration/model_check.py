"""The model check a user runs before tracking: how far one world of the robot's config, replayed
open loop from a recording's true start, follows what the recording measured, and which change
of the model would bring it closer.

Every variant is a group of one population (or of a second one, for a friction cone: a solver
option), so the whole check is one batched replay: the config as it is; its impratio ten times
higher and lower; each actuated joint's servo twice and half as strong (gain, damping and effort
together); and the other friction cone. What it reports per joint is the RMS error net of the
recording's joint noise, per track how hard the worlds press against what the robot felt
(fingertip forces, touch zones) and how far the object drifts from its true pose, and the
variants that lower the error most, as changes to make.

No library does this: it is MuJoCo-style replay of this project's robot configs against its
recordings, with the worlds' own per-world settings as the candidates.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from inhand_tracker.protocol import Trajectory
from inhand_tracker.sim_backend import Kinematics, Population, PopulationConfig, RobotSpec, catalog_object
from inhand_tracker.sim_backend.build import resolve_physics

__all__ = ["ModelCheck", "check_model", "model_check_report"]

_SCALE = 2.0
"""How much stronger or weaker a servo variant is: a halved or doubled actuator stands out."""
_IMPRATIO = 10.0
"""How much higher or lower an impratio variant is."""
_NAMED = 0.005
"""A joint further off than this, net of the noise [rad or m], is named a mismatch."""
_PRESS = (0.9, 1.1)
"""Pressing ratios outside this band are named a mismatch."""
_MOST_JOINTS = 12
"""Servo variants are tried on this many of the joints furthest off at most."""


@dataclass(frozen=True)
class Replay:
    """What one variant's worlds did over the tracks, against the recording."""

    joint_rms: np.ndarray
    """RMS joint error per joint over every track's frames, (D,) [rad or m]."""
    force_ratio: float
    """The worlds' summed fingertip force over the robot's (nan where it sensed none)."""
    touch_ratio: float
    """The worlds' summed touch-zone force over the robot's (nan where it sensed none)."""
    drift: np.ndarray
    """The object's mean position error per track, (n,) [m]."""


@dataclass(frozen=True)
class ModelCheck:
    """A robot config replayed against recordings, and the variants tried."""

    robot: str
    joints: tuple[str, ...]
    actuated: np.ndarray
    """Which joints the robot drives, (D,) bool (the others follow tendons, springs or contact)."""
    cone: str
    impratio: float
    integrator: str
    joint_noise: float
    base: Replay
    variants: dict[str, Replay] = field(default_factory=dict)
    """By what changed: "impratio 100", "cone elliptic", "servo robot0:FFJ1 x0.5", ..."""

    def net(self, rms: np.ndarray) -> np.ndarray:
        """``rms`` with the joints' noise taken out, (D,)."""
        return np.sqrt(np.maximum(rms**2 - self.joint_noise**2, 0.0))

    def score(self, r: Replay) -> float:
        """One number to rank variants by: the mean squared joint error net of noise [rad^2] plus
        the object's mean squared drift [m^2], so that 1 cm of drift weighs as 10 mrad on a joint."""
        return float(np.mean(self.net(r.joint_rms) ** 2) + np.mean(r.drift**2))

    def summary(self) -> dict:
        """As JSON-able numbers."""
        as_dict = lambda r: {  # noqa: E731
            "joint_rms_net": dict(zip(self.joints, self.net(r.joint_rms).tolist(), strict=True)),
            "force_ratio": r.force_ratio,
            "touch_ratio": r.touch_ratio,
            "drift_m": r.drift.tolist(),
            "score": self.score(r),
        }
        return {
            "robot": self.robot,
            "cone": self.cone,
            "impratio": self.impratio,
            "integrator": self.integrator,
            "joint_noise": self.joint_noise,
            "actuated": dict(zip(self.joints, self.actuated.tolist(), strict=True)),
            "as_configured": as_dict(self.base),
            "variants": {name: as_dict(r) for name, r in self.variants.items()},
            "changes": [{"change": w, "score_before": b, "score_after": a} for w, b, a in self.changes()],
        }

    def changes(self, most: int = 3) -> list[tuple[str, float, float]]:
        """The variants that lower the score most, best first: (what, score before, after)."""
        base = self.score(self.base)
        better = sorted((self.score(r), name) for name, r in self.variants.items() if self.score(r) < 0.8 * base)
        return [(name, base, s) for s, name in better[:most]]


def check_model(
    robot: RobotSpec,
    trajectories: list[Trajectory],
    device: str = "auto",
    joint_noise: float = 0.0,
    variants: bool = True,
    physics: dict | None = None,
) -> ModelCheck:
    """Replay ``trajectories`` (each with its truth: start, mass, friction, object poses) in one
    world each of ``robot``'s model, with the variants when ``variants``: first the config, its
    impratio ten times higher and lower, and the other friction cone; then each driven joint the
    config leaves off, with its servo twice and half as strong. ``physics``: PopulationConfig
    settings the service runs with (its ``[physics]``), by field name. A ValueError names a
    recording that cannot be checked."""
    _refuse(robot, trajectories, joint_noise)
    obj = catalog_object(trajectories[0].object)
    n = len(trajectories)
    layout = Kinematics(robot).layout
    base = PopulationConfig(groups=n, worlds=1, device=device, use_graph=False, **(physics or {}))
    cfg = resolve_physics(robot, base, layout)
    ratios = [1.0, _IMPRATIO, 1.0 / _IMPRATIO] if variants else [1.0]
    first = _replay(Population(robot, obj, replace(cfg, groups=n * len(ratios))), trajectories, impratio=ratios)
    out = {"as configured": first[0]}
    if not variants:
        return _check(robot, layout, cfg, joint_noise, out)
    out |= {f"impratio {cfg.impratio * r:g}": x for r, x in zip(ratios[1:], first[1:], strict=True)}
    other = "elliptic" if cfg.cone == "pyramidal" else "pyramidal"
    out[f"cone {other}"] = _replay(Population(robot, obj, replace(cfg, cone=other)), trajectories)[0]
    net = np.sqrt(np.maximum(first[0].joint_rms ** 2 - joint_noise**2, 0.0))
    off = [j for j in np.argsort(-net) if layout.actuated[j] and net[j] > _NAMED][:_MOST_JOINTS]
    if off:
        scales = [(j, f) for j in off for f in (1.0 / _SCALE, _SCALE)]
        pop = Population(robot, obj, replace(cfg, groups=n * len(scales)))
        servo = {s: pop.servos(s).view(len(scales), n, pop.D).clone() for s in ("ke", "kd", "effort")}
        for i, (j, f) in enumerate(scales):
            for x in servo.values():
                x[i, :, j] *= f
        scaled = _replay(pop, trajectories, servos={s: x.view(-1, 1, pop.D) for s, x in servo.items()})
        out |= {f"servo {layout.joint_names[j]} x{f:g}": x for (j, f), x in zip(scales, scaled, strict=True)}
    return _check(robot, layout, cfg, joint_noise, out)


def _check(robot: RobotSpec, layout, cfg: PopulationConfig, joint_noise: float, out: dict) -> ModelCheck:
    return ModelCheck(
        robot=robot.name,
        joints=layout.joint_names,
        actuated=layout.actuated.copy(),
        cone=str(cfg.cone),
        impratio=float(cfg.impratio),
        integrator=str(cfg.integrator),
        joint_noise=joint_noise,
        base=out.pop("as configured"),
        variants=out,
    )


def _refuse(robot: RobotSpec, trajectories: list[Trajectory], joint_noise: float) -> None:
    if not trajectories:
        raise ValueError("check-model: no recording given")
    for t in trajectories:
        if t.truth is None:
            raise ValueError(f"check-model: '{t.name}' carries no truth (the object's start, mass and poses)")
        if t.robot != robot.name:
            raise ValueError(f"check-model: '{t.name}' is of robot '{t.robot}', the config's is '{robot.name}'")
        if t.object != trajectories[0].object:
            raise ValueError(f"check-model: recordings of several objects ({trajectories[0].object} and {t.object})")
    if not (0.0 <= joint_noise < 1.0):
        raise ValueError(f"check-model: joint_noise: expected 0 to 1 rad or m, got {joint_noise}")


def _replay(
    pop: Population,
    trajectories: list[Trajectory],
    impratio: list[float] | None = None,
    servos: dict[str, torch.Tensor] | None = None,
) -> list[Replay]:
    """Every group of ``pop`` (variants x tracks, tracks fastest) replays its track from the truth's
    start with the truth's mass and friction; one :class:`Replay` per variant. ``impratio``: each
    variant's factor on the model's; ``servos``: every world's servo settings, (G, 1, D) each."""
    n = len(trajectories)
    v = pop.G // n
    dev = pop.torch_device
    lengths = np.array([t.frames for t in trajectories])
    f = int(lengths.max())
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], f - len(a), axis=0)]) if len(a) < f else a  # noqa: E731
    tile = lambda a: np.tile(np.asarray(a, np.float32), (v,) + (1,) * (np.ndim(a) - 1))  # noqa: E731
    truth = [t.truth for t in trajectories]
    pop.reset_state(tile(np.stack([t.initial_pose for t in truth])), tile(np.stack([t.initial_q for t in truth])))
    mass = torch.as_tensor(tile([t.mass for t in truth]), device=dev)[:, None]
    friction = torch.as_tensor(tile([t.friction for t in truth]), device=dev)[:, None]
    pop.set_params(mass=mass, friction=friction)
    if impratio is not None:
        factor = torch.as_tensor(np.repeat(impratio, n), dtype=torch.float32, device=dev)[:, None]
        pop.write_params(None, None, None, pop.params.impratio * factor)
    if servos is not None:
        pop.set_servos(**servos)
    controls = np.stack([pad(t.controls) for t in trajectories], axis=1)  # (F, n, D)
    felt = {  # what the robot felt per frame, (F, n, ...), for the kinds it sensed
        k: np.stack([pad(getattr(t, k)) for t in trajectories], axis=1)
        for k in ("force", "touch")
        if getattr(trajectories[0], k) is not None  # present for all or none: one robot, one recorder
    }
    q_true = np.stack([pad(t.q) for t in trajectories], axis=1)
    pose_true = np.stack([pad(t.pose) for t in truth], axis=1)
    within = np.arange(f)[:, None] < lengths[None]  # (F, n)
    sq = np.zeros((v, n, pop.D))
    drift = np.zeros((v, n))
    pressed = {k: np.zeros((v, 2)) for k in ("force", "touch")}
    for i in range(f):
        pop.set_targets(np.tile(controls[i], (v, 1)))
        pop.step()
        w = within[i]
        q = pop.obs.q[:, 0].cpu().numpy().reshape(v, n, pop.D)
        sq += (q - q_true[i]) ** 2 * w[:, None]
        pos = pop.obs.object_pose[:, 0, :3].cpu().numpy().reshape(v, n, 3)
        drift += np.linalg.norm(pos - pose_true[i, :, :3], axis=-1) * w
        for k, sim in (("force", pop.obs.force), ("touch", pop.obs.touch)):
            if k not in felt or sim.shape[-1] == 0:
                continue
            got = sim[:, 0].reshape(v, n, -1).cpu().numpy()
            mag = np.linalg.norm(got.reshape(v, n, -1, 3), axis=-1) if k == "force" else got
            real_mag = np.linalg.norm(felt[k][i], axis=-1) if k == "force" else felt[k][i]
            pressed[k][:, 0] += (mag.sum(-1) * w).sum(-1)
            pressed[k][:, 1] += float((real_mag.sum(-1) * w).sum())
    frames = within.sum()
    ratio = lambda p: p[:, 0] / p[:, 1] if p[0, 1] > 0 else np.full(v, np.nan)  # noqa: E731
    force, touch = ratio(pressed["force"]), ratio(pressed["touch"])
    return [
        Replay(np.sqrt(sq[x].sum(0) / frames), float(force[x]), float(touch[x]), drift[x] / np.maximum(lengths, 1))
        for x in range(v)
    ]


def model_check_report(check: ModelCheck) -> str:
    """The check as text: per joint RMS net of noise, the pressing ratios and drift, the
    mismatches named, and the changes that would bring the model closest."""
    b = check.base
    net = check.net(b.joint_rms)
    lines = [
        f"model check: robot '{check.robot}' (cone {check.cone}, impratio {check.impratio:g},"
        f" integrator {check.integrator}),"
        f" joint noise {check.joint_noise * 1e3:g} mrad taken out",
        "",
        "| joint | driven | RMS net of noise, mrad or mm |",
        "|---|---|---|",
        *(
            f"| {name} | {'yes' if a else 'no (follows)'} | {r * 1e3:.1f} |"
            for name, a, r in zip(check.joints, check.actuated, net, strict=True)
        ),
        "",
        "pressing against what the robot felt: fingertips "
        f"{_ratio(b.force_ratio)}, touch zones {_ratio(b.touch_ratio)}",
        f"object drift from its true pose: mean {np.mean(b.drift) * 1e3:.1f} mm (per track "
        + ", ".join(f"{d * 1e3:.1f}" for d in b.drift)
        + ")",
    ]
    named = [f"{n} {r * 1e3:.1f} mrad" for n, r in sorted(zip(check.joints, net, strict=True), key=lambda x: -x[1])]
    off = [s for s, r in zip(named, sorted(net, reverse=True), strict=True) if r > _NAMED]
    pressing = [
        f"{what} x{x:.2f}" for what, x in (("fingertips", b.force_ratio), ("touch", b.touch_ratio))
        if np.isfinite(x) and not _PRESS[0] <= x <= _PRESS[1]
    ]  # fmt: skip
    lines += ["", "mismatches: " + ("; ".join(off[:5] + pressing) if off or pressing else "none")]
    changes = check.changes()
    if changes:
        lines += ["what would bring the worlds closer (score: mean squared joint error, drift weighed in):"]
        for what, before, after in changes:
            r = check.variants[what]
            lines.append(
                f"  {what}: score {before * 1e6:.1f} -> {after * 1e6:.1f}, drift {np.mean(r.drift) * 1e3:.1f} mm,"
                f" pressing {_ratio(r.force_ratio)} / {_ratio(r.touch_ratio)}"
            )
    elif off or pressing:
        lines += ["no variant tried brings the worlds closer: `inhand-tracker calibrate` fits every servo setting"]
    return "\n".join(lines)


def _ratio(x: float) -> str:
    return f"x{x:.2f}" if np.isfinite(x) else "(not sensed)"

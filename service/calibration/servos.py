"""Servo identification: the robot's position servos (gain, damping, effort limit per joint) and
its joints' own damping, armature and friction fitted to a recording of its commands and measured
joints, with the population as the sampler.

Every world of a population replays the recording's commands with a candidate of its own; the
candidates are scaled from the robot config's values by log factors that CMA-ES (the ``cmaes``
package) proposes, a generation per replay, and scored by the squared difference between each
world's joints and the measured ones. A joint keeps its fitted servo only where that lowers its own
error and the recording excited it; the spread of the best quarter of the last generation says
how well the data pinned each setting.

The recording should be free motion of the hand, or grasps of an object whose pose it carries
(``.traj`` files with ground truth): the worlds simulate the object where the truth says it is,
else far from the hand, where a grasp's blocked joints read as a servo too weak.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from cmaes import CMA

from inhand_tracker.protocol import Trajectory
from inhand_tracker.sim_backend import Population, PopulationConfig
from inhand_tracker.sim_backend.objects import ObjectSpec
from inhand_tracker.sim_backend.robots import RobotSpec

__all__ = ["SERVO_SETTINGS", "STAYS_OFF", "ServoFit", "fit_servos", "out_of_reach"]

log = logging.getLogger(__name__)

SERVO_SETTINGS = ("ke", "kd", "effort", "damping", "armature", "friction")
"""What can be fitted (:data:`sim_backend.SERVO_ARRAYS`): the servo's gain [N m/rad or N/m],
damping [N m s/rad or N s/m] and effort limit [N m or N]; the joint's own damping (its robot
file's, which the servo's adds to), armature [kg m^2 or kg] and dry friction [N m or N]."""
_FACTOR = math.log(10.0)
"""Candidates stay within a factor of 10 of the config's value either way."""
_GAIN = 0.05
"""A joint keeps its fitted servo when that lowers its RMS error by at least this share."""
_EXCITED = 0.1
"""A joint counts as excited when its measured motion spans this share of its range."""
STAYS_OFF = 0.015
"""A joint that the fit leaves further off than this, net of the joints' noise [rad or m], keeps
the config's servo: its model differs in more than its servo (a coupling, a contact, a mass), and
a fitted servo there stands in for what is missing (and drives the worlds to press far harder than
the robot does). Half what the service's model check names at run time (docs/calibration.md)."""


def _net(rms: np.ndarray, noise: float) -> np.ndarray:
    """RMS errors with a measurement noise of standard deviation ``noise`` taken out: independent of
    the model's error, it adds to it in quadrature."""
    return np.sqrt(np.maximum(np.square(rms) - noise**2, 0.0))


@dataclass(frozen=True)
class ServoFit:
    """What a calibration found, per actuated joint (D,)."""

    robot: str
    joints: tuple[str, ...]
    settings: tuple[str, ...]
    """The servo settings fitted (of :data:`SERVO_SETTINGS`)."""
    nominal: dict[str, np.ndarray]
    """The robot config's values, each (D,)."""
    fitted: dict[str, np.ndarray]
    """The fitted values, each (D,): the config's where the joint keeps its servo."""
    spread: dict[str, np.ndarray]
    """How far the best candidates disagree, each (D,): a relative standard deviation."""
    identified: np.ndarray
    """Whether each joint takes its fitted servo, (D,) bool: it was excited and the fit lowered its
    own error."""
    excited: np.ndarray
    """Whether each joint moved enough to say anything, (D,) bool."""
    rms_before: np.ndarray
    """RMS joint error replaying the recording with the config's servos, (D,) [rad or m]."""
    rms_after: np.ndarray
    """The same with the fitted servos, (D,) [rad or m]."""
    worlds: int
    generations: int
    frames: int
    seconds: float
    device: str
    rms_fit: np.ndarray
    """The fit's own RMS error per joint, (D,) [rad or m], kept or not."""
    history: list[float] = field(default_factory=list)
    """The best candidate's mean squared joint error per generation [rad^2 or m^2]."""
    joint_noise: float = 0.0
    """The measured joints' own noise, a standard deviation [rad or m]: no model follows them closer."""

    def net(self, rms: np.ndarray) -> np.ndarray:
        """RMS errors ``rms`` with the joints' noise taken out, (D,) [rad or m]."""
        return _net(rms, self.joint_noise)

    def summary(self) -> dict:
        """As JSON-able numbers, per joint."""
        after_net = self.net(self.rms_after)
        per_joint = [
            {
                "joint": name,
                "excited": bool(self.excited[j]),
                "identified": bool(self.identified[j]),
                "rms_before": float(self.rms_before[j]),
                "rms_after": float(self.rms_after[j]),
                "rms_after_net": float(after_net[j]),
                "rms_fit": float(self.rms_fit[j]),
                **{
                    s: {
                        "nominal": float(self.nominal[s][j]),
                        "fitted": float(self.fitted[s][j]),
                        "spread": float(self.spread[s][j]),
                    }
                    for s in self.settings
                },
            }
            for j, name in enumerate(self.joints)
        ]
        return {
            "robot": self.robot,
            "device": self.device,
            "settings": list(self.settings),
            "worlds": self.worlds,
            "generations": self.generations,
            "frames": self.frames,
            "seconds": self.seconds,
            "rms_before": float(np.sqrt(np.mean(self.rms_before**2))),
            "rms_after": float(np.sqrt(np.mean(self.rms_after**2))),
            "joint_noise": self.joint_noise,
            "history": self.history,
            "joints": per_joint,
        }


@dataclass
class _Series:
    """The recordings side by side on the device: G groups of the population, one per recording."""

    controls: torch.Tensor  # (F, G, D)
    q: torch.Tensor  # (F, G, D)
    valid: torch.Tensor  # (F, G, 1, 1): frames within each recording
    q0: np.ndarray  # (G, D)
    start: np.ndarray  # (G, 7)

    @property
    def frames(self) -> int:
        return int(self.controls.shape[0])


def out_of_reach(obj: ObjectSpec) -> np.ndarray:
    """Where the object lies while the hand moves freely: on the table a metre away, (7,)."""
    return np.array([1.0, 1.0, -obj.mesh.bounds[0, 2], 0.0, 0.0, 0.0, 1.0], np.float32)


def _series(trajectories: list[Trajectory], obj: ObjectSpec, device: torch.device) -> _Series:
    lengths = np.array([t.frames for t in trajectories])
    f = int(lengths.max())

    def pad(a: np.ndarray) -> np.ndarray:
        return np.concatenate([a, np.repeat(a[-1:], f - len(a), axis=0)]) if len(a) < f else a

    stack = lambda name: torch.as_tensor(  # noqa: E731
        np.stack([pad(np.asarray(getattr(t, name), np.float32)) for t in trajectories], axis=1), device=device
    )
    valid = torch.as_tensor(np.arange(f)[:, None] < lengths[None], dtype=torch.float32, device=device)
    start = np.stack([t.truth.initial_pose if t.truth is not None else out_of_reach(obj) for t in trajectories])
    q0 = np.stack([t.truth.initial_q if t.truth is not None else t.q[0] for t in trajectories])
    return _Series(stack("controls"), stack("q"), valid[..., None, None], q0, start)


def _replay(pop: Population, series: _Series, servos: dict[str, torch.Tensor]) -> torch.Tensor:
    """Every world replays the recording with its servos, (K, D) each; returns each world's summed
    squared joint error over the groups' frames, (K, D)."""
    pop.set_servos(**{name: v[None] for name, v in servos.items()})
    pop.reset_state(series.start, series.q0)
    err = torch.zeros((pop.G, pop.K, pop.D), device=pop.torch_device)
    for f in range(series.frames):
        pop.set_targets(series.controls[f])
        pop.step()
        err += (pop.obs.q - series.q[f][:, None]) ** 2 * series.valid[f]
    return err.sum(0)


def _check(
    settings: tuple[str, ...], worlds: int, generations: int, trajectories: list[Trajectory], joint_noise: float
) -> None:
    """A ValueError naming a bad argument of :func:`fit_servos`."""
    unknown = sorted(set(settings) - set(SERVO_SETTINGS))
    if unknown or not settings:
        raise ValueError(f"calibrate settings: expected some of {list(SERVO_SETTINGS)}, got {list(settings)}")
    if worlds < 4 or generations < 1:
        raise ValueError(f"calibrate: expected worlds >= 4 and generations >= 1, got {worlds} and {generations}")
    if not trajectories:
        raise ValueError("calibrate: no recording given")
    if wrong := [t.name for t in trajectories if t.robot != trajectories[0].robot]:
        raise ValueError(f"calibrate: recordings of several robots ({trajectories[0].robot} and {wrong[0]})")
    if not (0.0 <= joint_noise < 1.0):
        raise ValueError(f"calibrate: joint_noise: expected 0 to 1 rad or m, got {joint_noise}")


class _Search:
    """CMA-ES over log factors of the config's settings, scored by replaying the recording: a
    generation is one replay, every world a candidate."""

    def __init__(self, pop: Population, series: _Series, candidates: Callable, worlds: int, seed: int, progress):
        self.pop, self.series, self.candidates = pop, series, candidates
        self.worlds, self.seed, self.progress = worlds, seed, progress
        self.frames_valid = float(series.valid.sum())
        self.history: list[float] = []
        """The best candidate's mean squared joint error [rad^2] per generation."""
        self.xs = self.err = np.zeros(0)
        """The last generation's candidates as (N, S, D) log factors, and each joint's mean squared
        error with them, (N, D)."""

    def joint_rms(self, factors: list[np.ndarray]) -> np.ndarray:
        """Each joint's RMS error [rad or m] replaying with each of ``factors`` ((S, D) log factors,
        at most one per world), (len(factors), D); the last fills the worlds left over."""
        rows = factors + [factors[-1]] * (self.worlds - len(factors))
        err = _replay(self.pop, self.series, self.candidates(np.stack(rows)))
        return np.sqrt(err.cpu().numpy() / self.frames_valid)[: len(factors)]

    def diagonal(self, n_set: int) -> np.ndarray:
        """Each joint's best log factor (D,) for all its ``n_set`` settings at once, from one replay
        with a factor per world between 1/10 and 10. A joint leaves its config's values (factor 0)
        only where that halves its error: elsewhere the data may pin its settings' ratios but hardly
        their scale, and the search is better off near the config."""
        d = self.pop.D
        scales = np.linspace(-_FACTOR, _FACTOR, self.worlds - 1)
        rms = self.joint_rms([np.zeros((n_set, d))] + [np.full((n_set, d), x) for x in scales])
        return np.where(rms[1:].min(0) < 0.5 * rms[0], scales[rms[1:].argmin(0)], 0.0)

    def run(self, mean: np.ndarray, sigma: float, generations: int) -> np.ndarray:
        """``generations`` of CMA-ES per joint from ``mean`` ((S, D) log factors); returns the final
        means, (S, D). A joint's servo acts mostly on its own joint, so every world carries a
        candidate for each joint and each joint's search learns from its own joint's error: N worlds
        are N samples for each joint's few settings, where one search over all of them (S * D
        dimensions) learned little in tens of generations. Each search keeps a full covariance: a
        joint's settings trade against each other along a valley (gain and damping scaled together
        keep their time constant) that a diagonal one cannot follow."""
        n_set, d = mean.shape
        # cmaes needs two dimensions at least: a one-setting fit carries a second that nothing reads.
        width = max(n_set, 2)
        bounds = np.tile([-_FACTOR, _FACTOR], (width, 1))
        start = np.zeros((width, d))
        start[:n_set] = mean
        cmas = [
            CMA(start[:, j], sigma, bounds=bounds, population_size=self.worlds, seed=self.seed + j) for j in range(d)
        ]
        for _ in range(generations):
            xs = np.stack([np.stack([c.ask() for _ in range(self.worlds)]) for c in cmas], axis=-1)  # (N, W, D)
            full = xs[:, :n_set]
            err = (_replay(self.pop, self.series, self.candidates(full)) / self.frames_valid).cpu().numpy()
            for j, c in enumerate(cmas):
                c.tell(list(zip(xs[:, :, j], err[:, j].astype(np.float64), strict=True)))
            self.xs, self.err = full, err
            self.history.append(float(err.mean(-1).min()))
            log.info(
                f"calibrate: generation {len(self.history)}: mean squared joint error best {self.history[-1]:.3g},"
                f" median {float(np.median(err.mean(-1))):.3g}, spread {float(full.std(0).mean()):.3g}"
            )
            if self.progress is not None:
                self.progress(len(self.history), self.history[-1])
        return np.stack([c.mean[:n_set] for c in cmas], axis=-1)


def fit_servos(
    spec: RobotSpec,
    obj: ObjectSpec,
    trajectories: list[Trajectory],
    settings: tuple[str, ...] = ("ke", "kd"),
    worlds: int = 64,
    generations: int = 25,
    device: str = "auto",
    seed: int = 0,
    progress: Callable[[int, float], None] | None = None,
    joint_noise: float = 0.0,
) -> ServoFit:
    """Fit ``settings`` of every actuated joint of ``spec`` to ``trajectories`` (commands and
    measured joints of that robot; ``obj`` is what the population simulates beside it) with
    ``worlds`` candidates a generation; ``progress(generation, best)`` after each. ``joint_noise``:
    the measured joints' noise [rad or m], out of the report's errors. A ValueError names a bad argument."""
    _check(settings, worlds, generations, trajectories, joint_noise)
    t0 = time.perf_counter()
    pop = Population(spec, obj, PopulationConfig(groups=len(trajectories), worlds=worlds, device=device, seed=seed))
    d = pop.D
    if (given := trajectories[0].controls.shape[1]) != d:
        raise ValueError(f"calibrate: the recordings have {given} joints, robot '{spec.name}' {d}")
    series = _series(trajectories, obj, pop.torch_device)
    nominal = {s: pop.servos(s)[0, 0].cpu().numpy().astype(np.float64) for s in settings}
    base = torch.as_tensor(np.stack([nominal[s] for s in settings]), dtype=torch.float32, device=pop.torch_device)

    def candidates(x: np.ndarray) -> dict[str, torch.Tensor]:
        factor = torch.exp(torch.as_tensor(x, dtype=torch.float32, device=pop.torch_device).view(-1, len(settings), d))
        return {name: base[i] * factor[:, i] for i, name in enumerate(settings)}

    # A joint's settings trade against each other (at its limit a servo moves as fast as effort
    # over damping), so from the config's values a search runs up a valley of more effort, away
    # from a joint whose settings are all scaled alike. So one replay first scales all of a joint's
    # settings together along the diagonal, a factor per world, and the search starts from each
    # joint's best.
    n_set = len(settings)
    search = _Search(pop, series, candidates, worlds, seed, progress)
    diagonal = search.diagonal(n_set)
    on_diagonal = np.tile(diagonal, (n_set, 1))
    searched = search.run(on_diagonal, 0.3, generations)
    # The spread of each joint's best quarter, ranked by its own error.
    elite = np.argsort(search.err, axis=0)[: max(2, worlds // 4)]  # (B, D)
    spread = np.take_along_axis(search.xs, elite[:, None, :], axis=0).std(axis=0)  # (S, D) in log factors
    excited = np.ptp(series.q.cpu().numpy(), axis=(0, 1)) >= _EXCITED * (pop.layout.upper - pop.layout.lower)
    # One more replay scores the config's servos, the diagonal's and the search's: each joint takes
    # the better of the last two, and keeps it only where it was excited, its own error fell by a
    # margin (its servo acts on its own joint: a fit that does not help it is noise) and the fit
    # brought it near the measured joint (see STAYS_OFF).
    rms = search.joint_rms([np.zeros((n_set, d)), on_diagonal, searched])
    x_mean = np.where(rms[2] <= rms[1], searched, on_diagonal)
    best = np.minimum(rms[1], rms[2])
    identified = excited & (best < (1.0 - _GAIN) * rms[0]) & (_net(best, joint_noise) <= STAYS_OFF)
    rms = np.stack([rms[0], np.where(identified, best, rms[0])])
    x_fit = np.where(identified, x_mean, 0.0)
    fitted = {s: nominal[s] * np.exp(x_fit[i]) for i, s in enumerate(settings)}
    return ServoFit(
        robot=spec.name,
        joints=pop.layout.joint_names,
        settings=tuple(settings),
        nominal=nominal,
        fitted=fitted,
        spread={s: np.expm1(spread[i]) for i, s in enumerate(settings)},
        identified=identified,
        excited=excited,
        rms_before=rms[0],
        rms_after=rms[1],
        rms_fit=best,
        worlds=worlds,
        generations=generations,
        frames=series.frames,
        seconds=time.perf_counter() - t0,
        device=pop.device.alias,
        history=search.history,
        joint_noise=joint_noise,
    )

"""The recorder: demos run in a population with hidden physics (one world per group), and what
the real robot would have sent (joints, fingertip forces, slip) and where the object really was,
as a :class:`Recording` of G tracks side by side."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from inhand_tracker.protocol import SENSING, GroundTruth, SensingAttributes, Trajectory
from inhand_tracker.sim_backend import Population

from .demos import FRAME_RATE, Demo

__all__ = ["SENSING_NAMES", "Recording", "record", "sensitivity"]

SENSING_NAMES = tuple(f.name for f in SENSING)


@dataclass
class Recording(SensingAttributes):
    """What the robots sent and where the objects really were: G tracks side by side, (F, G, ...).

    Tracks shorter than F are padded by holding their last controls; ``lengths`` says where each
    really ends.
    """

    sensing: dict[str, np.ndarray | None]
    """Every field of protocol.SENSING, (F, G, ...): what the robots sent; None for a field of a
    presence group no track sensed (a robot without fingertip sensors sends no forces)."""
    object_pose: np.ndarray
    """True object pose after each frame, (F, G, 7)."""
    initial_pose: np.ndarray
    """True object pose before the first frame, (G, 7)."""
    initial_q: np.ndarray
    """Joint positions before the first frame, (G, D)."""
    mass: np.ndarray
    """Hidden true mass per group, (G,) [kg]."""
    friction: np.ndarray
    """Hidden true friction per group, (G,)."""
    lengths: np.ndarray
    """Real frames of each track, (G,)."""
    names: tuple[str, ...]
    """Each track's name, (G,)."""

    @property
    def frames(self) -> int:
        return self.object_pose.shape[0]

    def trajectory(self, g: int, robot: str, obj: str, meta: dict | None = None) -> Trajectory:
        """Track ``g`` as a trajectory file's content."""
        n = int(self.lengths[g])
        cut = lambda a: np.ascontiguousarray(a[:n, g])  # noqa: E731
        truth = GroundTruth(
            initial_pose=self.initial_pose[g],
            initial_q=self.initial_q[g],
            pose=cut(self.object_pose),
            mass=float(self.mass[g]),
            friction=float(self.friction[g]),
        )
        sensing = {name: None if v is None else cut(v) for name, v in self.sensing.items()}
        return Trajectory(self.names[g], robot, obj, FRAME_RATE, truth=truth, meta=dict(meta or {}), **sensing)

    @classmethod
    def gather(cls, tracks: Sequence[tuple[Recording, int]]) -> Recording:
        """Track ``g`` of recording ``r`` for each ``(r, g)``, in order. The recordings must have
        the same number of frames (the same demos)."""
        per_frame = lambda name: np.stack([getattr(r, name)[:, g] for r, g in tracks], axis=1)  # noqa: E731
        per_track = lambda name: np.stack([getattr(r, name)[g] for r, g in tracks])  # noqa: E731
        return cls(
            sensing={
                name: None if v is None else np.stack([r.sensing[name][:, g] for r, g in tracks], axis=1)
                for name, v in tracks[0][0].sensing.items()
            },
            object_pose=per_frame("object_pose"),
            **{name: per_track(name) for name in ("initial_pose", "initial_q", "mass", "friction", "lengths")},
            names=tuple(r.names[g] for r, g in tracks),
        )

    def held(self, demos: Sequence[Demo], margin: float = 0.02) -> np.ndarray:
        """Whether each track kept its object in the hand from the lift to the set-down, (G,): the
        object's centre stays ``margin`` [m] above where it started (a lift raises it 6 cm; an
        object carried on the palm is held while it lies there, a negative margin)."""
        out = np.empty(len(demos), bool)
        for g, d in enumerate(demos):
            first = {name: i for name, i in reversed(d.phases)}
            z = self.object_pose[first["carry"] : first["place"], g, 2]
            out[g] = bool(np.all(z >= self.initial_pose[g, 2] + margin))
        return out

    @classmethod
    def stack(cls, trajectories: Sequence[Trajectory]) -> Recording:
        """G trajectories (with truth) side by side, padded to the longest; a field a trajectory
        lacks is zero, one they all lack None."""
        if any(t.truth is None for t in trajectories):
            raise ValueError("recording: every trajectory needs its ground truth")
        lengths = np.array([t.frames for t in trajectories])
        f = int(lengths.max())

        def pad(a: np.ndarray | None, n: int, like: tuple[int, ...]) -> np.ndarray:
            a = np.zeros((n, *like), np.float32) if a is None else np.asarray(a, np.float32)
            return np.concatenate([a, np.repeat(a[-1:], f - n, axis=0)]) if n < f else a

        d = trajectories[0].controls.shape[1]
        l_count = next((t.force.shape[1] for t in trajectories if t.force is not None), 0)
        z_count = next((t.touch.shape[1] for t in trajectories if t.touch is not None), 0)
        sensing = {
            s.name: np.stack(
                [pad(t.sensing[s.name], t.frames, s.shape(d, l_count, z_count)) for t in trajectories], axis=1
            )
            for s in SENSING
            if any(t.sensing[s.name] is not None for t in trajectories)
        }
        sensing |= {s.name: None for s in SENSING if s.name not in sensing}
        return cls(
            sensing=sensing,
            object_pose=np.stack([pad(t.truth.pose, t.frames, (7,)) for t in trajectories], axis=1),
            initial_pose=np.stack([t.truth.initial_pose for t in trajectories]),
            initial_q=np.stack([t.truth.initial_q for t in trajectories]),
            mass=np.array([t.truth.mass for t in trajectories], np.float32),
            friction=np.array([t.truth.friction for t in trajectories], np.float32),
            lengths=lengths,
            names=tuple(t.name for t in trajectories),
        )


_SLIPPERY = 0.02
"""The friction of an object that slips out of the hand (:func:`record`)."""


def record(
    truth: Population,
    demos: Demo | Sequence[Demo],
    mass: np.ndarray,
    friction: np.ndarray,
    slip_from: np.ndarray | None = None,
) -> Recording:
    """Run ``demos`` (one per group, or one for all) in ``truth`` (K=1 per group) with hidden
    ``mass``, ``friction`` (G,). Shorter demos hold their last targets until the longest ends.
    ``slip_from``: per group, the frame from which its object turns slippery (friction 0.02) and
    slides out of the grasp, a drop no robot commanded (-1: never), (G,)."""
    if truth.K != 1:
        raise ValueError(f"truth population: expected 1 world per group, got {truth.K}")
    G = truth.G
    demos = [demos] * G if isinstance(demos, Demo) else list(demos)
    if len(demos) != G:
        raise ValueError(f"record: expected {G} demos (one per group), got {len(demos)}")
    lengths = np.array([d.frames for d in demos])
    f = int(lengths.max())
    controls = np.stack(
        [np.concatenate([d.controls, np.repeat(d.controls[-1:], f - d.frames, axis=0)]) for d in demos], axis=1
    )
    truth.reset_state(np.stack([d.object_pose for d in demos]), np.stack([d.q for d in demos]))
    truth.set_params(
        mass=torch.as_tensor(mass, dtype=torch.float32)[:, None],
        friction=torch.as_tensor(friction, dtype=torch.float32)[:, None],
    )
    # What a robot senses is what a world observes, field for field; the controls are the demo's.
    fields = [f.name for f in SENSING if f.name != "controls"] + ["object_pose"]
    rows: dict[str, list[torch.Tensor]] = {f: [] for f in fields}
    for i, u in enumerate(controls):
        truth.set_targets(u)
        if slip_from is not None and (slip_from == i).any():
            slippery = torch.as_tensor(np.where(slip_from <= i, _SLIPPERY, friction), dtype=torch.float32)
            # Below the object's friction range on purpose (set_params would refuse it): the real
            # object has turned slippery, as no prior of the tracker's allows.
            truth.write_params(truth.mass, slippery[:, None].to(truth.mass.device))
        truth.step()
        for name in fields:
            rows[name].append(getattr(truth.obs, name)[:, 0].clone())
    recorded = {name: torch.stack(v).cpu().numpy() for name, v in rows.items()}
    object_pose = recorded.pop("object_pose")
    return Recording(
        sensing={"controls": controls, **recorded},
        object_pose=object_pose,
        initial_pose=np.stack([d.object_pose for d in demos]),
        initial_q=np.stack([d.q for d in demos]),
        mass=np.asarray(mass, dtype=np.float32),
        friction=np.asarray(friction, dtype=np.float32),
        lengths=lengths,
        names=tuple(d.name for d in demos),
    )


def sensitivity(
    population: Population, demos: Sequence[Demo], mass: np.ndarray, friction: np.ndarray, shift: float = 1e-6
) -> np.ndarray:
    """How far each demo's object ends up from itself when its start moves by ``shift`` [m] along
    x: the largest distance between the two object centres over the demo, (n,) [m].

    ``population`` holds 2n groups of one world: each demo ``n`` as given and shifted, with hidden
    ``mass`` and ``friction`` (n,). A demo whose micrometre shift grows into millimetres is chaotic:
    no tracker can follow its object to the millimetre from a noisy start, whatever its K (the
    banana's pinch when it lay on its back: 64 mm by the lift, docs/benchmarks.md)."""
    n = len(demos)
    if population.G != 2 * n:
        raise ValueError(f"sensitivity: expected a population of {2 * n} groups (two per demo), got {population.G}")
    moved = []
    for d in demos:
        pose = d.object_pose.copy()
        pose[0] += shift
        moved.append(replace(d, object_pose=pose))
    rec = record(population, [*demos, *moved], np.tile(mass, 2), np.tile(friction, 2))
    gap = np.linalg.norm(rec.object_pose[:, :n, :3] - rec.object_pose[:, n:, :3], axis=-1)  # (F, n)
    return np.array([gap[: d.frames, i].max() for i, d in enumerate(demos)])

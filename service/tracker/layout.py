"""The tracker's host-side records and the packed rows that cross between host and device.

A frame crosses to the device as one float32 row per group, laid out from
:data:`protocol.SENSING` (every field flattened, then one presence flag per group of optional
fields); the estimate crosses back as one row per group laid out by :data:`ESTIMATE`. Packer
and reader use the same layout, so a column can never be read at another's offset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from inhand_tracker.protocol import PRESENCE, SENSING, SensingAttributes

__all__ = ["ESTIMATE", "Columns", "Frame", "GroupEstimates", "InputLayout"]


class Frame(SensingAttributes):
    """One frame from the robots of all G groups (host arrays).

    The fields of :data:`protocol.SENSING` by name, each (G, ...): ``controls`` and ``q`` always,
    the touch fields when any group sensed them. ``present`` says per group which presence
    groups it sensed, {"force": (G,) bool, ...}; by default a presence group is present in every
    group when its field of the same name is given, else absent.
    """

    def __init__(self, present: dict[str, np.ndarray] | None = None, **sensing: np.ndarray | None):
        unknown = sorted(set(sensing) - {f.name for f in SENSING})
        if unknown:
            raise ValueError(f"frame: unknown fields {unknown} (known: {[f.name for f in SENSING]})")
        self.sensing = {f.name: sensing.get(f.name) for f in SENSING}
        self.present = present

    def presence(self, groups: int) -> dict[str, np.ndarray]:
        """Each presence group's (G,) bool mask."""
        out = {}
        for name in PRESENCE:
            given = self.present.get(name) if self.present is not None else None
            if given is None:
                given = np.full(groups, self.sensing[name] is not None)
            out[name] = np.broadcast_to(np.asarray(given, bool), (groups,))
        return out


@dataclass(frozen=True)
class Columns:
    """Named column ranges of a packed row: name -> (start, shape)."""

    spans: dict[str, tuple[int, int, tuple[int, ...]]]
    """name -> (first column, column count, shape)."""
    width: int

    @classmethod
    def of(cls, shapes: dict[str, tuple[int, ...]]) -> Columns:
        spans, at = {}, 0
        for name, shape in shapes.items():
            size = int(np.prod(shape, dtype=np.int64))
            spans[name] = (at, size, shape)
            at += size
        return cls(spans, at)

    def view(self, rows, name: str):
        """Field ``name`` of ``rows`` (N, width), shaped (N, *shape); a view, never a copy."""
        start, size, shape = self.spans[name]
        return rows[:, start : start + size].reshape(rows.shape[0], *shape)

    def pack(self, parts: dict[str, torch.Tensor]) -> torch.Tensor:
        """The row (N, width) of ``parts``, each (N, *shape), in layout order."""
        return torch.cat([parts[name].reshape(parts[name].shape[0], -1) for name in self.spans], dim=-1)


ESTIMATE = Columns.of(
    {
        "pose": (7,),
        "best_pose": (7,),
        "mean_pose": (7,),
        "covariance": (6, 6),
        "cost": (),
        "mass": (),
        "friction": (),
        "lost": (),
        "contact_disagreement": (),
        "hand": (3,),
        "modes": (2, 7),
        "mode_weights": (2,),
        "contacts_explored": (),
        "overflow": (),
        "separation": (),
        "evidence": (),
        "reckoning": (),
        "residual": (3,),
    }
)
"""The packed estimate: what one device-to-host copy per frame carries for every group."""


class InputLayout:
    """The packed input row of a robot with ``d`` joints, ``l`` sensors and ``z`` touch zones: every
    sensing field, then one 0/1 flag per presence group (``has_force``, ..., ``has_touch``)."""

    def __init__(self, d: int, l: int, z: int = 0):
        self.d, self.l, self.z = d, l, z
        shapes = {f.name: f.shape(d, l, z) for f in SENSING} | {f"has_{p}": () for p in PRESENCE}
        self.columns = Columns.of(shapes)

    @property
    def width(self) -> int:
        return self.columns.width

    def views(self, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """Every field and flag of ``rows`` (G, width) as views, by name."""
        return {name: self.columns.view(rows, name) for name in self.columns.spans}

    def stage(self, frame: Frame, out: np.ndarray, joint_names: tuple[str, ...] | list[str]) -> None:
        """Check ``frame`` and write it into ``out`` (G, width); a ValueError names the field, the
        group and the numbers, and nothing is written then."""
        groups = out.shape[0]
        rows: dict[str, np.ndarray] = {}
        for f in SENSING:
            value = frame.sensing[f.name]
            if value is None:
                if not f.optional:
                    raise ValueError(f"frame {f.name}: required, got None")
                continue
            arr = np.asarray(value, dtype=np.float32)
            expected = (groups, *f.shape(self.d, self.l, self.z))
            if arr.shape != expected:
                raise ValueError(f"frame {f.name}: expected shape {expected}, got {arr.shape}")
            bad = ~np.isfinite(arr)
            if bad.any():
                at = np.argwhere(bad)[0]
                where = f"joint '{joint_names[at[1]]}'" if f.per == "joint" else f"index {tuple(at[1:])}"
                raise ValueError(
                    f"frame {f.name}: {int(bad.sum())} non-finite, first at group {at[0]} {where}: {arr[tuple(at)]}"
                )
            rows[f.name] = arr
        presence = frame.presence(groups)
        for f in SENSING:
            if f.optional and presence[f.group].any() and f.name not in rows:
                raise ValueError(f"frame {f.name}: required where '{f.group}' is present, got None")
        for name, arr in rows.items():
            self.columns.view(out, name)[...] = arr
        for name, mask in presence.items():
            self.columns.view(out, f"has_{name}")[...] = mask


@dataclass
class GroupEstimates:
    """What the tracker reports for every group after a frame (host arrays)."""

    frame: int
    pose: np.ndarray
    """The estimate, (G, 7): position [m], quaternion (x, y, z, w); the mean over the best world's
    mode (``EstimateConfig.mean_over_mode``), over all, or the best world's (``mean_estimate``)."""
    best_pose: np.ndarray
    """The lowest-cost world's object pose, (G, 7)."""
    cost: np.ndarray
    """Best world's window cost, (G,)."""
    mean_pose: np.ndarray
    """Cost-weighted mean object pose of the group, (G, 7)."""
    covariance: np.ndarray
    """Cost-weighted covariance of (position [m], rotation vector [rad]) about the mean, (G, 6, 6)."""
    mass: np.ndarray
    """Best world's object mass, (G,) [kg]."""
    friction: np.ndarray
    """Best world's object friction, (G,)."""
    lost: np.ndarray
    """Fraction of each group's worlds that lost the object, (G,)."""
    contact_disagreement: np.ndarray
    """Sensors on which the best world and the real robot disagree about contact, (G,)."""
    status: np.ndarray
    """Track state per group, (G,) int (:class:`protocol.TrackState`)."""
    modes: np.ndarray | None = None
    """The two heaviest pose modes' seeds, (G, 2, 7): the lowest-cost world's, then the heaviest
    world's away from it."""
    mode_weights: np.ndarray | None = None
    """The share of the cost weights in each mode, (G, 2)."""
    contacts_explored: np.ndarray | None = None
    """Whether each group's worlds explore their contacts, (G,) bool: its lowest cost said the
    model's contacts are wrong (:attr:`.ContactExploration.contact_gate_cost`)."""
    overflow: np.ndarray | None = None
    """Whether a world of each group dropped contacts or constraint rows for want of room this
    frame, (G,) bool: its physics is then not the robot's (PopulationConfig.contacts_per_world)."""
    joint_rms: np.ndarray | None = None
    """How far the worlds' joints run from the robot's, RMS over the last seconds, (G, D) [rad or
    m]: the model check (:class:`.joint_check.JointCheck`)."""
    separation: np.ndarray | None = None
    """How far each group's last update window told its worlds apart beyond their noise, (G,): the
    F ratio of :func:`.evidence.separation`, about 1 on noise alone (0 before the first update)."""
    evidence: np.ndarray | None = None
    """How strongly each group's last update moved its worlds' poses, (G,): 0 (open loop: the
    sensing told them apart no better than noise, or ranked them by their physics alone) to 1 (full
    strength); 0 before the first update, and always 1 where every update runs at full strength
    (``optimizer.by_evidence`` off)."""
    reckoning: np.ndarray | None = None
    """How far each group's pose is its open-loop world's, (G,): 0, the population's, to 1, dead
    reckoning (always for an OLP group; ``optimizer.open_loop_ratio`` while dead reckoning explains
    the robot as well, or ``by_evidence`` as far as the last update fell short of full strength)."""
    residual: np.ndarray | None = None
    """What each group's lowest-cost world leaves unexplained, a running mean over about a second,
    (G, 3): joints (RMS per joint) [rad or m], each fingertip force's magnitude [N], each touch
    zone's force beyond twice the declared ``touch_noise`` [N]. It holds the sensors' noise and the
    model's mismatch: an upper bound on the noise a robot config declares (``joint_noise``,
    ``force_noise``, ``touch_noise``)."""
    reseeded: np.ndarray | None = None
    """Whether each group was re-seeded after this frame, (G,) bool (never an open-loop group)."""

    @classmethod
    def unpack(cls, rows: np.ndarray, frame: int, status: np.ndarray) -> GroupEstimates:
        """The estimates in the packed ``rows`` (G, ESTIMATE.width)."""
        v = lambda name: ESTIMATE.view(rows, name)  # noqa: E731
        return cls(
            frame=frame,
            pose=v("pose"),
            best_pose=v("best_pose"),
            mean_pose=v("mean_pose"),
            covariance=v("covariance"),
            cost=v("cost"),
            mass=v("mass"),
            friction=v("friction"),
            lost=v("lost"),
            contact_disagreement=v("contact_disagreement"),
            status=status,
            modes=v("modes"),
            mode_weights=v("mode_weights"),
            contacts_explored=v("contacts_explored") > 0.5,
            overflow=v("overflow") > 0.5,
            separation=v("separation"),
            evidence=v("evidence"),
            reckoning=v("reckoning"),
            residual=v("residual"),
        )

"""Scripted manipulation demos and the ground truth they make.

A demo is a sequence of joint targets (frames, D) for the procedural hand. Running it in a
population with hidden physics (one world per group) records what the real robot would send
(joint positions, fingertip forces, slip) and the object's true pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .grasp import Grasp, plan_pinch
from .kinematics import Kinematics
from .objects import ObjectSpec
from .population import Population

__all__ = ["Demo", "Recording", "pick_lift_twist", "pinch_lift_twist", "record"]


@dataclass(frozen=True)
class Demo:
    """A scripted demo: where it starts and the joint targets of every frame."""

    controls: np.ndarray
    """Joint targets, (F, D)."""
    object_pose: np.ndarray
    """Object pose before the first frame, (7,)."""
    q: np.ndarray
    """Joint positions before the first frame, (D,)."""


def _ramp(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n))  # smooth start and stop
    return a + (b - a) * s[:, None]


def pick_lift_twist(kin: Kinematics, obj: ObjectSpec, frames: int = 150, twist: float = 0.4) -> Demo:
    """Pick the object up from the table and turn it in the hand: the open hand descends over it,
    closes into a pinch (the thumb and fingers push it along the table as they meet it), lifts it
    by 5 cm and twists it about the vertical as :func:`pinch_lift_twist` does."""
    if frames < 80:
        raise ValueError(f"frames: a pick-lift-twist needs at least 80 frames, got {frames}")
    rest_z = -float(obj.mesh.bounds[0, 2])  # the object's centre height when it rests on the table
    wrist = np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    wrist[2] += rest_z - plan_pinch(kin, obj, wrist_q=wrist).object_pose[2]  # lower the pinch onto it
    grasp = plan_pinch(kin, obj, wrist_q=wrist)
    pose, palm_z = grasp.object_pose.copy(), float(wrist[2])
    open_hand = kin.layout.default_q.copy()
    open_hand[2] = palm_z + 0.08
    above = open_hand.copy()
    above[2] = palm_z
    n_descend, n_close = frames // 8, frames // 5
    rest = pinch_lift_twist(grasp, frames - n_descend - n_close, twist=twist)
    closing = np.concatenate([_ramp(above, grasp.q_touch, n_close - n_close // 3),
                              _ramp(grasp.q_touch, grasp.q_squeeze, n_close // 3)])  # fmt: skip
    controls = np.concatenate([_ramp(open_hand, above, n_descend), closing, rest])
    return Demo(controls=controls, object_pose=pose, q=open_hand)


def pinch_lift_twist(grasp: Grasp, frames: int = 120, lift: float = 0.05, twist: float = 0.4) -> np.ndarray:
    """Hold the pinch, lift by ``lift`` [m], then turn the object in the hand about the vertical:
    the fingers abduct one way and the thumb swings the other by ``twist`` [rad], rolling the
    pads over the object. Returns joint targets (frames, D)."""
    if frames < 40:
        raise ValueError(f"frames: a pinch-lift-twist needs at least 40 frames, got {frames}")
    n_squeeze, n_lift = frames // 8, frames // 4
    n_twist = frames // 2
    n_hold = frames - n_squeeze - n_lift - n_twist
    held = grasp.q_squeeze.copy()
    lifted = held.copy()
    lifted[2] += lift
    twisted = lifted.copy()
    twisted[[6, 10, 14]] -= twist  # finger abduction: the fingertips move towards -y
    twisted[18] -= twist  # thumb swing: its tip moves towards +y
    parts = [
        np.repeat(held[None], n_squeeze, axis=0),  # squeeze at once: a slow ramp lets it slip out
        _ramp(held, lifted, n_lift),
        _ramp(lifted, twisted, n_twist),
        np.repeat(twisted[None], n_hold, axis=0),
    ]
    return np.concatenate(parts)


@dataclass
class Recording:
    """What the robot sent and where the object really was, per group and frame."""

    controls: np.ndarray
    """Joint targets, (F, G, D)."""
    q: np.ndarray
    """Measured joint positions, (F, G, D)."""
    force: np.ndarray
    """Fingertip contact forces in the sensor frames, (F, G, L, 3) [N]."""
    slip: np.ndarray
    """(F, G, L) translational slip flags."""
    slip_dir: np.ndarray
    """(F, G, L, 2) slip directions."""
    spin: np.ndarray
    """(F, G, L) rotational slip flags."""
    spin_sense: np.ndarray
    """(F, G, L) rotational slip senses."""
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

    @property
    def frames(self) -> int:
        return self.controls.shape[0]


def record(truth: Population, demo: Demo, mass: np.ndarray, friction: np.ndarray) -> Recording:
    """Run ``demo`` in ``truth`` (K=1 per group) with hidden ``mass``, ``friction`` (G,)."""
    if truth.K != 1:
        raise ValueError(f"truth population: expected 1 world per group, got {truth.K}")
    G = truth.G
    controls = demo.controls
    truth.reset_state(demo.object_pose, demo.q)
    truth.set_params(mass=torch.as_tensor(mass, dtype=torch.float32)[:, None],
                     friction=torch.as_tensor(friction, dtype=torch.float32)[:, None])  # fmt: skip
    fields = ("q", "force", "slip", "slip_dir", "spin", "spin_sense", "object_pose")
    rows: dict[str, list[np.ndarray]] = {f: [] for f in fields}
    for u in controls:
        truth.set_targets(np.broadcast_to(u, (G, u.shape[0])))
        truth.step()
        for f in fields:
            rows[f].append(getattr(truth.obs, f)[:, 0].cpu().numpy().copy())
    return Recording(
        controls=np.broadcast_to(controls[:, None], (controls.shape[0], G, controls.shape[1])).copy(),
        initial_pose=np.broadcast_to(demo.object_pose, (G, 7)).copy(),
        initial_q=np.broadcast_to(demo.q, (G, demo.q.shape[0])).copy(),
        mass=np.asarray(mass, dtype=np.float32),
        friction=np.asarray(friction, dtype=np.float32),
        **{f: np.stack(v) for f, v in rows.items()},
    )

"""Scripted manipulation demos for the default hand (the recorder runs them: :mod:`.recorder`).

The paper's demos were teleoperated; ours are scripted for the default hand (the procedural
Allegro-like hand on a 6-DoF wrist) so that any number can be made with known truth:

- ``pick_place``: reach the object on the table, pinch it with the fingertips, lift it, carry it
  about (quick moves, so it slips from inertia), turn it in the hand by 30 degrees or more with
  the fingers and thumb, set it down pressing against the table (it slips again), let go.
- ``gaiting``: the same, but before the turn, while all four pads hold the object, each finger in
  turn breaks contact and makes it again (finger gaiting), three times over.

A demo is a sequence of joint targets (F, D). Running it in a population with hidden physics
(one world per group) records what the real robot would send (joint positions, fingertip
forces, slip) and the object's true pose.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from inhand_tracker.sim_backend.grasp import SQUEEZE_JOINTS, plan_pinch
from inhand_tracker.sim_backend.kinematics import Kinematics
from inhand_tracker.sim_backend.objects import ObjectSpec

__all__ = ["DEMO_KINDS", "FRAME_RATE", "Demo", "Script", "make_demo"]

DEMO_KINDS = ("pick_place", "gaiting")
FRAME_RATE = 30.0
"""Frames per second of every demo [Hz]."""

_FINGER_ABDUCTION = (6, 10, 14)
_FINGER_FLEXION = ((7, 8, 9), (11, 12, 13), (15, 16, 17))
_THUMB_SWING = 18
_TURNS = ((0.08, (0.55, 0.65), 1.0), (0.15, (0.55, 0.65), 1.3), (math.inf, (0.35, 0.4), 1.0))
"""How the fingers turn an object, by its length along the fingers' row: (up to [m], the range of
the finger abduction that turns it [rad], how much further the thumb swings). Measured on the CPU
at friction x0.7-1.3 (docs/benchmarks.md):

- up to 8 cm (the brick) turns 32-37 degrees; a thumb swinging further turned it 50-62 and set it
  down on an edge, where 1 um at the start ended up to 40 mm apart;
- up to 15 cm (the spam can): the outer fingers' abduction stops at its limit (0.47 rad), and a
  thumb that swung no further turned it only 26-30 degrees; at 1.3 times it turns 31-42;
- longer (the banana): the thumb pushing its middle turns it 30-64 degrees at a smaller swing, and
  0.55-0.65 rad turned it so far that its ends left the outer pads and it fell."""
_PLACE_DEPTH = 0.01
"""How far below where it picked the object up the hand sets it down [m]: it presses on the table and slips."""
_CLEAR = 0.2
"""How far past touching the flexion joints open [rad]: just clear of the object, for a gaiting
finger (the others hold it meanwhile) and for letting go."""
_GAITS = 3
"""Finger gaits per demo: each re-press walks the object a few millimetres over the pads, and an
open-loop script (unlike a teleoperator) cannot correct that, so more gaits walk it out of the hand."""


@dataclass(frozen=True)
class Demo:
    """A scripted demo: where it starts and the joint targets of every frame."""

    name: str
    controls: np.ndarray
    """Joint targets, (F, D), within the joint limits."""
    object_pose: np.ndarray
    """Object pose before the first frame, (7,): position [m], quaternion (x, y, z, w)."""
    q: np.ndarray
    """Joint positions before the first frame, (D,)."""
    phases: tuple[tuple[str, int], ...]
    """(phase name, first frame) in order: what the hand is doing when."""

    @property
    def frames(self) -> int:
        return self.controls.shape[0]

    def until(self, phase: str) -> Demo:
        """The demo up to the first frame of ``phase`` (e.g. "carry": picked up and lifted)."""
        end = next((i for name, i in self.phases if name == phase), None)
        if end is None:
            raise ValueError(f"demo '{self.name}' has no phase '{phase}' (phases: {[n for n, _ in self.phases]})")
        return replace(self, controls=self.controls[:end], phases=tuple(p for p in self.phases if p[1] < end))


def cosine_profile(t: np.ndarray) -> np.ndarray:
    """Progress at times ``t`` in (0, 1] of a move with a cosine velocity profile."""
    return 0.5 - 0.5 * np.cos(np.pi * t)


class Script:
    """Joint targets built phase by phase, each a smooth move (along ``profile``: progress in
    [0, 1] at normalised time) or a hold of so many seconds."""

    def __init__(self, q: np.ndarray, lower: np.ndarray, upper: np.ndarray, pace: float = 1.0,
                 profile=cosine_profile):  # fmt: skip
        self.q, self.lower, self.upper, self.pace, self.profile = q.copy(), lower, upper, pace, profile
        self.rows: list[np.ndarray] = []
        self.phases: list[tuple[str, int]] = []
        self.count = 0

    def move(self, phase: str, target: np.ndarray, seconds: float) -> None:
        """Go to ``target`` along the profile (smooth start and stop)."""
        n = max(2, round(seconds * self.pace * FRAME_RATE))
        s = self.profile(np.linspace(0.0, 1.0, n + 1)[1:])
        target = np.clip(target, self.lower, self.upper)
        self._add(phase, self.q + (target - self.q) * s[:, None])
        self.q = target.copy()

    def hold(self, phase: str, seconds: float) -> None:
        self._add(phase, np.repeat(self.q[None], max(1, round(seconds * self.pace * FRAME_RATE)), axis=0))

    def let_go(self, q_touch: np.ndarray) -> None:
        """Uncurl the digits just clear of where they touch the object (``q_touch``), then rise
        straight up. Opening to the rest pose at table height swept the turned fingers and the
        thumb sideways through the object and flung it (the banana half a metre)."""
        release = self.q.copy()
        release[SQUEEZE_JOINTS] = q_touch[SQUEEZE_JOINTS] - _CLEAR
        self.move("release", release, 0.8)
        retreat = release.copy()
        retreat[2] += 0.08
        self.move("retreat", retreat, 1.0)

    def demo(self, name: str, object_pose: np.ndarray, q: np.ndarray) -> Demo:
        """The script so far as a demo of the object at ``object_pose`` with the hand starting at ``q``."""
        return Demo(
            name=name,
            controls=np.concatenate(self.rows).astype(np.float32),
            object_pose=object_pose.astype(np.float32),
            q=q.astype(np.float32),
            phases=tuple(self.phases),
        )

    def _add(self, phase: str, rows: np.ndarray) -> None:
        if not self.phases or self.phases[-1][0] != phase:
            self.phases.append((phase, self.count))
        self.rows.append(rows)
        self.count += rows.shape[0]


def make_demo(
    kin: Kinematics,
    obj: ObjectSpec,
    kind: str = "pick_place",
    variant: int = 0,
    seconds: float = 60.0,
    pace: float = 1.0,
) -> Demo:
    """Script a demo of ``kind`` (see :data:`DEMO_KINDS`) for ``obj`` on the table.

    ``variant`` seeds where the object lies, how far the fingers turn it and where it is carried.
    The manipulation in the middle repeats until the demo lasts about ``seconds``; ``pace`` < 1
    runs every motion faster (short demos).
    """
    if kind not in DEMO_KINDS:
        raise ValueError(f"demo kind: expected one of {DEMO_KINDS}, got {kind!r}")
    if not (0.2 <= pace <= 5.0):
        raise ValueError(f"demo pace: expected 0.2 to 5, got {pace}")
    lay = kin.layout
    rng = np.random.default_rng([variant, DEMO_KINDS.index(kind)])
    length = float(obj.mesh.extents[:2].max())  # the pinch lays the longer side along the row
    turn_range, lead = next((r, lead) for up_to, r, lead in _TURNS if length <= up_to)
    turn = float(rng.uniform(*turn_range))

    rest_z = -float(obj.mesh.bounds[0, 2])  # the object's centre height when it rests on the table
    wrist = np.array([*rng.uniform(-0.05, 0.05, 2), 0.3, 0.0, 0.0, 0.0])
    wrist[2] += rest_z - plan_pinch(kin, obj, wrist_q=wrist).object_pose[2]  # lower the pinch onto it
    grasp = plan_pinch(kin, obj, wrist_q=wrist)
    palm_z = float(wrist[2])
    open_hand = lay.default_q.copy()
    open_hand[:3] = wrist[0], wrist[1], palm_z + 0.12  # straight above: the fingers clear the object
    script = Script(open_hand, lay.lower, lay.upper, pace)

    held = _pick_up(script, open_hand, grasp, palm_z)
    carry = functools.partial(_carry, script, rng)
    # The gaiting demo gaits before the turn, while all four pads press the object: a finger
    # lifts only while the two others and the thumb carry it. Turned, the object rests on the
    # index and thumb alone (docs/benchmarks.md), and lifting either drops it. Turning back and
    # forth more often walks the object out of an open-loop grasp, which a teleoperator would not do.
    carry()
    for gait in range(_GAITS if kind == "gaiting" else 0):
        _gait(script, grasp.q_touch, held, first_first=gait % 2 == 0)
        script.hold("hold", 0.5)
        carry()
    script.move("turn", _turned(script.q, held, turn, lead), 3.0)
    script.hold("turn", 0.5)
    while script.count < (seconds - 3.3) * pace * FRAME_RATE:  # 3.3 s: place, let go, retreat
        carry()
        script.hold("hold", 0.8)
    down = script.q.copy()
    down[2] = palm_z - _PLACE_DEPTH
    script.move("place", down, 1.2)
    script.hold("place", 0.3)
    script.let_go(grasp.q_touch)
    return script.demo(f"{obj.name}_{kind}_{variant}", grasp.object_pose, open_hand)


def _pick_up(script: Script, open_hand: np.ndarray, grasp, palm_z: float) -> np.ndarray:
    """Reach down over the object, close on it, squeeze and lift; returns the holding joints."""
    above = open_hand.copy()
    above[2] = palm_z
    script.move("reach", above, 1.2)
    script.move("close", grasp.q_touch, 0.8)
    script.move("squeeze", grasp.q_squeeze, 0.15)  # squeeze at once: a slow ramp lets it slip out
    script.hold("squeeze", 0.3)
    held = grasp.q_squeeze.copy()
    held[2] += 0.06
    script.move("lift", held, 1.2)
    return held


def _turned(q: np.ndarray, held: np.ndarray, turn: float, lead: float) -> np.ndarray:
    """Fingers abduct one way and the thumb swings the other, rolling the pads over the object.

    Fingers towards -y and the thumb towards +y: the planned pinch leaves the thumb's swing
    next to its upper limit, so the other way barely turns the object."""
    out = q.copy()
    out[list(_FINGER_ABDUCTION)] = held[list(_FINGER_ABDUCTION)] - turn
    out[_THUMB_SWING] = held[_THUMB_SWING] - turn * lead
    return out


def _gait(script: Script, q_touch: np.ndarray, held: np.ndarray, first_first: bool) -> None:
    """Each finger in turn lifts just clear of the object, stays clear a moment and presses
    again, the first finger first (``first_first``) or last."""
    for flexion in _FINGER_FLEXION if first_first else _FINGER_FLEXION[::-1]:
        lifted = script.q.copy()
        lifted[list(flexion)] = q_touch[list(flexion)] - _CLEAR
        script.move("gait", lifted, 0.35)
        script.hold("gait", 0.35)
        pressed = lifted.copy()
        pressed[list(flexion)] = held[list(flexion)]
        script.move("gait", pressed, 0.35)
        script.hold("gait", 0.2)


def _carry(script: Script, rng: np.random.Generator) -> None:
    """A quick move and back: the object lags behind and slips."""
    angle = rng.uniform(0.0, 2.0 * math.pi)
    there = script.q.copy()
    there[:2] += 0.04 * np.array([math.cos(angle), math.sin(angle)])
    back = script.q.copy()
    script.move("carry", there, 0.8)
    script.hold("carry", 0.3)
    script.move("carry", back, 0.8)

"""The accuracy benchmark's suites: which demos, how the truth's physics and sensors differ from
the tracker's, and the levels the paper varies."""

from __future__ import annotations

from dataclasses import dataclass, replace

from inhand_tracker.client.replay import NOISE_LEVELS
from inhand_tracker.service.paths import CONFIG_DIR
from inhand_tracker.sim_backend import HandSpec, Kinematics, PopulationConfig, RobotSpec, load_robot

from .allegro_motions import ALLEGRO_MOTION_KINDS
from .demos import DEMO_KINDS
from .motions import MOTION_KINDS
from .scene_truth import (
    ALLEGRO_PALM_BLOCK,
    ALLEGRO_PALM_BLOCK_TIPS,
    ALLEGRO_PALM_GRID_BLOCK,
    MANIPULATE_BLOCK,
    MANIPULATE_BLOCK_TIPS,
    MANIPULATE_EGG,
    MANIPULATE_EGG_TIPS,
    MANIPULATE_PEN,
    MANIPULATE_PEN_TIPS,
    SceneFile,
)
from .shadow_motions import SHADOW_MOTION_KINDS

__all__ = [
    "EXPLORATION",
    "K_ABLATION",
    "NOISE_LEVELS",
    "SUITES",
    "PhysicsGap",
    "SensorNoise",
    "Suite",
    "robot_spec",
]

EXPLORATION: dict[str, float] = {"low": 0.25, "med": 1.0, "high": 4.0}
"""Exploration levels of the ablation: multipliers on the parameter and wrench noise."""
K_ABLATION = (10, 40, 160, 640, 2560)


@dataclass(frozen=True)
class PhysicsGap:
    """How the ground truth's physics differs from the tracker's."""

    substeps: int = PopulationConfig.substeps
    """Truth substeps per frame (by default the tracker's)."""
    object_scale: float = 1.0
    """Truth object size relative to the tracker's model."""
    finger_damping: float = 1.0
    """Truth finger joint damping relative to the tracker's model."""
    servo_scale: float = 1.0
    """Truth servos' gain, damping and effort limit relative to the robot config's: servos the
    config does not know, what a calibration recovers."""
    impratio: float | None = None
    """Truth friction-to-normal impedance ratio: how stiffly contacts resist sliding (None: the
    robot's, as the tracker's)."""
    ramp_targets: bool = True
    """The truth's position controllers move each target across the frame, as real ones interpolate."""


@dataclass(frozen=True)
class SensorNoise:
    """What real sensors add to the robot's frames."""

    joint_sigma: float = 0.0
    """Joint encoder noise, standard deviation [rad] (and [m] for the wrist slides)."""
    force_sigma: float = 0.0
    """Fingertip force noise, standard deviation per axis [N]."""
    force_bias: float = 0.0
    """Fingertip force bias, standard deviation per sensor and axis, fixed per track [N]."""
    slip_miss: float = 0.0
    """Fraction of slip events the slip detector misses."""
    touch_sigma: float = 0.0
    """Touch-zone noise while pressed, standard deviation [N]."""
    touch_deadband: float = 0.0
    """A touch zone reads 0 under this force [N]."""


@dataclass(frozen=True)
class Suite:
    name: str
    objects: tuple[str, ...]
    kinds: tuple[str, ...]
    variants: int
    """Demos per object and kind."""
    seconds: float
    """About how long each demo lasts [s]."""
    pace: float = 1.0
    gap: PhysicsGap = PhysicsGap()
    sensors: SensorNoise = SensorNoise()
    seed: int = 0
    engine: str = "newton"
    """What records the truth: "newton" (the tracker's own simulator, the demos), "mujoco"
    (MuJoCo C from the robot's MJCF, the motions of :mod:`.motions`) or "scene" (MuJoCo C from a
    scene file someone else wrote: :attr:`scene`)."""
    scene: SceneFile | None = None
    """The scene file of an engine "scene" suite: robot, object and physics as its authors ship them."""
    drop: bool = False
    """The object slips out of the hand in the middle of the first carry, a drop that the robot
    did not command and the tracker is not told of (its friction falls to 0.02 in the truth). Its
    frame is in each trajectory's ``meta["drop_frame"]``."""
    robot: str = HandSpec().name
    """The robot config (``configs/robots/NAME.toml``) the truth is recorded with and the tracker
    runs: the procedural hand's suites pick up and carry, the Shadow Hand's carry on the palm."""

    def short(self) -> Suite:
        """The suite in short form (one object, two kinds, 10 s tracks): a check that runs on a CPU."""
        return replace(
            self, name=f"{self.name}-short", objects=self.objects[:1], kinds=self.kinds[:2], variants=1,
            seconds=min(self.seconds, 10.0),
        )  # fmt: skip


_REAL_SENSORS = SensorNoise(
    joint_sigma=0.005, force_sigma=0.05, force_bias=0.05, slip_miss=0.2, touch_sigma=0.05, touch_deadband=0.1
)
"""What the suites that stand in for a real robot add to its sensing."""

_SHADOW_OBJECTS = ("spam_can", "foam_brick")
"""What the Shadow Hand's suites carry on the palm (the banana rolls off an open palm)."""

_EGG_KINDS = tuple(k for k in SHADOW_MOTION_KINDS if k != "cup")
"""The palm motions the egg stays on the hand through (it rolls out of a cupping hand whatever its physics)."""


def _on_scene(
    name: str, scene: SceneFile, robot: str, kinds: tuple[str, ...], obj: str = "block", gap: PhysicsGap = PhysicsGap()
) -> Suite:
    """A suite on a scene file someone else wrote: one ``obj`` in ``scene`` (the truth, in MuJoCo C
    as its authors ship it), the ``robot`` config with a real robot's sensor noise, 15 s tracks."""
    return Suite(
        name, (obj,), kinds, 1, seconds=15.0, gap=gap, sensors=_REAL_SENSORS, engine="scene", scene=scene, robot=robot
    )


SUITES: dict[str, Suite] = {
    "smoke": Suite("smoke", ("foam_brick",), ("pick_place",), 2, seconds=10.0, pace=0.7),
    "paper": Suite("paper", ("spam_can", "foam_brick", "toy_banana"), DEMO_KINDS, 2, seconds=60.0),
    "reality-gap": Suite(
        "reality-gap",
        ("spam_can", "foam_brick", "toy_banana"),
        DEMO_KINDS,
        1,
        seconds=30.0,
        gap=PhysicsGap(substeps=32, object_scale=1.03, finger_damping=2.0, impratio=3.0),
        sensors=_REAL_SENSORS,
    ),
    "loss": Suite("loss", ("spam_can", "foam_brick", "toy_banana"), ("pick_place",), 2, seconds=20.0, drop=True),
    "cross-engine": Suite(
        "cross-engine",
        ("spam_can", "foam_brick", "toy_banana"),
        MOTION_KINDS,
        1,
        seconds=20.0,
        sensors=_REAL_SENSORS,
        engine="mujoco",
    ),
    "paper-shadow": Suite("paper-shadow", _SHADOW_OBJECTS, SHADOW_MOTION_KINDS, 1, seconds=20.0, robot="shadow_hand"),
    "reality-gap-shadow": Suite(
        "reality-gap-shadow",
        _SHADOW_OBJECTS,
        SHADOW_MOTION_KINDS,
        1,
        seconds=20.0,
        gap=PhysicsGap(substeps=32, object_scale=1.03, finger_damping=2.0, impratio=3.0),
        sensors=_REAL_SENSORS,
        robot="shadow_hand",
    ),
    "manipulate": _on_scene("manipulate", MANIPULATE_BLOCK, "shadow_touch", SHADOW_MOTION_KINDS),
    "manipulate-fingertips": _on_scene(
        "manipulate-fingertips", MANIPULATE_BLOCK_TIPS, "shadow_hand", SHADOW_MOTION_KINDS
    ),
    "manipulate-egg": _on_scene("manipulate-egg", MANIPULATE_EGG, "shadow_touch", _EGG_KINDS, "egg"),
    "manipulate-egg-fingertips": _on_scene(
        "manipulate-egg-fingertips", MANIPULATE_EGG_TIPS, "shadow_hand", _EGG_KINDS, "egg"
    ),
    "manipulate-pen": _on_scene("manipulate-pen", MANIPULATE_PEN, "shadow_touch", SHADOW_MOTION_KINDS, "pen"),
    "manipulate-pen-fingertips": _on_scene(
        "manipulate-pen-fingertips", MANIPULATE_PEN_TIPS, "shadow_hand", SHADOW_MOTION_KINDS, "pen"
    ),
    "allegro-palm": _on_scene("allegro-palm", ALLEGRO_PALM_BLOCK, "allegro_palm", ALLEGRO_MOTION_KINDS),
    "allegro-palm-grid": _on_scene(
        "allegro-palm-grid", ALLEGRO_PALM_GRID_BLOCK, "allegro_palm_grid", ALLEGRO_MOTION_KINDS
    ),
    "allegro-palm-fingertips": _on_scene(
        "allegro-palm-fingertips", ALLEGRO_PALM_BLOCK_TIPS, "allegro_palm_tips", ALLEGRO_MOTION_KINDS
    ),
    "allegro-palm-weak": _on_scene(
        "allegro-palm-weak", ALLEGRO_PALM_BLOCK, "allegro_palm", ALLEGRO_MOTION_KINDS, gap=PhysicsGap(servo_scale=0.5)
    ),
    "cross-engine-shadow": Suite(
        "cross-engine-shadow",
        _SHADOW_OBJECTS,
        SHADOW_MOTION_KINDS,
        1,
        seconds=20.0,
        sensors=_REAL_SENSORS,
        engine="mujoco",
        robot="shadow_hand",
    ),
}


def robot_spec(name: str, finger_damping: float = 1.0, servo_scale: float = 1.0) -> RobotSpec:
    """The robot called ``name``: the procedural hand, or a robot config of ``configs/robots``;
    ``finger_damping`` scales its fingers' damping and ``servo_scale`` its fingers' servos (gain,
    damping and effort limit): a truth's physics gap. A robot from a file has all its joints' servos
    scaled, not the damping its file gives them."""
    if name == HandSpec().name:
        hand = HandSpec()
        return HandSpec(
            finger_ke=hand.finger_ke * servo_scale, finger_kd=hand.finger_kd * finger_damping * servo_scale,
            finger_effort=hand.finger_effort * servo_scale,
        )  # fmt: skip
    spec = load_robot(CONFIG_DIR / "robots" / f"{name}.toml")
    if finger_damping == 1.0 and servo_scale == 1.0:
        return spec
    # A robot from a file does not tell its fingers' joints from the others: all its servos (its
    # config's, or its file's actuators') are scaled.
    servos = Kinematics(spec).servos()
    scaled = lambda name, by: tuple(float(x) * by for x in servos[name])  # noqa: E731
    return replace(
        spec, ke=scaled("ke", servo_scale), kd=scaled("kd", finger_damping * servo_scale),
        effort=scaled("effort", servo_scale),
    )  # fmt: skip

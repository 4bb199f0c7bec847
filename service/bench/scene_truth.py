"""Ground truth from a scene someone else wrote: an MJCF that holds the robot, the object and
their physics as its authors ship them, run in MuJoCo C. Nothing of it passes through this
project's model building: the hand's mount, its actuators, the object, the contact settings and
the touch sensors are the file's own, and only the tracker's robot config says how its joints and
touch zones are named there.

The scene's touch sensors are read as the robot's touch array (MuJoCo's touch sensor: the normal
force of the contacts inside its site), one per touch zone of the tracker's robot, matched by
site name.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np

from inhand_tracker.service.paths import CONFIG_DIR
from inhand_tracker.sim_backend.robot_files import python_package_path
from inhand_tracker.sim_backend.robot_specs import RobotLayout

from .mujoco_truth import MujocoScene

__all__ = [
    "ALLEGRO_PALM_BLOCK",
    "ALLEGRO_PALM_BLOCK_TIPS",
    "ALLEGRO_PALM_GRID_BLOCK",
    "MANIPULATE_BLOCK",
    "MANIPULATE_BLOCK_TIPS",
    "MANIPULATE_EGG",
    "MANIPULATE_EGG_TIPS",
    "MANIPULATE_PEN",
    "MANIPULATE_PEN_TIPS",
    "SceneFile",
    "load_scene",
]


@dataclass(frozen=True)
class SceneFile:
    """A scene file and what the truth needs to know of it."""

    path: str
    """The MJCF, a path or ``python://PACKAGE/...``."""
    object_body: str
    """The body of the object the robot handles."""
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where the tracker's world origin lies in the scene's world [m] (the robot config's ``base``
    moves the same mount there)."""
    fingertip_forces: bool = False
    """The robot feels the forces on its fingertips (its config's ``sensor_links``), as the contact
    forces on the scene's links of those names; else it feels only the scene's touch sensors."""


MANIPULATE_BLOCK = SceneFile(
    "python://gymnasium_robotics/envs/assets/hand/manipulate_block_touch_sensors.xml", "object", (1.0, 1.0, 0.0)
)
"""Gymnasium-Robotics' HandManipulateBlockTouchSensors scene: the Shadow hand palm up on its mount,
the 5 cm block, its 2 ms step and solver, and 92 touch sensors over palm and phalanges."""

MANIPULATE_BLOCK_TIPS = replace(MANIPULATE_BLOCK, fingertip_forces=True)
"""The same scene felt by a hand with force sensors in its fingertips and none on its palm or
phalanges: what a Shadow hand with fingertip sensors feels of a block on its palm."""

MANIPULATE_EGG = replace(
    MANIPULATE_BLOCK, path="python://gymnasium_robotics/envs/assets/hand/manipulate_egg_touch_sensors.xml"
)
"""The package's egg scene (HandManipulateEggTouchSensors): the same hand and sensors, a 6 x 8 cm
ellipsoid that rolls."""

MANIPULATE_EGG_TIPS = replace(MANIPULATE_EGG, fingertip_forces=True)
"""The egg felt through the fingertips' force sensors alone."""

MANIPULATE_PEN = replace(
    MANIPULATE_BLOCK, path="python://gymnasium_robotics/envs/assets/hand/manipulate_pen_touch_sensors.xml"
)
"""The package's pen scene (HandManipulatePenTouchSensors): a 21.6 cm capsule 1.6 cm thick, lying
across palm and fingers."""

MANIPULATE_PEN_TIPS = replace(MANIPULATE_PEN, fingertip_forces=True)
"""The pen felt through the fingertips' force sensors alone."""

ALLEGRO_PALM_BLOCK = SceneFile(str(CONFIG_DIR / "robots" / "allegro_palm_scene.xml"), "object")
"""The Allegro Hand palm up with the 5 cm block on its palm, MuJoCo's own contact model and a 2 ms
step, and a touch sensor on each of the hand's 14 touch sites (``configs/robots/allegro_palm.toml``)."""

ALLEGRO_PALM_BLOCK_TIPS = replace(ALLEGRO_PALM_BLOCK, fingertip_forces=True)
"""The same scene felt by the hand's fingertip force sensors alone (``configs/robots/allegro_palm_tips.toml``)."""

ALLEGRO_PALM_GRID_BLOCK = SceneFile(str(CONFIG_DIR / "robots" / "allegro_palm_grid_scene.xml"), "object")
"""The same scene with a touch sensor on each taxel of a 4 x 4 grid over the palm
(``configs/robots/allegro_palm_grid.toml``)."""


def _scale_servos(model: mujoco.MjModel, joints: list[int], by: float) -> None:
    """Position actuators apply kp * (ctrl - q) - kv * qdot within their force range (gainprm[0] =
    kp, biasprm[1] = -kp, biasprm[2] = -kv): all scaled, with the joints' passive damping."""
    model.actuator_gainprm[:, 0] *= by
    model.actuator_biasprm[:, 1:3] *= by
    model.actuator_forcerange[:] *= by
    model.dof_damping[model.jnt_dofadr[joints]] *= by


def load_scene(scene: SceneFile, layout: RobotLayout, nominal_mass: float, servo_scale: float = 1.0) -> MujocoScene:
    """``scene`` in MuJoCo C, with the tracker's robot ``layout`` found in it by name: its joints,
    the joint each actuator drives, the touch sensor on each touch zone's site, and (where the
    scene says the robot feels them) the link of each fingertip force sensor. A ValueError names
    what the scene lacks. ``servo_scale`` scales the robot's position servos (gain, force range)
    and its joints' damping: servos other than the scene's authors wrote."""
    path = Path(python_package_path(scene.path))
    model = mujoco.MjModel.from_xml_path(str(path))

    def find(kind: mujoco.mjtObj, name: str, what: str) -> int:
        i = mujoco.mj_name2id(model, kind, name)
        if i < 0:
            raise ValueError(f"scene '{path.name}': no {what} '{name}' (the robot config '{layout.name}' names it)")
        return i

    joints = [find(mujoco.mjtObj.mjOBJ_JOINT, n, "joint") for n in layout.joint_names]
    qpos = np.array([model.jnt_qposadr[j] for j in joints])
    index = {j: d for d, j in enumerate(joints)}
    actuator_joint = []
    for a in range(model.nu):
        j = int(model.actuator_trnid[a, 0])
        if model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT or j not in index:
            raise ValueError(f"scene '{path.name}': actuator '{model.actuator(a).name}' drives no joint of the robot")
        actuator_joint.append(index[j])
    if servo_scale != 1.0:
        _scale_servos(model, joints, servo_scale)
    touch_of_site = {
        int(model.sensor_objid[s]): int(model.sensor_adr[s])
        for s in range(model.nsensor)
        if model.sensor_type[s] == mujoco.mjtSensor.mjSENS_TOUCH
    }
    sites = [find(mujoco.mjtObj.mjOBJ_SITE, n, "site") for n in layout.zone_names]
    missing = [n for n, s in zip(layout.zone_names, sites, strict=True) if s not in touch_of_site]
    if missing:
        raise ValueError(f"scene '{path.name}': no touch sensor on the sites {missing}")
    body = find(mujoco.mjtObj.mjOBJ_BODY, scene.object_body, "body")
    if scene.fingertip_forces:
        tips = np.array([find(mujoco.mjtObj.mjOBJ_BODY, n, "link") for n in layout.sensor_names], np.int64)
        offsets = np.asarray(layout.sensor_offsets, np.float64).reshape(-1, 7)
    else:  # a robot that reads the scene's touch sensors feels no fingertip forces
        tips, offsets = np.zeros(0, np.int64), np.zeros((0, 7))
    return MujocoScene(
        model=model,
        xml=path,
        qpos=qpos,
        actuator_joint=np.array(actuator_joint),
        object_body=body,
        object_qpos=int(model.jnt_qposadr[model.body_jntadr[body]]),
        sensor_bodies=tips,
        sensor_offsets=offsets,
        nominal_mass=nominal_mass,
        touch_sensors=np.array([touch_of_site[s] for s in sites], np.int64),
        origin=np.asarray(scene.origin, np.float64),
    )

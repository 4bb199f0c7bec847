"""Ground truth from another physics engine: the robot and object written out as MJCF and run in
MuJoCo C (the ``mujoco`` package), one track at a time on the CPU.

The tracker simulates with Newton's collision pipeline feeding MuJoCo-Warp at a few milliseconds
per substep, targets held for the frame. This truth differs the way a real robot would: MuJoCo's
own collision detection, a 1 ms step, and each frame's joint targets ramped across the frame as a
real position controller interpolates its commands. What the robot senses is read from MuJoCo's
contacts with the same conventions as :mod:`sim_backend.observe` (force of the object on each pad
in the sensor frame, force-weighted slip and spin against thresholds).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import newton
import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from inhand_tracker.protocol import SENSING
from inhand_tracker.sim_backend import PopulationConfig, RobotSpec, observe
from inhand_tracker.sim_backend.build import build_model, margins_said, resolve_physics
from inhand_tracker.sim_backend.objects import ObjectSpec

from .demos import FRAME_RATE, Demo
from .recorder import Recording

__all__ = ["MujocoScene", "export_scene", "record_mujoco"]

log = logging.getLogger(__name__)

STEP = 0.001
"""MuJoCo's time step [s]."""


@dataclass
class MujocoScene:
    """The robot and object as a MuJoCo C model, and where the robot's parts live in it."""

    model: mujoco.MjModel
    xml: Path
    """The MJCF file the model was loaded from."""
    qpos: np.ndarray
    """qpos address of each actuated joint, (D,)."""
    actuator_joint: np.ndarray
    """Which actuated joint each actuator drives, (nu,)."""
    object_body: int
    object_qpos: int
    """qpos address of the object's free joint (x, y, z, qw, qx, qy, qz)."""
    sensor_bodies: np.ndarray
    """MuJoCo body of each touch sensor, (L,)."""
    sensor_offsets: np.ndarray
    """Each sensor frame in its body's frame, (L, 7): position [m], quaternion (x, y, z, w)."""
    nominal_mass: float
    """The object's mass as built [kg]."""
    touch_sensors: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """sensordata address of the MuJoCo touch sensor of each touch zone, (Z,)."""
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """Where the tracker's world origin lies in the model's world [m]: a scene written by others
    places the robot where its authors chose."""


def export_scene(robot: RobotSpec, obj: ObjectSpec, xml: Path) -> MujocoScene:
    """Write ``robot`` and ``obj`` over a ground plane as MJCF to ``xml`` (Newton's MuJoCo
    converter, so both engines start from one description) and load it back into MuJoCo C."""
    cpu = wp.get_device("cpu")
    config = PopulationConfig(groups=1, worlds=1, device="cpu")
    built = build_model(robot, obj, config, cpu)
    config = resolve_physics(robot, config, built.layout)
    xml.parent.mkdir(parents=True, exist_ok=True)
    with wp.ScopedDevice(cpu), margins_said():
        solver = newton.solvers.SolverMuJoCo(
            built.model,
            use_mujoco_cpu=True,
            use_mujoco_contacts=True,
            save_to_mjcf=str(xml),
            solver="newton",
            integrator=config.integrator,
            cone=config.cone,
            impratio=config.impratio,
            iterations=100,
            ls_iterations=50,
        )
    written = solver.mj_model
    model = mujoco.MjModel.from_xml_path(str(xml))
    if (model.nbody, model.njnt, model.nu) != (written.nbody, written.njnt, written.nu):
        raise RuntimeError(f"{xml}: the MJCF read back differs from the model written")
    model.opt.timestep = STEP
    body_of = {int(n): b for b, n in enumerate(solver.mjc_body_to_newton.numpy()[0]) if n >= 0}
    q_start, qd_start = built.model.joint_q_start.numpy(), built.model.joint_qd_start.numpy()
    joint_to_newton = solver.mjc_jnt_to_newton_jnt.numpy()[0]
    joint_to_dof = solver.mjc_jnt_to_newton_dof.numpy()[0]
    # A Newton joint of several axes (the wrist's D6) becomes one MuJoCo joint per axis.
    qpos_of_coord = {
        int(q_start[n] + joint_to_dof[j] - qd_start[n]): int(model.jnt_qposadr[j])
        for j, n in enumerate(joint_to_newton)
        if n >= 0
    }
    lay = built.layout
    qpos = np.array([qpos_of_coord[int(c)] for c in lay.coord_indices])
    d_of_qpos = {int(a): d for d, a in enumerate(qpos)}
    actuator_joint = np.array([d_of_qpos[int(model.jnt_qposadr[model.actuator_trnid[a, 0]])] for a in range(model.nu)])
    object_body = body_of[built.object_body]
    free = int(model.body_jntadr[object_body])
    return MujocoScene(
        model=model,
        xml=xml,
        qpos=qpos,
        actuator_joint=actuator_joint,
        object_body=object_body,
        object_qpos=int(model.jnt_qposadr[free]),
        sensor_bodies=np.array([body_of[int(b)] for b in lay.sensor_bodies]),
        sensor_offsets=np.asarray(lay.sensor_offsets, np.float64),
        nominal_mass=built.nominal_mass,
    )


def record_mujoco(
    scene: MujocoScene,
    demo: Demo,
    mass: float,
    friction: float,
    slip_speed: float = PopulationConfig.slip_speed,
    spin_speed: float = PopulationConfig.spin_speed,
) -> Recording:
    """Run ``demo`` in MuJoCo C with hidden ``mass`` [kg] and ``friction``; one track, (F, 1, ...)."""
    m = scene.model
    body_mass, body_inertia, geom_friction = m.body_mass.copy(), m.body_inertia.copy(), m.geom_friction.copy()
    try:
        b = scene.object_body
        m.body_inertia[b] *= mass / m.body_mass[b]
        m.body_mass[b] = mass
        m.geom_friction[m.geom_bodyid == b, 0] = friction
        return _run(scene, demo, slip_speed, spin_speed, mass, friction)
    finally:
        m.body_mass[:], m.body_inertia[:], m.geom_friction[:] = body_mass, body_inertia, geom_friction


def _run(
    scene: MujocoScene, demo: Demo, slip_speed: float, spin_speed: float, mass: float, friction: float
) -> Recording:
    m = scene.model
    d = mujoco.MjData(m)
    d.qpos[scene.qpos] = demo.q
    p = demo.object_pose.astype(np.float64)
    d.qpos[scene.object_qpos : scene.object_qpos + 7] = [*(p[:3] + scene.origin), p[6], *p[3:6]]
    d.ctrl[:] = demo.q[scene.actuator_joint]
    mujoco.mj_forward(m, d)
    steps = round(1.0 / (FRAME_RATE * m.opt.timestep))  # the model's own step, as near as the rate allows
    m.opt.timestep = 1.0 / (FRAME_RATE * steps)
    sensing = {f.name: [] for f in SENSING if f.name != "controls"}
    poses = []
    last = demo.q.astype(np.float64)
    for u in demo.controls.astype(np.float64):
        for i in range(steps):
            d.ctrl[:] = (last + (i + 1) / steps * (u - last))[scene.actuator_joint]
            mujoco.mj_step(m, d)
        last = u
        for name, value in _observe(scene, d, slip_speed, spin_speed).items():
            sensing[name].append(value)
        x, q = d.xpos[scene.object_body] - scene.origin, d.xquat[scene.object_body]
        poses.append([*x, q[1], q[2], q[3], q[0]])
    stack = lambda rows: np.asarray(rows, np.float32)[:, None]  # noqa: E731
    return Recording(  # a field the robot does not sense (no fingertip sensors: no forces) is None
        sensing={"controls": demo.controls[:, None], **{k: stack(v) if v else None for k, v in sensing.items()}},
        object_pose=stack(poses),
        initial_pose=demo.object_pose[None].astype(np.float32),
        initial_q=demo.q[None].astype(np.float32),
        mass=np.array([mass], np.float32),
        friction=np.array([friction], np.float32),
        lengths=np.array([demo.frames]),
        names=(demo.name,),
    )


def _observe(scene: MujocoScene, d: mujoco.MjData, slip_speed: float, spin_speed: float) -> dict[str, np.ndarray]:
    """What the robot senses now, as :mod:`sim_backend.observe` computes it for a world."""
    m = scene.model
    L = len(scene.sensor_bodies)
    joints_and_touch = {"q": d.qpos[scene.qpos].copy(), "touch": d.sensordata[scene.touch_sensors].astype(np.float32)}
    if L == 0:  # a robot without fingertip sensors senses no forces, slip or spin
        return joints_and_touch
    sensors = Rotation.from_matrix(d.xmat[scene.sensor_bodies].reshape(-1, 3, 3)) * Rotation.from_quat(
        scene.sensor_offsets[:, 3:]
    )  # each sensor frame in the world (scipy's quaternions are (x, y, z, w), as ours)
    force, slip_acc, spin_acc, weight = np.zeros((L, 3)), np.zeros((L, 3)), np.zeros((L, 3)), np.zeros(L)
    row = {int(b): l for l, b in enumerate(scene.sensor_bodies)}
    f6, vel = np.zeros(6), np.zeros((2, 6))
    for i in range(d.ncon):
        c = d.contact[i]
        b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
        if b1 in row and b2 == scene.object_body:
            sensor, sign = b1, -1.0  # MuJoCo's contact force acts on geom2; the pad is geom1
        elif b2 in row and b1 == scene.object_body:
            sensor, sign = b2, 1.0
        else:
            continue
        mujoco.mj_contactForce(m, d, i, f6)
        frame = c.frame.reshape(3, 3)
        f = sign * (frame.T @ f6[:3])
        w = float(np.linalg.norm(f))
        if w == 0.0:
            continue
        at_point = []
        for k, body in enumerate((sensor, scene.object_body)):
            # velocity at the body's frame origin, world orientation: (angular, linear)
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, body, vel[k], 0)
            at_point.append(vel[k, 3:] + np.cross(vel[k, :3], c.pos - d.xpos[body]))
        v_rel = at_point[0] - at_point[1]
        n = frame[0]
        l = row[sensor]
        force[l] += f
        slip_acc[l] += w * (v_rel - np.dot(v_rel, n) * n)
        spin_acc[l] += w * (vel[0, :3] - vel[1, :3])
        weight[l] += w
    to_sensor = sensors.inv()
    forces, sliding, turning = (to_sensor.apply(v) for v in (force, slip_acc, spin_acc))
    return joints_and_touch | observe.touch_from_sums(forces, sliding, turning, weight, slip_speed, spin_speed)

"""Newton's narrow phase against MuJoCo C on one small scene (a capsule and a box resting on a
table, each tilted 2 degrees): Newton writes each touch twice where MuJoCo writes it once, which
makes the touch twice as stiff in the solver. The first test is the upstream report's reproduction
and fails once Newton stops doing it (then drop sim_backend/duplicates.py); the second checks the
workaround leaves each touch once, as MuJoCo C has it; the third steps worlds with it on."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import warp as wp

TILT = 2.0  # degrees
SCENE = f"""
<mujoco>
  <worldbody>
    <geom name="table" type="box" size="0.1 0.1 0.02" pos="0 0 -0.02"/>
    <body name="capsule" pos="0 0 0.0104" euler="0 {90 + TILT} 0">
      <freejoint/>
      <geom name="capsule" type="capsule" size="0.01 0.02" mass="0.05"/>
    </body>
    <body name="box" pos="0.05 0.05 0.0255" euler="{TILT} {TILT / 2} 0">
      <freejoint/>
      <geom name="box" type="box" size="0.025 0.025 0.025" mass="0.07"/>
    </body>
  </worldbody>
</mujoco>
"""


def _mujoco_touches() -> dict[str, int]:
    m = mujoco.MjModel.from_xml_string(SCENE)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    touches: dict[str, int] = {}
    for c in d.contact[: d.ncon]:
        if c.dist < 0:
            names = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in (c.geom1, c.geom2)}
            (name,) = names - {"table"}
            touches[name] = touches.get(name, 0) + 1
    return touches


def _newton_touches(drop: bool) -> dict[str, list[tuple[float, ...]]]:
    """Each body's touches of the table (separation < 0): its points in the body's frame [m]."""
    import newton

    from inhand_tracker.sim_backend.duplicates import drop_duplicate_contacts

    with wp.ScopedDevice("cpu"):
        builder = newton.ModelBuilder()
        builder.add_mjcf(SCENE)
        builder.rigid_gap = 0.005
        model = builder.finalize(device="cpu")
        state = model.state()
        newton.eval_fk(model, model.joint_q, model.joint_qd, state)
        pipeline = newton.CollisionPipeline(model)
        contacts = pipeline.contacts()
        pipeline.collide(state, contacts)
        if drop:
            drop_duplicate_contacts(contacts)
    c = contacts
    n = int(c.rigid_contact_count.numpy()[0])
    s0, s1 = c.rigid_contact_shape0.numpy()[:n], c.rigid_contact_shape1.numpy()[:n]
    p0, p1, normal = (a.numpy()[:n] for a in (c.rigid_contact_point0, c.rigid_contact_point1, c.rigid_contact_normal))
    margin = c.rigid_contact_margin0.numpy()[:n] + c.rigid_contact_margin1.numpy()[:n]
    body_q, shape_body = state.body_q.numpy(), model.shape_body.numpy()

    def world(point: np.ndarray, shape: int) -> np.ndarray:
        if shape_body[shape] < 0:
            return point
        t = body_q[shape_body[shape]]
        return np.array(wp.transform_point(wp.transform(wp.vec3(*t[:3]), wp.quat(*t[3:])), wp.vec3(*point)))

    touches: dict[str, list[tuple[float, ...]]] = {}
    for i in range(n):
        separation = float(np.dot(normal[i], world(p1[i], s1[i]) - world(p0[i], s0[i])) - margin[i])
        if separation < 0:
            mover = s0[i] if shape_body[s0[i]] >= 0 else s1[i]
            name = model.shape_label[mover].rsplit("/", 1)[-1]
            touches.setdefault(name, []).append((*p0[i], *p1[i]))
    return touches


def test_newton_writes_a_touch_twice_where_mujoco_writes_it_once():
    assert _mujoco_touches() == {"capsule": 1, "box": 1}
    touches = _newton_touches(drop=False)

    def copies(points: list[tuple[float, ...]]) -> int:  # points with an earlier one within 10 um
        a = np.array(points)
        return sum(bool((np.abs(a[:i] - a[i]).max(axis=1) < 1e-5).any()) for i in range(1, len(a)))

    twice = {name: len(points) for name, points in touches.items() if copies(points)}
    assert twice, f"Newton writes each touch once now ({touches}): sim_backend/duplicates.py can go"
    assert twice == {"capsule": 2, "box": 2}, touches


def test_dropping_the_copies_leaves_each_touch_once_as_mujoco_has_it():
    touches = _newton_touches(drop=True)
    assert {name: len(points) for name, points in touches.items()} == _mujoco_touches()


@pytest.mark.parametrize("drop", [False, True])
def test_worlds_step_with_the_copies_dropped(drop):
    """The setting inside a population's captured frame graph: the worlds step and sense."""
    from inhand_tracker.service.paths import CONFIG_DIR
    from inhand_tracker.sim_backend import Population, PopulationConfig, load_catalog, load_robot

    robot = load_robot(CONFIG_DIR / "robots/allegro.toml")
    config = PopulationConfig(worlds=2, device="cpu", drop_duplicate_contacts=drop)
    pop = Population(robot, load_catalog()["foam_brick"], config)
    pop.reset_state()
    for _ in range(3):
        pop.step()
    assert np.isfinite(pop.obs.force.cpu().numpy()).all()


def test_the_setting_is_said_unused_where_the_worlds_collide_as_mujoco_does(caplog):
    """A robot from an MJCF collides with MuJoCo-Warp's own collision, which writes no copies: the
    setting would do nothing there, and the service says so rather than take it silently."""
    from inhand_tracker.service.paths import CONFIG_DIR
    from inhand_tracker.sim_backend import Population, PopulationConfig, load_catalog, load_robot

    robot = load_robot(CONFIG_DIR / "robots/allegro_palm.toml")
    config = PopulationConfig(worlds=1, device="cpu", use_graph=False, drop_duplicate_contacts=True)
    with caplog.at_level("WARNING"):
        pop = Population(robot, load_catalog()["block"], config)
    assert pop.config.collision == "mujoco"
    assert "population.drop_duplicate_contacts: not used" in caplog.text

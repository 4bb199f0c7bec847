"""Object catalog, physics from config, and objects from mesh files."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import pytest
import trimesh

from inhand_tracker.sim_backend import CATALOG, HandSpec, Population, PopulationConfig, load_catalog, load_mesh_object


def test_catalog_has_the_papers_three_objects_and_the_gym_scenes_three_with_their_physics():
    assert set(CATALOG) == {"spam_can", "foam_brick", "toy_banana", "block", "egg", "pen"}
    assert CATALOG["block"].box_half_extents == pytest.approx((0.025, 0.025, 0.025))  # a `box` entry
    # The scenes' egg and pen at their density of 1000 kg/m^3: the masses the scenes give them.
    egg, pen = CATALOG["egg"], CATALOG["pen"]
    assert egg.mesh.extents == pytest.approx([0.06, 0.06, 0.08]) and not egg.capsules  # its hull collides
    assert egg.mass == pytest.approx(1000 * 4 / 3 * np.pi * 0.03 * 0.03 * 0.04, rel=0.01)
    assert pen.capsules == ((0.0, 0.0, -0.1, 0.0, 0.0, 0.1, 0.008),)
    assert pen.mass == pytest.approx(1000 * pen.mesh.volume, rel=0.01)
    for obj in CATALOG.values():
        lo, hi = obj.mass_range
        assert 0 < lo <= obj.mass <= hi
        assert obj.mesh.is_watertight and obj.mesh.volume > 0
        # The body frame is the centre of mass.
        assert np.allclose(obj.mesh.center_mass, 0.0, atol=1e-6)
    banana = CATALOG["toy_banana"]
    assert len(banana.capsules) >= 4 and banana.mesh.extents[0] > 0.15  # long and curved
    points = banana.surface_points(1000)
    assert points.shape == (1000, 3)


def test_config_overrides_physics_and_adds_mesh_objects(tmp_path):
    trimesh.creation.cylinder(radius=20.0, height=60.0).export(tmp_path / "can.stl")  # millimetres
    cfg = tmp_path / "objects.toml"
    cfg.write_text(
        '[foam_brick]\nmass = 0.04\n\n[can]\nmesh = "can.stl"\nscale = 0.001\nmass = 0.2\nmass_range = [0.1, 0.3]\n'
    )
    catalog = load_catalog(cfg)
    assert catalog["foam_brick"].mass == 0.04 and catalog["foam_brick"].mass_range == (0.015, 0.05)
    can = catalog["can"]
    assert can.mesh.extents == pytest.approx([0.04, 0.04, 0.06], abs=1e-3)
    # A mesh object collides as its convex hull: dropped on the table it comes to rest on it.
    pop = Population(HandSpec(), can, PopulationConfig(worlds=1, device="cpu"))
    pop.reset_state(np.array([0.2, 0.0, 0.05, 0.0, 0.0, 0.0, 1.0]))
    for _ in range(30):
        pop.step()
    assert pop.obs.object_pose[0, 0, 2].item() == pytest.approx(0.03, abs=0.002)


@pytest.mark.parametrize(("name", "rests_at"), [("egg", 0.03), ("pen", 0.008)])
def test_an_ellipsoid_and_a_capsule_come_to_rest_on_the_table_as_their_shapes_do(name, rests_at):
    """Stood on end and let go, the egg falls over and the pen topples: each lies on its side,
    its centre its short semi-axis or its radius above the table."""
    pop = Population(HandSpec(), CATALOG[name], PopulationConfig(worlds=1, device="cpu"))
    tilted = np.array([0.2, 0.0, 0.15, np.sin(0.3), 0.0, 0.0, np.cos(0.3)])  # 0.6 rad off upright
    pop.reset_state(tilted)
    for _ in range(90):
        pop.step()
    assert pop.obs.object_pose[0, 0, 2].item() == pytest.approx(rests_at, abs=0.003)


def test_bad_config_names_the_file_and_entry(tmp_path):
    cfg = tmp_path / "objects.toml"
    cfg.write_text("[teapot]\nmass = 0.3\n")
    no_shape = "'teapot' is not a catalog shape and has no 'box', 'ellipsoid', 'capsule' or 'mesh'"
    with pytest.raises(ValueError, match=no_shape):
        load_catalog(cfg)
    cfg.write_text("[rod]\ncapsule = [0.01, 0.1, 0.2]\nmass = 0.05\nmass_range = [0.02, 0.1]\n")
    with pytest.raises(ValueError, match=r"'rod' capsule: expected 2 sizes > 0 \[m\], got \[0.01, 0.1, 0.2\]"):
        load_catalog(cfg)
    cfg.write_text("[foam_brick]\nmass = 2.0\n")
    with pytest.raises(ValueError, match=r"object 'foam_brick' mass: need 0 < 0.015 <= 2.0 <= 0.05 kg"):
        load_catalog(cfg)
    with pytest.raises(ValueError, match="objects config: cannot read"):
        load_catalog(tmp_path / "missing.toml")


def test_a_mesh_object_is_refused_when_its_volume_or_mass_cannot_be_right(tmp_path):
    box = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    open_box = box.copy()
    open_box.update_faces(np.arange(len(box.faces)) > 1)  # one side missing: not watertight
    open_box.export(tmp_path / "open.stl")
    with pytest.raises(ValueError, match=r"object 'cup' mesh: '.*open.stl' is not watertight"):
        load_mesh_object("cup", str(tmp_path / "open.stl"), mass=0.1, mass_range=(0.05, 0.2))
    box.export(tmp_path / "box.stl")
    with pytest.raises(ValueError, match=r"object 'lead' mass: 5.0 kg in the 125 cm\^3 .* is 4e\+04 kg/m\^3, outside"):
        load_mesh_object("lead", str(tmp_path / "box.stl"), mass=5.0, mass_range=(1.0, 6.0))


def test_a_mesh_object_in_the_default_objects_file_loads_at_import(tmp_path, monkeypatch):
    """The catalog is read when the module is imported: a mesh entry in the default file must load
    then too (the module is run as it is, with its default file pointed at one with a mesh)."""
    import inhand_tracker.sim_backend.objects as objects

    trimesh.creation.box(extents=(0.04, 0.04, 0.06)).export(tmp_path / "block.stl")
    cfg = tmp_path / "objects.toml"
    cfg.write_text('[block]\nmesh = "block.stl"\nmass = 0.1\nmass_range = [0.05, 0.2]\n')
    source = Path(objects.__file__).read_text()
    line = next(x for x in source.splitlines() if x.startswith("DEFAULT_CONFIG = "))
    module = types.ModuleType("objects_with_a_mesh")
    module.__file__ = objects.__file__
    monkeypatch.setitem(sys.modules, module.__name__, module)  # dataclasses look their module up
    exec(compile(source.replace(line, f"DEFAULT_CONFIG = Path({str(cfg)!r})"), objects.__file__, "exec"), vars(module))
    assert "block" in module.CATALOG


_BLOCK = "[block]\nbox = [0.05, 0.05, 0.05]\nmass = 0.07\nmass_range = [0.04, 0.12]\n"


def test_an_object_s_contact_dimension_torsional_friction_and_damping_reach_its_worlds(tmp_path):
    """A box that resists a twist on a palm (MuJoCo's condim 4), and the damping a scene gives its
    object's free joint, are said in the objects file; the worlds' solver gives the object's contacts
    that dimension (the object's priority rules them) and its six degrees of freedom that damping."""
    objects = tmp_path / "objects.toml"
    objects.write_text(_BLOCK + "condim = 4\ntorsional_friction = 0.01\ndamping = 0.02\n")
    block = load_catalog(objects)["block"]
    assert (block.condim, block.torsional_friction, block.damping) == (4, 0.01, 0.02)
    shipped = CATALOG["block"]  # gymnasium-robotics' block scenes' own: condim 4, free joint damping 0.01
    assert (shipped.condim, shipped.torsional_friction, shipped.damping) == (4, 0.005, 0.01)
    assert CATALOG["foam_brick"].damping == 0.0
    pop = Population(HandSpec(), block, PopulationConfig(worlds=2, device="cpu", use_graph=False))
    geom_condim = pop.solver.mjw_model.geom_condim.numpy()
    assert geom_condim.max() == 4 and (geom_condim == 4).sum() == 1  # the block's shape alone
    damping = pop.solver.mjw_model.dof_damping.numpy()
    assert np.allclose(damping[:, -6:], 0.02) and not np.isclose(damping[:, :-6], 0.02).any()  # its free joint's alone
    for entry, words in [("condim = 5", "condim: expected 1, 3, 4 or 6, got 5"),
                         ("damping = -1.0", "damping: expected >= 0 N s/m, got -1.0")]:  # fmt: skip
        bad = tmp_path / "bad.toml"
        bad.write_text(_BLOCK + entry + "\n")
        with pytest.raises(ValueError, match=f"object 'block' {words}"):
            load_catalog(bad)

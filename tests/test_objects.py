"""Object catalog, physics from config, and objects from mesh files."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sim_backend import CATALOG, HandSpec, Population, PopulationConfig, load_catalog


def test_catalog_has_the_papers_three_objects_with_their_physics():
    assert set(CATALOG) == {"spam_can", "foam_brick", "toy_banana"}
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


def test_bad_config_names_the_file_and_entry(tmp_path):
    cfg = tmp_path / "objects.toml"
    cfg.write_text("[teapot]\nmass = 0.3\n")
    with pytest.raises(ValueError, match="'teapot' is not a catalog shape and has no 'mesh'"):
        load_catalog(cfg)
    cfg.write_text("[foam_brick]\nmass = 2.0\n")
    with pytest.raises(ValueError, match=r"object 'foam_brick' mass: need 0 < 0.015 <= 2.0 <= 0.05 kg"):
        load_catalog(cfg)
    with pytest.raises(ValueError, match="objects config: cannot read"):
        load_catalog(tmp_path / "missing.toml")

"""Objects: a catalog shaped like the paper's YCB objects, and any mesh file trimesh reads.

Every object is a surface mesh (used for ADD points and for viewing) plus a collision shape made
of convex primitives, which the collision pipeline handles analytically and fast: a box, a chain
of capsules (the banana), or the convex hull of a user's mesh. Colliding as a raw triangle mesh
gave hundreds of contacts per world and lost the grasp. The body frame is the centre of mass.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh

__all__ = [
    "CATALOG",
    "DEFAULT_CONFIG",
    "ObjectSpec",
    "catalog_object",
    "load_catalog",
    "load_mesh_object",
    "make_banana",
]

_ROOT = Path(__file__).resolve().parents[1]
if not (_ROOT / "configs").is_dir():  # an installed wheel carries configs/ in the service package
    _ROOT = _ROOT / "service" / "bundled"
DEFAULT_CONFIG = _ROOT / "configs" / "objects.toml"
"""Where the objects' physics (mass, friction and their ranges) are configured."""
_DENSITY = (5.0, 25000.0)
"""Plausible densities of a held object [kg/m^3]: expanded polystyrene to the densest metals."""


@dataclass(frozen=True)
class ObjectSpec:
    """A graspable rigid object and the range its unknown physics may take."""

    name: str
    mesh: trimesh.Trimesh
    """Surface mesh in the body frame (origin at the centre of mass) [m]."""
    mass: float
    """Default mass [kg]."""
    mass_range: tuple[float, float]
    """Allowed mass [kg]: priors and perturbations are clipped to it."""
    friction: float = 0.8
    """Default Coulomb friction coefficient against the fingertips [1]."""
    friction_range: tuple[float, float] = (0.3, 1.5)
    condim: int = 3
    """MuJoCo's contact dimension of the object's contacts: 3 sliding friction, 4 with torsional
    friction about the contact normal too (a box resisting a twist on a palm), 6 with rolling."""
    torsional_friction: float = 0.005
    """Torsional friction coefficient [m] (used with condim 4 or 6; MuJoCo's default)."""
    damping: float = 0.0
    """Viscous damping of the object's free motion, on each of its six degrees of freedom [N s/m,
    N m s/rad], as a MuJoCo free joint's ``damping``: what a scene damps its object with (the
    block scenes of gymnasium-robotics: 0.01, which on a 5 cm cube stops a spin within 3 ms)."""
    box_half_extents: tuple[float, float, float] | None = None
    """Collide as this box [m]."""
    capsules: tuple[tuple[float, ...], ...] = ()
    """Else collide as these capsules, each (x0, y0, z0, x1, y1, z1, radius) in the body frame [m];
    with neither, the mesh's convex hull."""

    def __post_init__(self) -> None:
        lo, hi = self.mass_range
        if not (0.0 < lo <= self.mass <= hi):
            raise ValueError(f"object '{self.name}' mass: need 0 < {lo} <= {self.mass} <= {hi} kg")
        lo, hi = self.friction_range
        if not (0.0 <= lo <= self.friction <= hi):
            raise ValueError(f"object '{self.name}' friction: need 0 <= {lo} <= {self.friction} <= {hi}")
        if self.condim not in (1, 3, 4, 6):
            raise ValueError(f"object '{self.name}' condim: expected 1, 3, 4 or 6, got {self.condim}")
        if not self.torsional_friction >= 0.0:
            raise ValueError(f"object '{self.name}' torsional_friction: expected >= 0 m, got {self.torsional_friction}")
        if not self.damping >= 0.0:
            raise ValueError(f"object '{self.name}' damping: expected >= 0 N s/m, got {self.damping}")

    def surface_points(self, count: int = 1024, seed: int = 0) -> np.ndarray:
        """``count`` points drawn uniformly by area over the surface, shape (count, 3) [m], for ADD."""
        points, _ = trimesh.sample.sample_surface(self.mesh, count, seed=seed)
        return np.asarray(points, dtype=np.float32)

    def scaled(self, factor: float) -> ObjectSpec:
        """The same object with every length times ``factor`` (same mass): a reality gap in size."""
        if not (0.5 <= factor <= 2.0):
            raise ValueError(f"object '{self.name}' scale: expected 0.5 to 2, got {factor}")
        mesh = self.mesh.copy()
        mesh.apply_scale(factor)
        box = None if self.box_half_extents is None else tuple(h * factor for h in self.box_half_extents)
        capsules = tuple(tuple(v * factor for v in c) for c in self.capsules)
        return replace(self, mesh=mesh, box_half_extents=box, capsules=capsules)


def make_banana(
    arc_radius: float = 0.15,
    arc_angle: float = 1.25,
    tube_radius: float = 0.018,
    rings: int = 24,
    sides: int = 16,
    segments: int = 6,
) -> tuple[trimesh.Trimesh, tuple[tuple[float, ...], ...]]:
    """A toy banana: a curved, tapered tube along a circular arc, closed at both ends, and the
    chain of ``segments`` capsules along the same arc that it collides as.

    The arc lies in the body's x-y plane, so the banana rests on its side, as a real one does. On
    its back (arc in x-z) it balanced on a rocker that the first fingertip touch tipped over: a
    micrometre at the start became 64 mm at the lift (docs/benchmarks.md)."""
    angles = np.linspace(-arc_angle / 2, arc_angle / 2, rings)
    s = np.linspace(-1.0, 1.0, rings)
    radii = tube_radius * np.sqrt(np.clip(1.0 - s**4, 0.08, None))  # blunt tapered ends
    phi = np.linspace(0.0, 2 * math.pi, sides, endpoint=False)
    verts = []
    for a, r in zip(angles, radii, strict=True):
        centre = np.array([arc_radius * math.sin(a), arc_radius * (1.0 - math.cos(a)), 0.0])
        normal = np.array([-math.sin(a), math.cos(a), 0.0])  # towards the arc's centre
        binormal = np.array([0.0, 0.0, 1.0])
        ring = centre + r * (np.cos(phi)[:, None] * normal + np.sin(phi)[:, None] * binormal)
        verts.append(ring)
    verts = np.concatenate(verts)
    faces = []
    for i in range(rings - 1):
        for j in range(sides):
            a, b = i * sides + j, i * sides + (j + 1) % sides
            c, d = a + sides, b + sides
            faces += [(a, c, b), (b, c, d)]
    tip0, tip1 = len(verts), len(verts) + 1
    verts = np.vstack([verts, verts[:sides].mean(0), verts[-sides:].mean(0)])
    last = (rings - 1) * sides
    for j in range(sides):
        faces.append((tip0, j, (j + 1) % sides))
        faces.append((tip1, last + (j + 1) % sides, last + j))
    mesh = trimesh.Trimesh(verts, np.asarray(faces), process=True)
    if mesh.volume < 0:  # outward normals, so volume and centre of mass come out right
        mesh.invert()
    com = mesh.center_mass
    mesh.apply_translation(-com)
    knots = np.linspace(-arc_angle / 2, arc_angle / 2, segments + 1)
    centres = np.stack([arc_radius * np.sin(knots), arc_radius * (1 - np.cos(knots)), 0 * knots], 1) - com
    knot_s = np.linspace(-1.0, 1.0, segments + 1)
    knot_r = tube_radius * np.sqrt(np.clip(1.0 - knot_s**4, 0.08, None))
    capsules = tuple((*centres[i], *centres[i + 1], float(min(knot_r[i], knot_r[i + 1]))) for i in range(segments))
    return mesh, capsules


def _centred(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh = mesh.copy()
    mesh.apply_translation(-mesh.center_mass if mesh.is_volume else -mesh.centroid)
    return mesh


def load_mesh_object(
    name: str,
    path: str,
    *,
    mass: float,
    mass_range: tuple[float, float],
    friction: float = 0.8,
    friction_range: tuple[float, float] = (0.3, 1.5),
    scale: float = 1.0,
) -> ObjectSpec:
    """An object from any mesh file trimesh reads (STL, OBJ, PLY, GLB, ...), in metres after ``scale``."""
    if not os.path.isfile(path):
        raise ValueError(f"object '{name}' mesh: no such file '{path}'")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for bad files
        raise ValueError(f"object '{name}' mesh: cannot read '{path}': {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"object '{name}' mesh: '{path}' holds no triangles")
    mesh.apply_scale(scale)
    extent = float(np.max(mesh.extents))
    if not (0.005 <= extent <= 0.5):
        raise ValueError(f"object '{name}' mesh: largest extent {extent:.4g} m is outside [0.005, 0.5] m; check scale")
    if not mesh.is_watertight:
        # Its volume, and so the density the physics is given, would be meaningless.
        raise ValueError(f"object '{name}' mesh: '{path}' is not watertight (its volume sets the density)")
    density = mass / abs(float(mesh.volume))
    if not (_DENSITY[0] <= density <= _DENSITY[1]):
        raise ValueError(
            f"object '{name}' mass: {mass} kg in the {abs(float(mesh.volume)) * 1e6:.4g} cm^3 of '{path}' is "
            f"{density:.4g} kg/m^3, outside [{_DENSITY[0]}, {_DENSITY[1]}]; check mass and scale"
        )
    return ObjectSpec(
        name=name,
        mesh=_centred(mesh),
        mass=mass,
        mass_range=mass_range,
        friction=friction,
        friction_range=friction_range,
    )


def _box(name: str, size: tuple[float, float, float], **kw) -> ObjectSpec:
    half = tuple(0.5 * s for s in size)
    return ObjectSpec(name=name, mesh=trimesh.creation.box(extents=size), box_half_extents=half, **kw)  # type: ignore[arg-type]


def _ellipsoid(name: str, semi_axes: tuple[float, float, float], **kw) -> ObjectSpec:
    """An ellipsoid of these semi-axes [m] (an egg), colliding as its mesh's convex hull: not every
    collision pipeline has an ellipsoid shape, and 642 vertices keep the hull's faces within 0.5 %
    of the surface (0.2 mm on the egg)."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.apply_scale(semi_axes)
    return ObjectSpec(name=name, mesh=mesh, **kw)


def _capsule(name: str, radius: float, half_length: float, **kw) -> ObjectSpec:
    """A capsule along the body's z axis (a pen): MuJoCo's ``size="radius half_length"`` [m]."""
    mesh = trimesh.creation.capsule(height=2.0 * half_length, radius=radius)
    return ObjectSpec(name=name, mesh=mesh, capsules=((0.0, 0.0, -half_length, 0.0, 0.0, half_length, radius),), **kw)


def _sizes(path: Path, name: str, key: str, value: object, count: int) -> tuple[float, ...]:
    """Entry ``name``'s ``key``: ``count`` lengths > 0 [m], else a ValueError naming them."""
    sizes = tuple(float(v) for v in value)  # type: ignore[attr-defined]
    if len(sizes) != count or min(sizes) <= 0:
        raise ValueError(f"objects config '{path}': '{name}' {key}: expected {count} sizes > 0 [m], got {list(sizes)}")
    return sizes


_BANANA_MESH, _BANANA_CAPSULES = make_banana()

# Shapes of the paper's three YCB objects; their physics comes from configs/objects.toml.
_SHAPES: dict[str, ObjectSpec] = {
    "spam_can": _box("spam_can", (0.097, 0.056, 0.082), mass=0.1, mass_range=(0.05, 0.2)),
    "foam_brick": _box("foam_brick", (0.05, 0.075, 0.05), mass=0.028, mass_range=(0.015, 0.05)),
    "toy_banana": ObjectSpec("toy_banana", _BANANA_MESH, mass=0.066, mass_range=(0.04, 0.1), capsules=_BANANA_CAPSULES),
}


def load_catalog(path: str | os.PathLike = DEFAULT_CONFIG) -> dict[str, ObjectSpec]:
    """The object catalog with physics from the TOML file at ``path`` (see configs/objects.toml)."""
    path = Path(path)
    try:
        table = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"objects config: cannot read '{path}': {exc}") from exc
    catalog = dict(_SHAPES)
    for name, entry in table.items():
        physics = {k: entry[k] for k in ("mass", "friction", "condim", "torsional_friction", "damping") if k in entry}
        physics |= {k: tuple(entry[k]) for k in ("mass_range", "friction_range") if k in entry}
        if "box" in entry:
            catalog[name] = _box(name, _sizes(path, name, "box", entry["box"], 3), **physics)  # type: ignore[arg-type]
        elif "ellipsoid" in entry:
            axes = _sizes(path, name, "ellipsoid", entry["ellipsoid"], 3)
            catalog[name] = _ellipsoid(name, axes, **physics)  # type: ignore[arg-type]
        elif "capsule" in entry:
            radius, half = _sizes(path, name, "capsule", entry["capsule"], 2)
            catalog[name] = _capsule(name, radius, half, **physics)
        elif "mesh" in entry:
            mesh_path = str(path.parent / entry["mesh"])
            catalog[name] = load_mesh_object(name, mesh_path, scale=float(entry.get("scale", 1.0)), **physics)
        elif name in catalog:
            catalog[name] = replace(catalog[name], **physics)
        else:
            shapes = "'box', 'ellipsoid', 'capsule' or 'mesh'"
            raise ValueError(f"objects config '{path}': '{name}' is not a catalog shape and has no {shapes}")
    return catalog


CATALOG: dict[str, ObjectSpec] = load_catalog() if DEFAULT_CONFIG.is_file() else dict(_SHAPES)


def catalog_object(name: str) -> ObjectSpec:
    """The catalog object ``name``; a ValueError lists the known names."""
    try:
        return CATALOG[name]
    except KeyError:
        raise ValueError(f"object: unknown name '{name}', known: {sorted(CATALOG)}") from None

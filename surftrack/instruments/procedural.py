"""Procedural part meshes for EndoWrist-style instruments, built from real dimensions (mm).

Frames follow :mod:`surftrack.instruments.kinematics`:
- shaft: origin on the wrist pitch axis (the part-frame x axis), shaft along -z behind it;
- wrist: origin on the pitch axis, the yaw axis (parallel to y) at z = ``pitch_to_yaw``;
- jaw: origin on the yaw axis, the jaw along +z to its tip; ``side`` +1 puts the jaw on the +x side of
  the closing plane x = 0 (its hub on the +y half of the yaw pin), -1 mirrors it.
The parts of one instrument are shaped so that they do not intersect anywhere within the joint limits
at non-negative jaw opening (checked in the tests). Every builder returns ``(mesh, keypoints)``.
Meshes are unions of primitives and extruded profiles through manifold3d, so they are watertight.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh
from shapely.geometry import Polygon

Keypoints = dict[str, np.ndarray]
Builder = Callable[..., tuple[trimesh.Trimesh, Keypoints]]

SECTIONS = 48  # facets around a cylinder: smooth enough for 1-px silhouettes at 640x512, ~100 mm away


def union(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.union(list(meshes), engine="manifold")


def difference(a: trimesh.Trimesh, *b: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.difference([a, *b], engine="manifold")


def intersection(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.intersection(list(meshes), engine="manifold")


def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
    """Axis-aligned box between corners ``lo`` and ``hi``."""
    lo_, hi_ = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi_ - lo_, transform=trimesh.transformations.translation_matrix((lo_ + hi_) / 2))


_AXIS_ROT = {
    "z": np.eye(4),
    "x": trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)),
    "y": trimesh.transformations.rotation_matrix(-np.pi / 2, (1, 0, 0)),
}


def cylinder(radius: float, a: float, b: float, axis: str = "z", center: tuple[float, float] = (0.0, 0.0),
             sections: int = SECTIONS) -> trimesh.Trimesh:
    """Cylinder along ``axis`` from coordinate ``a`` to ``b``; ``center`` gives the two other coordinates
    of its axis in xyz order: (x, y) for a z cylinder, (y, z) for x, (x, z) for y."""
    m = trimesh.creation.cylinder(radius=radius, height=abs(b - a), sections=sections)
    m.apply_translation((0, 0, (a + b) / 2))
    m.apply_transform(_AXIS_ROT[axis])
    off = {"z": (center[0], center[1], 0.0), "x": (0.0, center[0], center[1]), "y": (center[0], 0.0, center[1])}[axis]
    m.apply_translation(off)
    return m


def extrude_xz(points_xz: list[tuple[float, float]], y0: float, y1: float) -> trimesh.Trimesh:
    """Prism of a polygon given in the x-z plane, extruded along y from y0 to y1."""
    m = trimesh.creation.extrude_polygon(Polygon(points_xz).buffer(0), y1 - y0)
    # (a, b, e) -> (a, -e, b) is a proper rotation: x = a, z = b, y = -e in [-h, 0]; then shift to [y0, y1].
    m.apply_transform(np.array([[1, 0, 0, 0], [0, 0, -1, y1], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=float))
    return m


def extrude_yz(points_yz: list[tuple[float, float]], x0: float, x1: float) -> trimesh.Trimesh:
    """Prism of a polygon given in the y-z plane, extruded along x from x0 to x1."""
    m = trimesh.creation.extrude_polygon(Polygon(points_yz).buffer(0), x1 - x0)
    # (a, b, e) -> (e, a, b) is a cyclic permutation (a rotation): y = a, z = b, x = e.
    m.apply_transform(np.array([[0, 0, 1, x0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=float))
    return m


def mirror_x(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Mirror image through the plane x = 0 (trimesh keeps the faces outward)."""
    m = mesh.copy()
    m.apply_transform(np.diag([-1.0, 1.0, 1.0, 1.0]))
    return m


def mirror_y(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    m = mesh.copy()
    m.apply_transform(np.diag([1.0, -1.0, 1.0, 1.0]))
    return m


def finish(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Merge duplicate vertices, drop degenerate faces and fix normals; check the result is closed."""
    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True, validate=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


# --------------------------------------------------------------------------------------------------
# Shaft and wrist, shared by all wristed instruments
# --------------------------------------------------------------------------------------------------

def shaft(diameter: float = 8.0, length: float = 40.0, lug_gap: float = 4.6, lug_thickness: float = 1.4,
          lug_radius: float = 2.8) -> tuple[trimesh.Trimesh, Keypoints]:
    """Distal shaft segment: tube ending 3.5 mm before the pitch axis, two clevis lugs around the pitch
    pin (along x) and a longitudinal groove on +y that breaks the roll symmetry."""
    r = diameter / 2.0
    tube_end = -3.5
    tube = cylinder(r, -length, tube_end)
    groove = box((-0.6, r - 0.45, -length - 1), (0.6, r + 1.0, tube_end - 3.0))
    tube = difference(tube, groove)
    xa, xb = lug_gap / 2.0, lug_gap / 2.0 + lug_thickness
    lug = union(box((xa, -lug_radius, tube_end - 0.5), (xb, lug_radius, 0.0)),
                cylinder(lug_radius, xa, xb, axis="x"))
    lugs = intersection(union(lug, mirror_x(lug)), cylinder(r - 0.1, tube_end - 1.0, lug_radius + 1.0))
    pin = cylinder(0.7, -(xb + 0.25), xb + 0.25, axis="x")
    mesh = finish(union(tube, lugs, pin))
    kps = {"pitch_axis": np.zeros(3), "shaft_tip": np.array([0.0, 0.0, tube_end])}
    return mesh, kps


def wrist_clevis(diameter: float = 8.0, pitch_to_yaw: float = 9.1, knuckle_width: float = 4.4,
                 knuckle_radius: float = 2.6, hub_gap: float = 3.3, lug_thickness: float = 1.4,
                 lug_radius: float = 2.5) -> tuple[trimesh.Trimesh, Keypoints]:
    """Wrist link: a knuckle on the pitch pin, a bridge, and a clevis whose two lugs (normal to y) hold
    the yaw pin at z = ``pitch_to_yaw``."""
    d = pitch_to_yaw
    hw = knuckle_width / 2.0
    knuckle = cylinder(knuckle_radius, -hw, hw, axis="x")
    bridge = box((-hw, -knuckle_radius, 0.0), (hw, knuckle_radius, d - 3.0))
    ya, yb = hub_gap / 2.0, hub_gap / 2.0 + lug_thickness
    lug = union(box((-lug_radius, ya, d - 3.6), (lug_radius, yb, d)), cylinder(lug_radius, ya, yb, axis="y", center=(0.0, d)))
    web = box((-lug_radius, -yb, d - 3.6), (lug_radius, yb, d - 2.9))
    body = union(knuckle, bridge, lug, mirror_y(lug), web)
    body = intersection(body, cylinder(diameter / 2.0 - 0.2, -diameter, d + diameter))
    pin = cylinder(0.6, -(yb + 0.2), yb + 0.2, axis="y", center=(0.0, d))
    mesh = finish(union(body, pin))
    kps = {"pitch_axis": np.zeros(3), "yaw_axis": np.array([0.0, 0.0, d])}
    return mesh, kps


def shaft_extension(diameter: float = 8.0, start: float = -40.0, length: float = 360.0) -> tuple[trimesh.Trimesh, Keypoints]:
    """Render-only continuation of the shaft towards the trocar (not a model part); it starts 0.5 mm
    inside the shaft part so that no crack shows between the two."""
    return cylinder(diameter / 2.0 - 0.01, start - length, start + 0.5), {}


# --------------------------------------------------------------------------------------------------
# Jaws
# --------------------------------------------------------------------------------------------------

HUB_RADIUS = 1.6
HUB_HALF_WIDTH = 1.5


def hub() -> trimesh.Trimesh:
    """Half-width hub on the yaw pin (+y half) with a web to the +x jaw body. The side -1 jaw is the
    side +1 jaw turned 180 deg about z, so its hub takes the -y half and the two hubs interleave."""
    return union(cylinder(HUB_RADIUS, 0.05, HUB_HALF_WIDTH, axis="y"),
                 box((0.05, 0.05, 0.0), (HUB_RADIUS, HUB_HALF_WIDTH, HUB_RADIUS + 0.2)))


def _taper(length: float, w0: float, w1: float, z0: float = 0.0) -> trimesh.Trimesh:
    """Top-view outline: half-width w0 at z0 narrowing to w1 at the tip, extruded along x."""
    return extrude_yz([(-w0, z0), (w0, z0), (w1, length), (-w1, length)], -5.0, 5.0)


def for_side(mesh: trimesh.Trimesh, side: int) -> trimesh.Trimesh:
    """The finished jaw for ``side``: as built (+x side) for +1, turned 180 deg about z for -1."""
    if side not in (1, -1):
        raise ValueError(f"jaw side must be +1 or -1, got {side}")
    m = mesh.copy()
    if side < 0:
        m.apply_transform(np.diag([-1.0, -1.0, 1.0, 1.0]))
    return finish(m)


def jaw_needle_driver(length: float = 10.2, side: int = 1, tooth_pitch: float = 0.5,
                      tooth_depth: float = 0.25) -> tuple[trimesh.Trimesh, Keypoints]:
    """Large-needle-driver jaw: stout, tapered, with cross serrations on the gripping face."""
    z0 = HUB_RADIUS + 0.05
    n = int((length - 0.5 - z0) / tooth_pitch)
    face = []
    for i in range(n + 1):
        z = z0 + i * tooth_pitch
        face.append((0.05 + (tooth_depth if i % 2 else 0.0), z))
    profile = face + [(0.6, length), (1.3, length - 1.2), (1.8, length - 4.0), (1.9, z0 + 1.0), (1.6, z0)]
    body = extrude_xz(profile, -1.4, 1.4)
    body = intersection(body, _taper(length + 1.0, 1.45, 0.75))
    mesh = for_side(union(body, hub()), side)
    kps = {"tip": np.array([0.3 * side, 0.0, length - 0.05]), "grip_base": np.array([0.1 * side, 0.0, z0])}
    return mesh, kps


BUILDERS: dict[str, Builder] = {
    "shaft": shaft,
    "wrist_clevis": wrist_clevis,
    "shaft_extension": shaft_extension,
    "jaw_needle_driver": jaw_needle_driver,
}


def build(builder: str, **params: float) -> tuple[trimesh.Trimesh, Keypoints]:
    """Run the named builder with ``params`` (from an instrument YAML)."""
    if builder not in BUILDERS:
        raise ValueError(f"unknown mesh builder {builder!r}; available: {sorted(BUILDERS)}")
    try:
        return BUILDERS[builder](**params)
    except TypeError as e:
        raise ValueError(f"bad parameters for mesh builder {builder!r}: {e}") from None

"""Procedural part meshes for EndoWrist-style instruments, built from real dimensions (mm).

Frames follow :mod:`surftrack.instruments.kinematics`:
- shaft: origin on the wrist pitch axis (the part-frame x axis), shaft along -z behind it;
- wrist: origin on the pitch axis, the yaw axis (parallel to y) at z = ``pitch_to_yaw``;
- jaw: origin on the yaw axis, the jaw along +z to its tip; ``side`` +1 puts the jaw on the +x side of
  the closing plane x = 0 (its hub on the +y half of the yaw pin), -1 mirrors it.
The parts of one instrument are shaped so that they do not intersect anywhere within the joint limits
at non-negative jaw opening (checked in the tests): each pin belongs to the part that holds it and runs
in a bore ``PIN_CLEARANCE`` wider in the part that turns on it. Every builder returns ``(mesh, keypoints)``.
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

PITCH_PIN_RADIUS = 0.7  # pin of the shaft clevis, through the wrist knuckle
YAW_PIN_RADIUS = 0.6  # pin of the wrist clevis, through the jaw hubs
PIN_CLEARANCE = 0.05  # radial gap between a pin and the bore of the part turning on it


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
    pin = cylinder(PITCH_PIN_RADIUS, -(xb + 0.25), xb + 0.25, axis="x")
    mesh = finish(union(tube, lugs, pin))
    kps = {"pitch_axis": np.zeros(3), "shaft_tip": np.array([0.0, 0.0, tube_end])}
    return mesh, kps


def wrist_clevis(diameter: float = 8.0, pitch_to_yaw: float = 9.1, knuckle_width: float = 4.4,
                 knuckle_radius: float = 2.6, hub_gap: float = 3.3, lug_thickness: float = 1.4,
                 lug_radius: float = 2.5, slot_depth: float = 4.2) -> tuple[trimesh.Trimesh, Keypoints]:
    """Wrist link: a knuckle on the pitch pin, a bridge, and a clevis whose two lugs (normal to y) hold
    the yaw pin at z = ``pitch_to_yaw``. The slot between the lugs (|y| < ``hub_gap`` / 2) goes down to
    ``slot_depth`` below the yaw axis, so that jaws turned by up to ~125 deg (yaw + half the opening)
    swing clear of the bridge. The knuckle has a bore of radius ``PITCH_PIN_RADIUS`` +
    ``PIN_CLEARANCE`` for the shaft's pitch pin."""
    d = pitch_to_yaw
    hw = knuckle_width / 2.0
    knuckle = cylinder(knuckle_radius, -hw, hw, axis="x")
    bridge = box((-hw, -knuckle_radius, 0.0), (hw, knuckle_radius, d - 3.0))
    ya, yb = hub_gap / 2.0, hub_gap / 2.0 + lug_thickness
    lug = union(box((-lug_radius, ya, d - 3.6), (lug_radius, yb, d)), cylinder(lug_radius, ya, yb, axis="y", center=(0.0, d)))
    web = box((-lug_radius, -yb, d - 3.6), (lug_radius, yb, d - 2.9))
    body = union(knuckle, bridge, lug, mirror_y(lug), web)
    body = intersection(body, cylinder(diameter / 2.0 - 0.2, -diameter, d + diameter))
    slot = box((-diameter, -ya, d - slot_depth), (diameter, ya, d + diameter))
    body = difference(body, slot, cylinder(PITCH_PIN_RADIUS + PIN_CLEARANCE, -diameter, diameter, axis="x"))
    pin = cylinder(YAW_PIN_RADIUS, -(yb + 0.2), yb + 0.2, axis="y", center=(0.0, d))
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
    side +1 jaw turned 180 deg about z, so its hub takes the -y half and the two hubs interleave. Jaw
    builders subtract :func:`hub_bore` from the finished jaw so that the wrist's yaw pin runs free."""
    return union(cylinder(HUB_RADIUS, 0.05, HUB_HALF_WIDTH, axis="y"),
                 box((0.05, 0.05, 0.0), (HUB_RADIUS, HUB_HALF_WIDTH, HUB_RADIUS + 0.2)))


def hub_bore() -> trimesh.Trimesh:
    """The bore to subtract from a finished jaw (both hub halves): clearance around the yaw pin."""
    return cylinder(YAW_PIN_RADIUS + PIN_CLEARANCE, -HUB_HALF_WIDTH - 1.0, HUB_HALF_WIDTH + 1.0, axis="y")


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
    mesh = for_side(difference(union(body, hub()), hub_bore()), side)
    kps = {"tip": np.array([0.3 * side, 0.0, length - 0.05]), "grip_base": np.array([0.1 * side, 0.0, z0])}
    return mesh, kps


def _ellipse(cy: float, cz: float, ry: float, rz: float, n: int = 32) -> list[tuple[float, float]]:
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return list(zip(cy + ry * np.cos(t), cz + rz * np.sin(t)))


def _ellipsoid(center: tuple[float, float, float], radii: tuple[float, float, float],
               subdivisions: int = 3) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    m.apply_scale(radii)
    m.apply_translation(center)
    return m


def _rounded_outline(z0: float, length: float, w0: float, w1: float, n_arc: int = 12) -> list[tuple[float, float]]:
    """Top-view (y, z) outline: half-width w0 at z0 narrowing to w1, closed by a half-circle of radius
    w1 whose apex is at z = ``length``."""
    zc = length - w1
    arc = [(w1 * np.cos(a), zc + w1 * np.sin(a)) for a in np.linspace(0.0, np.pi, n_arc + 1)]
    return [(-w0, z0), (w0, z0), *arc]


def jaw_scissors(length: float = 9.0, side: int = 1, curve: float = 1.2, blade_width: float = 1.9,
                 thickness: float = 0.6, bevel: float = 0.3) -> tuple[trimesh.Trimesh, Keypoints]:
    """Monopolar-Curved-Scissors blade: a thin plate (thin in y) tapering to a sharp point and curved
    within the x-z plane towards +x by ``curve`` mm at the tip, with a stepped cutting-edge bevel on its
    outer face. The blades shear past each other: side +1 lies on y in [0.05, 0.05 + thickness], side -1
    is its mirror image through y = 0, so both curve the same way (as real curved scissors) and each
    cutting edge leads when closing (side +1: the -x edge). Dimensions are estimates from photographs
    (blade ~9 mm from the pivot, ~1.9 mm wide, ~1 mm tip deflection); the hub is shared with the other
    jaws."""
    z0 = HUB_RADIUS + 0.05
    zc = 2.5  # the curve starts here (estimate)
    w0 = blade_width / 2.0
    z = np.linspace(0.0, length, 28)
    t = np.clip((z - z0) / (length - z0), 0.0, 1.0)
    xc = curve * np.clip((z - zc) / (length - zc), 0.0, 1.0) ** 2
    w = w0 * (1.0 - t ** 1.6)
    y0 = 0.05
    layers = []
    n_layers = 3
    edge = -1.0 if side > 0 else 1.0  # side of the centreline (in x) that carries the cutting edge
    for k in range(n_layers):
        inset = np.minimum(bevel * k / (n_layers - 1), 0.9 * w)
        lo = xc - w + (inset if edge < 0 else 0.0)
        hi = xc + w - (inset if edge > 0 else 0.0)
        pts = list(zip(hi, z)) + list(zip(lo[::-1], z[::-1]))
        ya = y0 + thickness * k / n_layers - (0.01 if k else 0.0)
        yb = y0 + thickness * (k + 1) / n_layers
        layers.append(extrude_xz(pts, ya, yb))
    blade = union(*layers)
    if side < 0:
        blade = mirror_y(blade)
    mesh = finish(difference(union(blade, for_side(hub(), side)), hub_bore()))
    ym = side * (y0 + thickness / 2.0)
    kps = {"tip": np.array([curve, ym, length]), "blade_base": np.array([0.0, ym, z0])}
    return mesh, kps


def jaw_cadiere(length: float = 12.0, side: int = 1, ridge_pitch: float = 0.4, ridge_depth: float = 0.12,
                window_length: float = 4.8, window_width: float = 1.0) -> tuple[trimesh.Trimesh, Keypoints]:
    """Cadiere-forceps jaw: long and slender with a rounded tip, an oval window through the jaw (in x)
    and fine transverse ridges on the grip face. Width ~2.6 mm tapering to ~1.7 mm, window ~4.8 x 1 mm
    (estimates from photographs)."""
    z0 = HUB_RADIUS + 0.05
    n = int((length - 1.0 - z0) / ridge_pitch)
    face = [(0.05 + (ridge_depth if i % 2 else 0.0), z0 + i * ridge_pitch) for i in range(n + 1)]
    back = [(0.4, length), (0.65, length - 0.5), (0.8, length - 1.2), (1.0, length - 4.0),
            (1.45, z0 + 1.5), (1.5, z0 + 0.5), (1.4, z0)]
    body = extrude_xz(face + back, -1.45, 1.45)
    body = intersection(body, extrude_yz(_rounded_outline(z0 - 0.5, length, 1.3, 0.85), -5.0, 5.0))
    zw = 0.6 * length
    window = extrude_yz(_ellipse(0.0, zw, window_width / 2.0, window_length / 2.0), -1.0, 3.0)
    body = difference(body, window)
    mesh = for_side(difference(union(body, hub()), hub_bore()), side)
    kps = {"tip": np.array([0.3 * side, 0.0, length - 0.05]), "window_center": np.array([0.6 * side, 0.0, zw]),
           "grip_base": np.array([0.1 * side, 0.0, z0])}
    return mesh, kps


def jaw_biopsy(length: float = 6.5, side: int = 1, cup_length: float = 4.0, cup_width: float = 2.7,
               cup_depth: float = 1.3, wall: float = 0.22, teeth: int = 16) -> tuple[trimesh.Trimesh, Keypoints]:
    """Biopsy-forceps jaw: a hollow half-ellipsoid cup (``cup_length`` x ``cup_width`` x ``cup_depth``)
    opening towards the closing plane, on a short arm from the hub, with a crenellated (toothed) rim. The
    teeth of the two jaws interleave (an even ``teeth`` count makes the 180 deg turn shift them by half a
    tooth). Dimensions are estimates (a ~4 mm cup)."""
    if teeth % 2:
        raise ValueError(f"jaw_biopsy needs an even number of teeth, got {teeth}")
    z0 = HUB_RADIUS + 0.05
    az, ay, ax = cup_length / 2.0, cup_width / 2.0, cup_depth
    zc = length - az
    outer = intersection(_ellipsoid((0.05, 0.0, zc), (ax, ay, az)), box((0.05, -3.0, zc - az - 1), (3.0, 3.0, length + 1)))
    arm = box((0.35, -0.8, z0), (1.2, 0.8, zc - az + 0.9))
    cup = difference(union(outer, arm), _ellipsoid((0.05, 0.0, zc), (ax - wall, ay - wall, az - wall)))
    tooth_h = 0.22
    step = 2.0 * np.pi / teeth
    r = 4.0
    wedges = [[(0.0, zc), (r * np.sin(a0), zc + r * np.cos(a0)), (r * np.sin(a1), zc + r * np.cos(a1))]
              for a0, a1 in ((2 * k * step, (2 * k + 1) * step) for k in range(teeth // 2))]
    tooth_region = union(*[extrude_yz(w, 0.0, 0.05 + tooth_h + 0.05) for w in wedges])
    keep = union(box((0.05 + tooth_h, -3.0, 0.0), (3.0, 3.0, length + 1)), tooth_region)
    cup = intersection(cup, keep)
    mesh = for_side(difference(union(cup, hub()), hub_bore()), side)
    kps = {"tip": np.array([0.15 * side, 0.0, length - 0.05]), "cup_center": np.array([0.05 * side, 0.0, zc])}
    return mesh, kps


def jaw_clip_applier(length: float = 8.5, side: int = 1, bend_deg: float = 15.0, bend_at: float = 5.0,
                     groove_width: float = 0.45, groove_depth: float = 0.33) -> tuple[trimesh.Trimesh, Keypoints]:
    """Clip-applier jaw: slender, with a longitudinal channel on the inner (grip) face that seats the
    clip, and a distal portion angled by ``bend_deg`` towards +y from z = ``bend_at``. The bend is out of
    the opening plane and the same for both jaws: the side -1 body is the side +1 body mirrored through
    x = 0 (its hub still turned 180 deg about z). Dimensions and bend are estimates."""
    z0 = HUB_RADIUS + 0.05
    tb = np.tan(np.radians(bend_deg))

    def yc(z: np.ndarray) -> np.ndarray:
        return np.maximum(np.asarray(z, float) - bend_at, 0.0) * tb

    def strip(za: float, zb: float, wa: float, wb: float) -> list[tuple[float, float]]:
        zs = np.array(sorted({za, zb, *[v for v in (bend_at,) if za < v < zb]}))
        ws = np.interp(zs, [za, zb], [wa, wb])
        return list(zip(yc(zs) + ws, zs)) + list(zip((yc(zs) - ws)[::-1], zs[::-1]))

    top = extrude_yz(strip(z0, length, 0.95, 0.55), -5.0, 5.0)
    side_profile = [(0.05, z0), (0.05, length), (0.45, length), (0.7, length - 0.4), (0.85, bend_at),
                    (1.2, z0 + 1.0), (1.3, z0)]
    body = intersection(top, extrude_xz(side_profile, -3.0, 3.0))
    groove = extrude_yz(strip(z0 + 1.0, length + 1.0, groove_width / 2.0, groove_width / 2.0), -1.0, 0.05 + groove_depth)
    body = difference(body, groove)
    if side < 0:
        body = mirror_x(body)
    elif side != 1:
        raise ValueError(f"jaw side must be +1 or -1, got {side}")
    mesh = finish(difference(union(body, for_side(hub(), side)), hub_bore()))
    zt = length - 0.05
    kps = {"tip": np.array([0.35 * side, float(yc(zt)), zt]), "bend": np.array([0.3 * side, 0.0, bend_at])}
    return mesh, kps


def spatula(length: float = 10.0, blade_width: float = 3.6, thickness: float = 0.8,
            curve: float = 0.7) -> tuple[trimesh.Trimesh, Keypoints]:
    """Permanent-cautery-spatula tip, one piece on the yaw pin: a full-width hub (|y| <= 1.5), a neck
    (|y| <= 0.8) and a flat rounded paddle ``blade_width`` wide in y and ``thickness`` thin in x, curved
    towards +x by ``curve`` mm at the tip. The paddle widens only beyond ~4.4 mm from the yaw axis, clear
    of the wrist lugs. Dimensions are estimates from photographs."""
    neck_w, neck_end, flare_end = 0.8, 3.0, 5.0
    wb = blade_width / 2.0
    zc = length - wb
    arc = [(wb * np.cos(a), zc + wb * np.sin(a)) for a in np.linspace(0.0, np.pi, 17)]
    top = [(-neck_w, 0.0), (neck_w, 0.0), (neck_w, neck_end), (wb, flare_end), *arc, (-wb, flare_end), (-neck_w, neck_end)]
    z = np.linspace(0.0, length + 0.5, 24)
    xc = curve * np.clip((z - neck_end) / (length - neck_end), 0.0, None) ** 2
    half = np.interp(z, [0.0, neck_end, neck_end + 1.5], [0.6, 0.6, thickness / 2.0])
    side_profile = list(zip(xc + half, z)) + list(zip((xc - half)[::-1], z[::-1]))
    body = intersection(extrude_yz(top, -3.0, 3.0), extrude_xz(side_profile, -3.0, 3.0))
    hub_full = cylinder(HUB_RADIUS, -HUB_HALF_WIDTH, HUB_HALF_WIDTH, axis="y")
    mesh = finish(difference(union(body, hub_full), hub_bore()))
    zm = (flare_end + length) / 2.0
    kps = {"tip": np.array([curve, 0.0, length]),
           "blade_center": np.array([curve * ((zm - neck_end) / (length - neck_end)) ** 2, 0.0, zm])}
    return mesh, kps


BUILDERS: dict[str, Builder] = {
    "shaft": shaft,
    "wrist_clevis": wrist_clevis,
    "shaft_extension": shaft_extension,
    "jaw_needle_driver": jaw_needle_driver,
    "jaw_scissors": jaw_scissors,
    "jaw_cadiere": jaw_cadiere,
    "jaw_biopsy": jaw_biopsy,
    "jaw_clip_applier": jaw_clip_applier,
    "spatula": spatula,
}


def build(builder: str, **params: float) -> tuple[trimesh.Trimesh, Keypoints]:
    """Run the named builder with ``params`` (from an instrument YAML)."""
    if builder not in BUILDERS:
        raise ValueError(f"unknown mesh builder {builder!r}; available: {sorted(BUILDERS)}")
    try:
        return BUILDERS[builder](**params)
    except TypeError as e:
        raise ValueError(f"bad parameters for mesh builder {builder!r}: {e}") from None

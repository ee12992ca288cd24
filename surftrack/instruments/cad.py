"""A lab's CAD meshes as instrument parts: file formats, units, a fixed transform and cutting a long shaft.

Formats are read by trimesh (STL, OBJ, glTF/GLB, COLLADA/DAE through pycollada; scenes are flattened with
their node transforms) except PLY, which is read with plyfile: CAD tools (Blender) export PLY faces as
n-gons, and trimesh's binary PLY reader only takes faces of one length. N-gons are split into triangle fans
(what most mesh tools do with a polygon; CAD n-gons are planar and convex in practice).

Every length in an instrument description is in millimetres; ``units`` only says how to read the file's
vertices. A mesh's transform maps file coordinates into the part frame::

    p_part = R @ (scale * p_file * units_to_mm) + origin_mm

with ``R`` from ``rpy`` (radians, URDF's fixed-axis roll about x, then pitch about y, then yaw about z),
``rpy_deg`` or ``quat_xyzw``. A URDF ``<visual><origin xyz rpy>`` therefore copies over with xyz times
1000 (metres to mm).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from surftrack.geometry import se3

UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4, "inch": 25.4}
ROTATION_KEYS = ("rpy", "rpy_deg", "quat_xyzw")


class MeshFileError(ValueError):
    """A mesh file that cannot be read or holds no triangles."""


def rotation_from_spec(spec: dict, where: str) -> np.ndarray:
    """3x3 rotation from at most one of ``rpy`` (radians), ``rpy_deg`` or ``quat_xyzw`` in ``spec``
    (identity when none); ``ValueError`` naming ``where`` otherwise."""
    given = [k for k in ROTATION_KEYS if k in spec]
    if len(given) > 1:
        raise ValueError(f"{where}: give one of {', '.join(ROTATION_KEYS)}, not {' and '.join(given)}")
    if not given:
        return np.eye(3)
    key = given[0]
    value = np.asarray(spec[key], dtype=np.float64) if _is_numbers(spec[key]) else None
    size = 4 if key == "quat_xyzw" else 3
    if value is None or value.shape != (size,) or not np.isfinite(value).all():
        raise ValueError(f"{where}: {key} must be {size} numbers, got {spec[key]!r}")
    if key == "quat_xyzw":
        if np.linalg.norm(value) < 1e-9:
            raise ValueError(f"{where}: quat_xyzw must be non-zero")
        return Rotation.from_quat(value / np.linalg.norm(value)).as_matrix()
    return Rotation.from_euler("xyz", np.radians(value) if key == "rpy_deg" else value).as_matrix()


def vector_from_spec(spec: dict, key: str, where: str, default: tuple[float, ...] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """``spec[key]`` as 3 finite numbers (``default`` when absent); ``ValueError`` naming ``where``."""
    if key not in spec:
        return np.asarray(default, dtype=np.float64)
    value = np.asarray(spec[key], dtype=np.float64) if _is_numbers(spec[key]) else None
    if value is None or value.shape != (3,) or not np.isfinite(value).all():
        raise ValueError(f"{where}: {key} must be 3 numbers, got {spec[key]!r}")
    return value


def _is_numbers(value: object) -> bool:
    return isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                     for v in value)


def read_mesh_file(path: Path) -> trimesh.Trimesh:
    """Triangles of a mesh file, in the file's own units and frame (vertices float64)."""
    if path.suffix.lower() == ".ply":
        return _read_ply(path)
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh and its format plug-ins raise many types for unreadable files
        hint = " (COLLADA needs the pycollada package)" if path.suffix.lower() == ".dae" else ""
        raise MeshFileError(f"cannot read mesh {path}: {e}{hint}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise MeshFileError(f"mesh {path} has no triangles")
    return loaded


def _read_ply(path: Path) -> trimesh.Trimesh:
    from plyfile import PlyData

    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
        vertices = np.stack([np.asarray(v[c], dtype=np.float64) for c in ("x", "y", "z")], axis=1)
        faces_el = ply["face"]
        name = next(n for n in ("vertex_indices", "vertex_index") if n in faces_el.data.dtype.names)
        polygons = faces_el[name]
    except (KeyError, StopIteration) as e:
        raise MeshFileError(f"cannot read mesh {path}: no vertex x/y/z or face vertex_indices ({e})") from None
    except Exception as e:  # plyfile raises PlyParseError, ValueError, EOFError, ...
        raise MeshFileError(f"cannot read mesh {path}: {e}") from None
    tris = [np.stack([np.full(len(f) - 2, f[0]), f[1:-1], f[2:]], axis=1) for f in polygons if len(f) >= 3]
    if not tris:
        raise MeshFileError(f"mesh {path} has no triangles")
    faces = np.concatenate(tris).astype(np.int64)
    if faces.max() >= len(vertices) or faces.min() < 0:
        raise MeshFileError(f"cannot read mesh {path}: a face refers to a vertex that does not exist")
    return trimesh.Trimesh(vertices, faces, process=False)


def mesh_transform(spec: dict, where: str) -> np.ndarray:
    """4x4 map from the file's coordinates (already in mm) to the part frame: ``origin`` (mm) and the
    rotation of :func:`rotation_from_spec`; the scale is applied separately (:func:`load_cad_mesh`)."""
    return se3(rotation_from_spec(spec, where), vector_from_spec(spec, "origin", where))


def load_cad_mesh(path: Path, units: str, spec: dict, where: str) -> trimesh.Trimesh:
    """The mesh of ``path`` in millimetres and the part frame: read, scaled by ``units`` and ``scale``
    (a number or 3 numbers), then moved by ``origin``/``rpy``/``rpy_deg``/``quat_xyzw`` from ``spec``."""
    mesh = read_mesh_file(path).copy()
    scale = spec.get("scale", 1.0)
    if isinstance(scale, (int, float)) and not isinstance(scale, bool):
        factors = np.full(3, float(scale))
    elif _is_numbers(scale) and len(scale) == 3:
        factors = np.asarray(scale, dtype=np.float64)
    else:
        raise ValueError(f"{where}: scale must be a number or 3 numbers, got {scale!r}")
    if not (np.isfinite(factors).all() and (factors > 0).all()):
        raise ValueError(f"{where}: scale must be positive, got {scale!r}")
    mesh.vertices = mesh.vertices * (factors * UNITS_TO_MM[units])
    mesh.apply_transform(mesh_transform(spec, where))
    return mesh


def cut_shaft(mesh: trimesh.Trimesh, length_mm: float) -> tuple[trimesh.Trimesh, trimesh.Trimesh | None]:
    """Split a long shaft mesh (part frame, +z towards the tip) at ``z = -length_mm``: the distal piece
    (z >= -length_mm), which is the tracked part, and the rest (rendered, not tracked), or None when
    nothing lies beyond the cut. Cut faces are capped where the mesh is closed, so a watertight shaft
    stays watertight."""
    normal, origin = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -float(length_mm)])
    pieces = []
    for n in (normal, -normal):
        try:
            piece = mesh.slice_plane(origin, n, cap=mesh.is_watertight)
        except ValueError:  # a cap that cannot be triangulated: keep the open cut
            piece = mesh.slice_plane(origin, n, cap=False)
        pieces.append(piece if piece is not None and len(piece.faces) else None)
    if pieces[0] is None:
        raise ValueError(f"shaft_length_mm {length_mm:g} leaves nothing of the mesh (it lies below "
                         f"z = {-length_mm:g} mm in the part frame; is +z towards the tip?)")
    return pieces[0], pieces[1]

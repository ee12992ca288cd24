"""A rigid instrument part: its mesh (mm, part frame), material, keypoints and derived quantities."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import trimesh
from scipy.spatial import ConvexHull
from scipy.spatial.distance import pdist


#: Two meshes are the same part when their triangles are the same and no vertex moved by more than this (mm).
#: Storing a mesh as float32 (BOP ``models/*.ply``, checkpoints) moves a vertex up to 500 mm from the origin
#: by < 3e-5 mm, while every byte of a hash changes; an edited CAD moves vertices by far more than 1e-3 mm.
GEOMETRY_TOL_MM = 1e-3


def same_geometry(vertices_a: np.ndarray, faces_a: np.ndarray, vertices_b: np.ndarray, faces_b: np.ndarray,
                  tol_mm: float = GEOMETRY_TOL_MM) -> bool:
    """Whether two meshes (vertices (N, 3) mm, faces (F, 3)) are one geometry: the same faces, in order,
    and every vertex within ``tol_mm`` of its counterpart."""
    va, vb = np.asarray(vertices_a, dtype=np.float64), np.asarray(vertices_b, dtype=np.float64)
    fa, fb = np.asarray(faces_a), np.asarray(faces_b)
    return (va.shape == vb.shape and fa.shape == fb.shape and bool(np.array_equal(fa, fb))
            and bool(np.abs(va - vb).max(initial=0.0) <= tol_mm))


@dataclass(frozen=True)
class Material:
    """Surface appearance for the renderer: linear RGB base colour, metallic and roughness in [0, 1]."""

    color: tuple[float, float, float] = (0.7, 0.7, 0.72)
    metallic: float = 0.9
    roughness: float = 0.3


@dataclass(eq=False)
class Part:
    """One rigid part. ``mesh`` is in millimetres in the part frame; ``keypoints`` name points in it."""

    name: str
    mesh: trimesh.Trimesh
    material: Material = field(default_factory=Material)
    keypoints: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.mesh.faces) == 0:
            raise ValueError(f"part {self.name!r} has an empty mesh")
        self.keypoints = {k: np.asarray(v, dtype=np.float64).reshape(3) for k, v in self.keypoints.items()}

    @cached_property
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre (3,) and radius of the minimal sphere around the vertices (normalisation frame)."""
        c, r = trimesh.nsphere.minimum_nsphere(self.mesh.vertices)
        return np.asarray(c, dtype=np.float64), float(r)

    def normalise(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) in mm to normalised coordinates ``(p - c) / r`` inside the unit ball."""
        c, r = self.bounding_sphere
        return (np.asarray(points, dtype=np.float64) - c) / r

    def denormalise(self, points: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`normalise`."""
        c, r = self.bounding_sphere
        return np.asarray(points, dtype=np.float64) * r + c

    @cached_property
    def diameter_max_pairwise(self) -> float:
        """BOP convention: the largest distance between two vertices (attained on the convex hull)."""
        v = self.mesh.vertices
        hull = v[ConvexHull(v).vertices] if len(v) > 4 else v
        return float(pdist(hull).max())

    @cached_property
    def diameter_bbox_diagonal(self) -> float:
        """SurgRIPE convention: the diagonal of the axis-aligned bounding box."""
        return float(np.linalg.norm(self.mesh.extents))

    @cached_property
    def mesh_hash(self) -> str:
        """SHA-256 of vertices and faces, to tie checkpoints and datasets to the exact geometry."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.mesh.faces, dtype=np.int64).tobytes())
        return h.hexdigest()

    def same_geometry(self, vertices: np.ndarray, faces: np.ndarray, tol_mm: float = GEOMETRY_TOL_MM) -> bool:
        """Whether this part's mesh is the mesh (``vertices`` mm, ``faces``) stored elsewhere (a checkpoint,
        a dataset's model) within ``tol_mm``: part identity by geometry, not by file bytes."""
        return same_geometry(self.mesh.vertices, self.mesh.faces, vertices, faces, tol_mm)

    def sample_surface(self, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Area-uniform surface samples (count, 3) in mm and their outward face normals (count, 3)."""
        pts, face_idx = trimesh.sample.sample_surface(self.mesh, count, seed=seed)
        return np.asarray(pts, dtype=np.float64), np.asarray(self.mesh.face_normals[face_idx], dtype=np.float64)

"""Per-corner vertex data for the GPU: meshes are unrolled to three vertices per face.

Unrolling keeps the face order of the source mesh (so ray-casting oracles can index the same faces) and
lets normals be smooth across gentle edges but sharp across creases.
"""

from __future__ import annotations

import numpy as np
import trimesh


def corner_normals(mesh: trimesh.Trimesh, crease_deg: float = 30.0) -> np.ndarray:
    """Normals (F, 3, 3) at each face corner: the area-weighted mean of the normals of the faces around
    that vertex that lie within ``crease_deg`` of the face's own normal (180 = fully smooth)."""
    fn = np.asarray(mesh.face_normals, dtype=np.float64)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    vf = np.asarray(mesh.vertex_faces)  # (V, M) incident faces, padded with -1
    inc = vf[mesh.faces]  # (F, 3, M)
    valid = inc >= 0
    incn = fn[np.where(valid, inc, 0)]  # (F, 3, M, 3)
    cos = np.einsum("fkmj,fj->fkm", incn, fn)
    w = np.where(valid & (cos >= np.cos(np.radians(crease_deg)) - 1e-9), area[np.where(valid, inc, 0)], 0.0)
    n = np.einsum("fkm,fkmj->fkj", w, incn)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), fn[:, None, :])
    return n


def unrolled_vertices(mesh: trimesh.Trimesh, crease_deg: float = 30.0, colors: np.ndarray | None = None,
                      uv: np.ndarray | None = None) -> np.ndarray:
    """Interleaved float32 vertex buffer (3F, 11): position, normal, colour (RGB in [0, 1]) and uv."""
    F = len(mesh.faces)
    out = np.zeros((F, 3, 11), dtype=np.float32)
    out[..., 0:3] = np.asarray(mesh.vertices)[mesh.faces]
    out[..., 3:6] = corner_normals(mesh, crease_deg)
    if colors is not None:
        c = np.asarray(colors)
        c = c[..., :3].astype(np.float64) / (255.0 if c.dtype == np.uint8 else 1.0)
        out[..., 6:9] = c[mesh.faces]
    else:
        out[..., 6:9] = 1.0
    if uv is not None:
        out[..., 9:11] = np.asarray(uv, dtype=np.float64)[mesh.faces]
    return out.reshape(F * 3, 11)

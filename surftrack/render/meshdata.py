"""Vertex data for the GPU: indexed vertices whose normals are smooth across gentle edges and sharp
across creases.

A mesh vertex is split into as many GPU vertices as it has distinct corner normals; faces keep the order
of the source mesh, so ray-casting oracles can index the same faces.
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


def vertex_buffer(mesh: trimesh.Trimesh, crease_deg: float = 30.0, colors: np.ndarray | None = None,
                  uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Interleaved float32 vertices (N, 11): position, normal, colour (RGB in [0, 1]), uv; and uint32
    indices (F, 3). Corners that share a mesh vertex and exactly the same normal share a GPU vertex."""
    F = len(mesh.faces)
    normals = corner_normals(mesh, crease_deg).reshape(F * 3, 3)
    vidx = np.asarray(mesh.faces).reshape(F * 3)
    key = np.concatenate([vidx[:, None].astype(np.float64), normals], axis=1)
    _, first, inverse = np.unique(np.ascontiguousarray(key).view(np.dtype((np.void, 32))).ravel(),
                                  return_index=True, return_inverse=True)
    v = vidx[first]
    out = np.zeros((len(first), 11), dtype=np.float32)
    out[:, 0:3] = np.asarray(mesh.vertices)[v]
    out[:, 3:6] = normals[first]
    if colors is not None:
        c = np.asarray(colors)
        out[:, 6:9] = c[v, :3].astype(np.float64) / (255.0 if c.dtype == np.uint8 else 1.0)
    else:
        out[:, 6:9] = 1.0
    if uv is not None:
        out[:, 9:11] = np.asarray(uv, dtype=np.float64)[v]
    return out, inverse.reshape(F, 3).astype(np.uint32)

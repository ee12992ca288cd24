"""Ray-casting oracle for renderer tests: trimesh (+ embree when available) through OpenCV pixel centres."""

from __future__ import annotations

import numpy as np
import trimesh

from surftrack.geometry import PinholeCamera


def raycast(camera: PinholeCamera, meshes: dict[int, tuple[trimesh.Trimesh, np.ndarray]]):
    """First hits of rays through every pixel centre against posed meshes (id -> (mesh, pose)).

    Returns (ids (H, W) int, depth (H, W) z in mm, face (H, W) index into that mesh's faces or -1,
    hit points (H, W, 3) in the camera frame).
    """
    posed, owner, local = [], [], []
    for iid, (mesh, T) in meshes.items():
        m = mesh.copy()
        m.apply_transform(T)
        posed.append(m)
        owner.append(np.full(len(m.faces), iid))
        local.append(np.arange(len(m.faces)))
    scene = trimesh.util.concatenate(posed)
    owner, local = np.concatenate(owner), np.concatenate(local)
    dirs = camera.rays().reshape(-1, 3)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    loc, ray_idx, tri = scene.ray.intersects_location(np.zeros_like(dirs), dirs, multiple_hits=False)
    H, W = camera.height, camera.width
    ids = np.zeros(H * W, int)
    depth = np.zeros(H * W)
    face = np.full(H * W, -1)
    pts = np.zeros((H * W, 3))
    ids[ray_idx], depth[ray_idx], face[ray_idx], pts[ray_idx] = owner[tri], loc[:, 2], local[tri], loc
    return ids.reshape(H, W), depth.reshape(H, W), face.reshape(H, W), pts.reshape(H, W, 3)


def edge_pixels(ids: np.ndarray) -> np.ndarray:
    """Pixels whose 8-neighbourhood holds another id: where rasterisation may legitimately differ."""
    p = np.pad(ids, 1, mode="edge")
    H, W = ids.shape
    edge = np.zeros_like(ids, dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            edge |= p[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] != ids
    return edge

"""Turning render modalities into viewable uint8 images (kept apart from the renderer itself)."""

from __future__ import annotations

import numpy as np

from surftrack.render.renderer import RenderResult

_ID_COLORS = np.array([[0, 0, 0], [230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
                       [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212]], np.uint8)


def colorize_ids(ids: np.ndarray) -> np.ndarray:
    """Instance-id image (H, W) to distinct colours (H, W, 3); 0 stays black."""
    ids = np.asarray(ids)
    return np.where(ids[..., None] > 0, _ID_COLORS[1:][(ids - 1) % (len(_ID_COLORS) - 1)], 0).astype(np.uint8)


def colorize_depth(depth: np.ndarray) -> np.ndarray:
    """Depth (mm, 0 = none) to grey levels, near = bright, over the range of valid pixels."""
    valid = depth > 0
    out = np.zeros(depth.shape + (3,), np.uint8)
    if valid.any():
        lo, hi = np.percentile(depth[valid], [1, 99])
        g = 1.0 - np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
        out[valid] = (40 + 215 * g[valid, None]).astype(np.uint8)
    return out


def colorize_normals(normal: np.ndarray) -> np.ndarray:
    """Unit normals to RGB ((n + 1) / 2), background black."""
    valid = np.linalg.norm(normal, axis=-1) > 0.5
    return np.where(valid[..., None], ((normal + 1.0) * 127.5).clip(0, 255), 0).astype(np.uint8)


def amodal_outlines(rgb: np.ndarray, amodal: dict[int, np.ndarray]) -> np.ndarray:
    """``rgb`` with the boundary of every amodal silhouette drawn in its instance colour."""
    out = rgb.copy()
    for iid, m in amodal.items():
        edge = m & ~(np.roll(m, 1, 0) & np.roll(m, -1, 0) & np.roll(m, 1, 1) & np.roll(m, -1, 1))
        out[edge] = _ID_COLORS[1:][(iid - 1) % (len(_ID_COLORS) - 1)]
    return out


def modality_panel(result: RenderResult) -> np.ndarray:
    """2x2 panel: RGB with amodal outlines | visible ids; depth | normals."""
    top = np.concatenate([amodal_outlines(result.rgb, result.amodal), colorize_ids(result.instance)], axis=1)
    bottom = np.concatenate([colorize_depth(result.depth), colorize_normals(result.normal)], axis=1)
    return np.concatenate([top, bottom], axis=0)

"""OpenCV intrinsics to an OpenGL clip transform that reproduces OpenCV's pixel-centre convention."""

from __future__ import annotations

import numpy as np

# OpenCV camera (x right, y down, z forward) to OpenGL eye space (x right, y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def gl_projection(K: np.ndarray, width: int, height: int, near: float, far: float) -> np.ndarray:
    """4x4 matrix taking OpenCV camera-frame points to GL clip space.

    The +0.5 terms put OpenCV pixel (u, v) at GL window position (u + 0.5, v + 0.5), the centre of GL
    pixel (u, v): a rasterised pixel samples exactly the ray through the OpenCV pixel centre. GL stores
    rows bottom-up; with v increasing upwards in window space, the first row in memory is image row 0,
    so read-backs need no flip. The y flip mirrors screen space: triangles' GL facing is reversed.
    """
    fx, fy, cx, cy, s = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    W, H = float(width), float(height)
    P = np.array([
        [2 * fx / W, -2 * s / W, 1 - 2 * (cx + 0.5) / W, 0.0],
        [0.0, -2 * fy / H, 1 - 2 * (cy + 0.5) / H, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])
    return P @ CV_TO_GL

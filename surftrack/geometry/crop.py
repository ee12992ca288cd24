"""Image crops: warping an image into a crop, and crops rotated in the image plane with the camera that
sees exactly the crop.

Coordinates follow :mod:`surftrack.geometry.camera` and :mod:`surftrack.geometry.boxes`: pixel centres at
integer coordinates, crop boxes (x0, y0, x1, y1) in pixel-EDGE coordinates (the full image is
(0, 0, W, H)). :func:`surftrack.geometry.crop_affine` gives the warp of an upright crop and its camera;
:func:`warp_image` applies a warp to an image, mask or id map; :func:`unwarp_image` carries a crop's
per-pixel values back into the image.

A crop rotated about its centre is an image warp that no pinhole K with the SAME camera frame can
describe. It is described instead by rotating the camera frame about its optical axis:
:func:`crop_with_rotation` returns ``(M, camera, R_crop)`` such that, for every camera-frame point X,
``camera.project(R_crop @ X) == M @ [original_camera.project(X), 1]``. Poses move to the crop camera as
``T_crop = R_crop @ T`` (:func:`pose_in_crop`). With square pixels (fx = fy, no skew) R_crop is the
rotation by the crop angle about z and the crop K is an ordinary K; with fx != fy the exact solution
(an RQ decomposition) gives a crop K with a small skew K[0, 1] and R_crop's angle differs slightly from
the image angle. Both are handled by :class:`PinholeCamera.project` and the renderer's projection.
"""

from __future__ import annotations

import cv2
import numpy as np

from surftrack.geometry.boxes import Box
from surftrack.geometry.camera import PinholeCamera, crop_affine


def _size(size: int | tuple[int, int]) -> tuple[int, int]:
    """(width, height) of an output ``size`` given as an int (a square) or as (width, height)."""
    return (int(size), int(size)) if np.isscalar(size) else (int(size[0]), int(size[1]))


def _rq2(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """M (2, 2) with det > 0 = K2 @ Q2: K2 upper triangular with positive diagonal, Q2 a rotation."""
    phi = np.arctan2(M[1, 0], M[1, 1])
    c, s = np.cos(phi), np.sin(phi)
    Q = np.array([[c, -s], [s, c]])
    K2 = M @ Q.T
    K2[1, 0] = 0.0
    return K2, Q


def crop_with_rotation(camera: PinholeCamera, box: Box, size: int | tuple[int, int],
                       angle_rad: float = 0.0) -> tuple[np.ndarray, PinholeCamera, np.ndarray]:
    """Warp (2, 3) for ``cv2.warpAffine``, the crop camera and ``R_crop`` (3, 3) of a rotated crop.

    The image content is rotated by ``angle_rad`` about the centre of ``box`` (pixel-edge coordinates;
    positive = clockwise as displayed, y pointing down), then the box is cropped and resized to ``size``
    (an int for a square, or (width, height)). See the module docstring for the meaning of ``R_crop``.
    With ``angle_rad = 0`` this is :func:`surftrack.geometry.crop_affine` and ``R_crop`` is the identity.
    """
    w, h = _size(size)
    M_crop, cam0 = crop_affine(camera, box, (w, h))
    if angle_rad == 0.0:
        return M_crop, cam0, np.eye(3)
    if camera.dist.size and np.any(camera.dist != 0):
        raise ValueError("a rotated crop of a distorted camera is not a pinhole camera; undistort the image first")
    x0, y0, x1, y1 = (float(b) for b in box)
    c = np.array([(x0 + x1) / 2.0 - 0.5, (y0 + y1) / 2.0 - 0.5])  # box centre in pixel-centre coordinates
    co, si = np.cos(angle_rad), np.sin(angle_rad)
    R2 = np.array([[co, -si], [si, co]])
    A_rot = np.eye(3)
    A_rot[:2, :2], A_rot[:2, 2] = R2, c - R2 @ c
    A = np.vstack([M_crop, [0.0, 0.0, 1.0]]) @ A_rot
    B = A @ camera.K
    K2, Q2 = _rq2(B[:2, :2])
    K = np.eye(3)
    K[:2, :2], K[:2, 2] = K2, B[:2, 2]
    R_crop = np.eye(3)
    R_crop[:2, :2] = Q2
    return A[:2], PinholeCamera(K, w, h), R_crop


def pose_in_crop(R_crop: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """4x4 model-to-crop-camera pose: ``R_crop`` applied to the model-to-camera ``pose`` (4, 4)."""
    T = np.asarray(pose, dtype=np.float64).copy()
    T[:3, :3] = R_crop @ T[:3, :3]
    T[:3, 3] = R_crop @ T[:3, 3]
    return T


def warp_image(img: np.ndarray, M: np.ndarray, size: int | tuple[int, int], nearest: bool = False) -> np.ndarray:
    """``img`` (H, W) or (H, W, C) warped by ``M`` (2, 3) (source pixel centre -> crop pixel centre, as from
    :func:`crop_affine` or :func:`crop_with_rotation`) to ``size`` (an int for a square, or (width,
    height)): bilinear, or nearest-neighbour with ``nearest`` (masks and ids; bool masks come back bool);
    zeros outside the source image."""
    w, h = _size(size)
    src = img.astype(np.uint8) if img.dtype == bool else img
    out = cv2.warpAffine(src, np.asarray(M, dtype=np.float64), (w, h),
                         flags=cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(bool) if img.dtype == bool else out


def unwarp_image(crop: np.ndarray, M: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`warp_image`: ``crop`` (h, w) float, made by the warp ``M`` (2, 3; image pixel
    centre -> crop pixel centre), carried back into an image of ``size`` (width, height), bilinearly.
    Returns (values (H, W) float32, zero outside the crop; covered (H, W) bool: the image pixels the crop
    saw). For putting a crop's per-pixel output (a network's mask) back into the frame."""
    w, h = _size(size)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    M = np.asarray(M, dtype=np.float64)
    values = cv2.warpAffine(np.asarray(crop, np.float32), M, (w, h), flags=flags, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=0)
    covered = cv2.warpAffine(np.ones(crop.shape[:2], np.float32), M, (w, h), flags=flags,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0.999
    return values, covered

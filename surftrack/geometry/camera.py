"""Pinhole camera with OpenCV conventions, and the one pinhole projection of the package.

Pixel (u, v) has its centre at integer coordinates; x right, y down, z forward; units mm.
:func:`project_points` is ``cv2.projectPoints`` without distortion, for points already in the camera frame
(pose them first with :func:`surftrack.geometry.transform_points`); :func:`projected_box` is the image box
a posed model covers.
A crop box is given in pixel-edge coordinates ``(x0, y0, x1, y1)``: the crop covers the image area from
edge x0 to edge x1, so a full image is ``(0, 0, W, H)`` (:mod:`surftrack.geometry.boxes`).
:func:`crop_affine` returns the 2x3 matrix for ``cv2.warpAffine`` and the camera of the crop, consistent
with each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from surftrack.geometry.boxes import Box
from surftrack.geometry.transforms import se3, skew, transform_points


def project_points(K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (..., 2) of camera-frame points (..., 3) in mm through the intrinsics
    ``K`` = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: ``(u, v, 1) ~ K @ X``, no distortion.

    Computed as ``u = fx x/z + cx (+ s y/z)``, ``v = fy y/z + cy``; the entries of ``K`` below the diagonal
    are taken to be those of an intrinsic matrix and not read. Meant for points in front of the camera
    (z > 0): a point at z <= 0 gives a meaningless or non-finite pixel, without a warning, so callers that
    may hold such points mask them by their depth.
    """
    X = np.asarray(points, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = X[..., :2] / X[..., 2:3]
        uv = xy * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    if K[0, 1] != 0.0:  # skew: the crop camera of a rotated crop with fx != fy
        uv[..., 0] += K[0, 1] * xy[..., 1]
    return uv


def project_pose_jacobian(K: np.ndarray, R: np.ndarray, t: np.ndarray, points: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of model points (N, 3, mm) at the model-to-camera pose (R, t), and their derivatives
    (N, 2, 6) with respect to a pose step ``(dt, dtheta)``: ``t' = t + dt`` (camera frame, mm),
    ``R' = R exp(dtheta)`` (body rotation, rad), the trackers' convention. Skew in ``K`` is ignored in the
    derivative (intrinsic matrices of video frames have none)."""
    xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)
    Xc = xyz @ R.T + t
    uv = project_points(K, Xc)
    z = np.maximum(Xc[:, 2], 1e-6)
    fx, fy = K[0, 0], K[1, 1]
    P = np.zeros((len(xyz), 2, 3))
    P[:, 0, 0], P[:, 0, 2] = fx / z, -fx * Xc[:, 0] / z**2
    P[:, 1, 1], P[:, 1, 2] = fy / z, -fy * Xc[:, 1] / z**2
    dX = np.concatenate([np.broadcast_to(np.eye(3), (len(xyz), 3, 3)), -R @ skew(xyz)], axis=2)  # dXc / d(dt, dtheta)
    return uv, P @ dX


def projected_box(K: np.ndarray, R: np.ndarray, t: np.ndarray, vertices: np.ndarray,
                  size: tuple[int, int]) -> tuple[Box | None, float]:
    """The image box of model points ``vertices`` (N, 3, mm) at the model-to-camera pose ``R``, ``t``:
    (the pixel-edge (x, y, w, h) box of their projections clipped to the image of ``size`` (W, H), the
    fraction of the unclipped box's area inside the image). (None, 0) when they lie behind the camera or
    entirely outside the image."""
    X = transform_points(se3(R, t), vertices)
    front = X[:, 2] > 1e-3
    if front.sum() < 3:
        return None, 0.0
    uv = project_points(K, X)[front]
    x0, y0 = uv.min(0)
    x1, y1 = uv.max(0) + 1.0  # pixel-edge box around pixel centres
    W, H = size
    area = (x1 - x0) * (y1 - y0)
    cx0, cy0, cx1, cy1 = max(x0, 0.0), max(y0, 0.0), min(x1, float(W)), min(y1, float(H))
    if cx1 <= cx0 or cy1 <= cy0 or area <= 0:
        return None, 0.0
    return (cx0, cy0, cx1 - cx0, cy1 - cy0), float((cx1 - cx0) * (cy1 - cy0) / area)


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics K (3x3), image size and optional OpenCV distortion coefficients."""

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or K[2, 2] != 1.0 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must be a 3x3 intrinsic matrix with fx, fy > 0 and K[2,2] = 1, got {K.tolist()}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", np.asarray(self.dist, dtype=np.float64).ravel())

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> PinholeCamera:
        """Camera with square pixels, the principal point at the image centre and a horizontal FOV."""
        f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2.0)
        K = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])
        return cls(K, width, height)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) of camera-frame points (N, 3) (no distortion; z must be > 0):
        :func:`project_points` with this camera's K."""
        return project_points(self.K, points)

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) of pixels (N, 2) at z-depths (N,)."""
        uv = np.asarray(uv, dtype=np.float64)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        x = (uv[:, 0] - self.cx) / self.fx
        y = (uv[:, 1] - self.cy) / self.fy
        return np.stack([x * z, y * z, z], axis=-1)

    def rays(self) -> np.ndarray:
        """Unit-depth ray directions (H, W, 3) through every pixel centre."""
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)

    def resized(self, width: int, height: int) -> PinholeCamera:
        """The camera of this image resized to ``width`` x ``height``."""
        return crop_affine(self, (0.0, 0.0, float(self.width), float(self.height)), (width, height))[1]

    def cropped(self, box: Box, size: tuple[int, int]) -> PinholeCamera:
        """The camera of the crop ``box`` (pixel edges) resized to ``size`` = (width, height)."""
        return crop_affine(self, box, size)[1]

    def to_dict(self) -> dict:
        d = {"K": self.K.tolist(), "width": int(self.width), "height": int(self.height)}
        if self.dist.size:
            d["dist"] = self.dist.tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> PinholeCamera:
        K = np.asarray(d["K"], dtype=np.float64).reshape(3, 3)
        return cls(K, int(d["width"]), int(d["height"]), np.asarray(d.get("dist", []), dtype=np.float64))


def crop_warp(box: Box, size: tuple[int, int]) -> np.ndarray:
    """Warp matrix (2, 3) (image pixel centre -> crop pixel centre) of the upright crop ``box`` = (x0, y0,
    x1, y1) (pixel-edge coordinates) resampled to ``size`` = (width, height): ``(u + 0.5 - x0) * s - 0.5``
    with ``s = width / (x1 - x0)``."""
    x0, y0, x1, y1 = (float(b) for b in box)
    w, h = int(size[0]), int(size[1])
    if x1 <= x0 or y1 <= y0 or w <= 0 or h <= 0:
        raise ValueError(f"invalid crop box {box} or size {size}")
    sx, sy = w / (x1 - x0), h / (y1 - y0)
    return np.array([[sx, 0.0, (0.5 - x0) * sx - 0.5], [0.0, sy, (0.5 - y0) * sy - 0.5]])


def crop_affine(
    camera: PinholeCamera, box: Box, size: tuple[int, int]
) -> tuple[np.ndarray, PinholeCamera]:
    """Warp matrix (2, 3) for ``cv2.warpAffine(img, M, size)`` and the camera of the crop.

    ``box`` = (x0, y0, x1, y1) in pixel-edge coordinates of ``camera``'s image, ``size`` = (width, height)
    of the output. A pixel centre u maps to ``(u + 0.5 - x0) * s - 0.5`` with ``s = width / (x1 - x0)``.
    """
    M = crop_warp(box, size)
    x0, y0 = float(box[0]), float(box[1])
    sx, sy = M[0, 0], M[1, 1]
    w, h = int(size[0]), int(size[1])
    K = camera.K.copy()
    K[0, 0] *= sx
    K[0, 1] *= sx
    K[1, 1] *= sy
    K[0, 2] = (camera.cx + 0.5 - x0) * sx - 0.5
    K[1, 2] = (camera.cy + 0.5 - y0) * sy - 0.5
    return M, PinholeCamera(K, w, h, camera.dist)

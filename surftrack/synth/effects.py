"""Camera effects on rendered frames: defocus and motion blur, vignetting, gamma, sensor noise, JPEG.

A renderer's image is clean; an endoscope's is not. :func:`apply_effects` degrades a uint8 RGB image
(H, W, 3) the way a camera would, with every random choice drawn from the ``numpy.random.Generator``
passed in, so a given generator state always gives the same image. The order is the physical one:
optics (defocus / motion blur), then vignetting, the tone curve (gamma), sensor noise and last the
JPEG re-compression of a recorder.

Effects change appearance only, never geometry: blur kernels are point-symmetric about their centre
pixel, so a blurred dot keeps its centroid, and nothing shifts or resamples the image. Pixel centres
are at integer coordinates (OpenCV), so the image centre is ``((W - 1) / 2, (H - 1) / 2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import cv2
import numpy as np

Range = tuple[float, float]


def _check_range(name: str, r: tuple, lo: float | None = None, hi: float | None = None) -> None:
    if len(r) != 2 or not (r[0] <= r[1]):
        raise ValueError(f"{name} must be a (min, max) pair with min <= max, got {r}")
    if (lo is not None and r[0] < lo) or (hi is not None and r[1] > hi):
        raise ValueError(f"{name} must lie within [{lo}, {hi}], got {r}")


@dataclass(frozen=True)
class CameraEffects:
    """Ranges of camera effects; :func:`apply_effects` draws one value from each range per image.

    ``noise_std``: Gaussian read-noise sigma in 8-bit levels. ``shot_noise``: signal-dependent noise,
    sigma = ``k * sqrt(intensity)`` (intensity in 8-bit levels), the two added in variance.
    ``blur_prob`` / ``blur_sigma``: probability and sigma (px) of a Gaussian defocus.
    ``motion_blur_prob`` / ``motion_blur_px``: probability and length (px) of a linear motion blur at a
    random angle. ``vignetting``: brightness at the image corner farthest from the principal point falls by
    this fraction (cos^4-like radial falloff, none at the principal point). ``gamma_jitter``: exponent of
    a tone curve ``out = 255 * (in / 255) ** gamma``. ``jpeg_quality``: (min, max) quality of a JPEG
    re-compression, or None for none.
    """

    noise_std: Range = (0.0, 4.0)
    shot_noise: Range = (0.0, 0.6)
    blur_prob: float = 0.3
    blur_sigma: Range = (0.3, 1.5)
    motion_blur_prob: float = 0.15
    motion_blur_px: Range = (2.0, 9.0)
    vignetting: Range = (0.0, 0.45)
    gamma_jitter: Range = (0.9, 1.1)
    jpeg_quality: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        for name in ("noise_std", "shot_noise", "blur_sigma", "motion_blur_px", "vignetting", "gamma_jitter"):
            value = tuple(float(v) for v in getattr(self, name))
            object.__setattr__(self, name, value)
        _check_range("noise_std", self.noise_std, lo=0.0)
        _check_range("shot_noise", self.shot_noise, lo=0.0)
        _check_range("blur_sigma", self.blur_sigma, lo=0.0)
        _check_range("motion_blur_px", self.motion_blur_px, lo=0.0)
        _check_range("vignetting", self.vignetting, lo=0.0, hi=0.99)
        _check_range("gamma_jitter", self.gamma_jitter, lo=1e-3)
        for name in ("blur_prob", "motion_blur_prob"):
            p = float(getattr(self, name))
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {p}")
            object.__setattr__(self, name, p)
        if self.jpeg_quality is not None:
            q = tuple(int(v) for v in self.jpeg_quality)
            _check_range("jpeg_quality", q, lo=1, hi=100)
            object.__setattr__(self, "jpeg_quality", q)

    @classmethod
    def from_dict(cls, d: dict) -> CameraEffects:
        """Effects from a config mapping (e.g. YAML); keys are the field names, missing ones keep defaults."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown camera effect key(s) {unknown}; known keys are {sorted(known)}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})

    @classmethod
    def none(cls) -> CameraEffects:
        """Effects that leave every image unchanged."""
        return cls(noise_std=(0.0, 0.0), shot_noise=(0.0, 0.0), blur_prob=0.0, motion_blur_prob=0.0,
                   vignetting=(0.0, 0.0), gamma_jitter=(1.0, 1.0), jpeg_quality=None)


def motion_blur_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """Normalised linear motion-blur kernel (odd square size) of a segment ``length_px`` long through the
    centre pixel at ``angle_rad`` (x right, y down); point-symmetric, so it does not shift the image."""
    half = 0.5 * max(float(length_px), 0.0)
    r = int(math.ceil(half)) + 1
    k = np.zeros((2 * r + 1, 2 * r + 1), dtype=np.float64)
    # Samples along the segment, symmetric about 0, each splatted bilinearly (anti-aliased line).
    n = max(2, int(math.ceil(4 * half)) + 1)
    t = np.linspace(-half, half, n)
    x, y = r + t * math.cos(angle_rad), r + t * math.sin(angle_rad)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy, x0 + dx), w)
    k = 0.5 * (k + k[::-1, ::-1])  # exact point symmetry despite floating-point splatting
    return k / k.sum()


def vignetting_gain(width: int, height: int, strength: float,
                    principal_point: tuple[float, float] | None = None) -> np.ndarray:
    """Per-pixel brightness gain (H, W) of a cos^4 falloff around ``principal_point`` (default the image
    centre): 1 there, ``1 - strength`` at the farthest image corner (pixel centre)."""
    cx, cy = principal_point if principal_point is not None else ((width - 1) / 2.0, (height - 1) / 2.0)
    if strength <= 0.0:
        return np.ones((height, width), dtype=np.float32)
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], dtype=np.float64)
    r_max = float(np.max(np.hypot(corners[:, 0] - cx, corners[:, 1] - cy)))
    if r_max <= 0.0:
        return np.ones((height, width), dtype=np.float32)
    # cos^4 of the field angle with an effective focal length f: gain = (1 + (r / f)^2)^-2 = 1 - strength at r_max.
    f = r_max / math.sqrt((1.0 - strength) ** -0.5 - 1.0)
    u = (np.arange(width, dtype=np.float64) - cx) / f
    v = (np.arange(height, dtype=np.float64) - cy) / f
    gain = 1.0 / (1.0 + u[None, :] ** 2 + v[:, None] ** 2) ** 2
    return gain.astype(np.float32)


def apply_effects(rgb: np.ndarray, effects: CameraEffects, rng: np.random.Generator,
                  principal_point: tuple[float, float] | None = None) -> np.ndarray:
    """A new uint8 RGB image: ``rgb`` (H, W, 3) uint8 degraded by ``effects``, drawing from ``rng``.

    Order: defocus / motion blur -> vignetting (centred at ``principal_point``, pixel coordinates, default
    the image centre) -> gamma -> read and shot noise -> JPEG. Deterministic for a given ``rng`` state.
    """
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected a uint8 RGB image (H, W, 3), got {rgb.dtype} {rgb.shape}")
    h, w = rgb.shape[:2]
    e = effects
    # Every random value is drawn up front in a fixed order, so one effect's setting does not change
    # the values another effect gets from the same generator state.
    do_blur = rng.random() < e.blur_prob
    sigma = rng.uniform(*e.blur_sigma)
    do_motion = rng.random() < e.motion_blur_prob
    length, angle = rng.uniform(*e.motion_blur_px), rng.uniform(0.0, np.pi)
    vignette = rng.uniform(*e.vignetting)
    gamma = rng.uniform(*e.gamma_jitter)
    read_std, shot_k = rng.uniform(*e.noise_std), rng.uniform(*e.shot_noise)
    quality = int(rng.integers(e.jpeg_quality[0], e.jpeg_quality[1] + 1)) if e.jpeg_quality else None

    img = rgb.astype(np.float32)
    if do_blur and sigma > 0.0:
        img = cv2.GaussianBlur(img, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT_101)
    if do_motion and length > 0.0:
        img = cv2.filter2D(img, -1, motion_blur_kernel(length, angle).astype(np.float32),
                           borderType=cv2.BORDER_REFLECT_101)
    if vignette > 0.0:
        img *= vignetting_gain(w, h, vignette, principal_point)[..., None]
    if gamma != 1.0:
        img = 255.0 * np.power(np.clip(img, 0.0, 255.0) / 255.0, gamma, dtype=np.float32)
    if read_std > 0.0 or shot_k > 0.0:
        var = read_std ** 2 + shot_k ** 2 * np.clip(img, 0.0, 255.0)
        img = img + np.sqrt(var) * rng.standard_normal(img.shape, dtype=np.float32)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if quality is not None:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        out = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return out

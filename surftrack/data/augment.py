"""Photometric augmentation of uint8 RGB crops, driven by an explicit ``numpy.random.Generator``.

Applied in this order, each with its own probability: synthetic occluders (random polygons / ellipses
of a random colour; their pixels are REMOVED from the returned modal mask, the amodal targets are left
as they are), synthetic specular highlights (bright soft blobs, half of them centred on the object),
colour jitter (brightness, contrast, saturation, hue), Gaussian blur, Gaussian noise and coarse dropout
(random rectangles of a flat colour; a camera-style corruption, so the modal mask is NOT changed by it:
use occluders to simulate occlusion).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

import cv2
import numpy as np

Range = tuple[float, float]


@dataclass(frozen=True)
class AugmentConfig:
    """Probabilities and ranges; sizes are fractions of the crop side, intensities in uint8 units."""

    p_color: float = 0.8
    brightness: float = 0.3      # factor in 1 +- brightness
    contrast: float = 0.3        # factor in 1 +- contrast, about the mean grey level
    saturation: float = 0.3      # factor in 1 +- saturation
    hue: float = 0.04            # shift in +- hue of a full turn
    p_blur: float = 0.2
    blur_sigma: Range = (0.4, 1.5)
    p_noise: float = 0.3
    noise_std: Range = (2.0, 8.0)
    p_dropout: float = 0.2
    dropout_count: tuple[int, int] = (1, 4)
    dropout_size: Range = (0.05, 0.2)
    p_occluder: float = 0.3
    occluder_count: tuple[int, int] = (1, 2)
    occluder_size: Range = (0.15, 0.45)
    p_specular: float = 0.3
    specular_count: tuple[int, int] = (1, 3)
    specular_size: Range = (0.01, 0.06)
    specular_strength: Range = (0.4, 1.0)

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.startswith("p_") and not 0.0 <= v <= 1.0:
                raise ValueError(f"augment.{f.name} must be a probability in [0, 1], got {v}")
            if isinstance(v, (tuple, list)):
                if len(v) != 2 or v[0] > v[1] or v[0] < 0:
                    raise ValueError(f"augment.{f.name} must be a range (lo, hi) with 0 <= lo <= hi, got {v}")
                object.__setattr__(self, f.name, tuple(v))

    @classmethod
    def from_dict(cls, d: dict | None) -> AugmentConfig:
        d = dict(d or {})
        unknown = set(d) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown augment keys {sorted(unknown)}; known: {sorted(f.name for f in fields(cls))}")
        return cls(**d)

    @classmethod
    def none(cls) -> AugmentConfig:
        """No augmentation at all."""
        return cls(**{f.name: 0.0 for f in fields(cls) if f.name.startswith("p_")})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _ri(rng: np.random.Generator, r: tuple[int, int]) -> int:
    return int(rng.integers(r[0], r[1] + 1))


def add_occluders(img: np.ndarray, mask: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """Paint random polygons / ellipses into ``img`` in place; returns the occluder mask (H, W) bool.
    Half the occluders are centred on a pixel of ``mask`` (when it has one) so they hit the object."""
    H, W = img.shape[:2]
    side = min(H, W)
    occ = np.zeros((H, W), np.uint8)
    ys, xs = np.nonzero(mask)
    for _ in range(_ri(rng, cfg.occluder_count)):
        if len(xs) and rng.random() < 0.5:
            k = int(rng.integers(len(xs)))
            c = np.array([xs[k], ys[k]], dtype=np.float64)
        else:
            c = rng.uniform([0, 0], [W, H])
        r = rng.uniform(*cfg.occluder_size) * side / 2.0
        one = np.zeros((H, W), np.uint8)
        if rng.random() < 0.5:
            n = int(rng.integers(3, 9))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = r * rng.uniform(0.4, 1.0, n)
            pts = np.stack([c[0] + rad * np.cos(ang), c[1] + rad * np.sin(ang)], axis=1)
            cv2.fillPoly(one, [np.round(pts).astype(np.int32)], 1)
        else:
            axes = (max(1, int(r)), max(1, int(r * rng.uniform(0.3, 1.0))))
            cv2.ellipse(one, (int(c[0]), int(c[1])), axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        colour = rng.uniform(0, 255, 3)
        shade = 1.0 + rng.normal(0, 0.05, (H, W, 1))  # a little texture so it is not a flat stamp
        sel = one.astype(bool)
        img[sel] = np.clip(colour * shade[sel], 0, 255).astype(np.uint8)
        occ |= one
    return occ.astype(bool)


def add_specular(img: np.ndarray, mask: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """Bright soft elliptical Gaussian blobs added to ``img`` (returned as a new uint8 array)."""
    H, W = img.shape[:2]
    side = min(H, W)
    ys, xs = np.nonzero(mask)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    out = img.astype(np.float32)
    for _ in range(_ri(rng, cfg.specular_count)):
        if len(xs) and rng.random() < 0.5:
            k = int(rng.integers(len(xs)))
            cx, cy = float(xs[k]), float(ys[k])
        else:
            cx, cy = rng.uniform(0, W), rng.uniform(0, H)
        s1 = max(0.5, rng.uniform(*cfg.specular_size) * side)
        s2 = s1 * rng.uniform(0.3, 1.0)
        a = rng.uniform(0, np.pi)
        dx, dy = xx - cx, yy - cy
        u = dx * np.cos(a) + dy * np.sin(a)
        v = -dx * np.sin(a) + dy * np.cos(a)
        blob = np.exp(-0.5 * ((u / s1) ** 2 + (v / s2) ** 2))
        tint = np.array([1.0, rng.uniform(0.9, 1.0), rng.uniform(0.85, 1.0)], dtype=np.float32)
        out += rng.uniform(*cfg.specular_strength) * 255.0 * blob[..., None] * tint
    return np.clip(out, 0, 255).astype(np.uint8)


def color_jitter(img: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """Brightness, contrast, saturation and hue changes in a random order."""
    out = img.astype(np.float32)
    for op in rng.permutation(4):
        if op == 0 and cfg.brightness > 0:
            out *= rng.uniform(1 - cfg.brightness, 1 + cfg.brightness)
        elif op == 1 and cfg.contrast > 0:
            mean = (out @ np.array([0.299, 0.587, 0.114], np.float32)).mean()
            out = (out - mean) * rng.uniform(1 - cfg.contrast, 1 + cfg.contrast) + mean
        elif op == 2 and cfg.saturation > 0:
            grey = (out @ np.array([0.299, 0.587, 0.114], np.float32))[..., None]
            out = (out - grey) * rng.uniform(1 - cfg.saturation, 1 + cfg.saturation) + grey
        elif op == 3 and cfg.hue > 0:
            hsv = cv2.cvtColor(np.clip(out, 0, 255).astype(np.uint8), cv2.COLOR_RGB2HSV)
            shift = int(round(rng.uniform(-cfg.hue, cfg.hue) * 180))
            hsv[..., 0] = ((hsv[..., 0].astype(np.int32) + shift) % 180).astype(np.uint8)
            out = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB).astype(np.float32)
        out = np.clip(out, 0, 255)
    return out.astype(np.uint8)


def coarse_dropout(img: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """Random rectangles of one flat random grey level (in place; returned)."""
    H, W = img.shape[:2]
    side = min(H, W)
    for _ in range(_ri(rng, cfg.dropout_count)):
        w = max(1, int(rng.uniform(*cfg.dropout_size) * side))
        h = max(1, int(rng.uniform(*cfg.dropout_size) * side))
        x, y = int(rng.integers(0, max(1, W - w + 1))), int(rng.integers(0, max(1, H - h + 1)))
        img[y:y + h, x:x + w] = int(rng.integers(0, 256))
    return img


def augment(image: np.ndarray, mask_modal: np.ndarray, cfg: AugmentConfig,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Augmented copy of ``image`` (H, W, 3) uint8 and the modal mask (H, W) bool with occluded pixels
    removed; see the module docstring for the order. Inputs are not modified."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"augment expects an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    if mask_modal.shape != image.shape[:2]:
        raise ValueError(f"mask {mask_modal.shape} does not match image {image.shape[:2]}")
    img = image.copy()
    mask = np.asarray(mask_modal, dtype=bool).copy()
    if rng.random() < cfg.p_occluder:
        occ = add_occluders(img, mask, cfg, rng)
        mask &= ~occ
    if rng.random() < cfg.p_specular:
        img = add_specular(img, mask, cfg, rng)
    if rng.random() < cfg.p_color:
        img = color_jitter(img, cfg, rng)
    if rng.random() < cfg.p_blur:
        img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(*cfg.blur_sigma)))
    if rng.random() < cfg.p_noise:
        noise = rng.normal(0.0, rng.uniform(*cfg.noise_std), img.shape)
        img = np.clip(img.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    if rng.random() < cfg.p_dropout:
        img = coarse_dropout(img, cfg, rng)
    return img, mask

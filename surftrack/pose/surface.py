"""Surface samples of a part with their keys, computed once per (model, part, count) and cached."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from surftrack.model.surfsurg6d import SurfSurg6D, surface_bank

_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@dataclass
class SurfaceBank:
    """``points`` (N, 3) mm and ``normals`` (N, 3) (outward, unit) float32, ``keys`` (N, E): area-uniform
    samples in random order, so every prefix is again an area-uniform sample. ``center``, ``radius``: the
    part's bounding sphere (mm), ``area`` its surface area (mm^2)."""

    points: torch.Tensor
    normals: torch.Tensor
    keys: torch.Tensor
    center: np.ndarray
    radius: float
    area: float

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @classmethod
    def from_arrays(cls, points_mm: np.ndarray, normals: np.ndarray, keys: np.ndarray | torch.Tensor,
                    center, radius: float, area: float, device: str | torch.device = "cpu") -> SurfaceBank:
        f = lambda a: torch.as_tensor(np.asarray(a, np.float32) if not torch.is_tensor(a) else a,  # noqa: E731
                                      dtype=torch.float32, device=device)
        return cls(f(points_mm), f(normals), f(keys), np.asarray(center, np.float64), float(radius), float(area))


def _key(part_index: int, count: int, seed: int, device: torch.device) -> tuple:
    return (int(part_index), int(count), int(seed), str(device))


def bank_is_cached(model: SurfSurg6D, part_index: int, count: int, seed: int = 0,
                   device: str | torch.device | None = None) -> bool:
    device = torch.device(device) if device is not None else next(model.parameters()).device
    return _key(part_index, count, seed, device) in _CACHE.get(model, {})


@torch.inference_mode()
def part_bank(model: SurfSurg6D, part_index: int, count: int, seed: int = 0,
              device: str | torch.device | None = None) -> SurfaceBank:
    """The cached bank of ``count`` samples of part ``part_index``. The cache is keyed by the model object
    (weakly): call :func:`clear_bank_cache` after changing its weights."""
    device = torch.device(device) if device is not None else next(model.parameters()).device
    per_model = _CACHE.setdefault(model, {})
    key = _key(part_index, count, seed, device)
    if key not in per_model:
        part = model.parts[part_index]
        coords, normals = surface_bank(part, int(count), seed)
        pts = torch.from_numpy(coords).to(device)
        keys = torch.cat([model.keys(part_index, pts[i:i + 16384]).float() for i in range(0, len(pts), 16384)])
        mm = coords.astype(np.float64) * part.radius + part.center
        area = float(trimesh.Trimesh(part.vertices, part.faces, process=False).area)
        per_model[key] = SurfaceBank.from_arrays(mm, normals, keys, part.center, part.radius, area, device)
    return per_model[key]


def clear_bank_cache(model: SurfSurg6D | None = None) -> None:
    if model is None:
        _CACHE.clear()
    else:
        _CACHE.pop(model, None)

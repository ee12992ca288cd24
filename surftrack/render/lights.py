"""Light sources of the renderer, in the OpenCV camera frame (mm)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Light:
    """A spot light (a point light when ``outer_deg`` >= 180).

    Irradiance falls off as ``(ref_distance / d)^2``, so ``intensity`` is the brightness at
    ``ref_distance`` mm on the spot axis.
    """

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    color: tuple[float, float, float] = (1.0, 0.98, 0.95)
    intensity: float = 1.0
    inner_deg: float = 25.0
    outer_deg: float = 60.0
    ref_distance: float = 80.0

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, dtype=np.float64)
        if np.linalg.norm(d) < 1e-9:
            raise ValueError("light direction must be non-zero")
        if not 0.0 <= self.inner_deg <= self.outer_deg:
            raise ValueError(f"need 0 <= inner_deg <= outer_deg, got {self.inner_deg}, {self.outer_deg}")
        object.__setattr__(self, "direction", tuple(d / np.linalg.norm(d)))


def endoscope_light(intensity: float = 1.0, offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
                    color: tuple[float, float, float] = (1.0, 0.97, 0.92)) -> Light:
    """The endoscope's own light: a wide spot at the lens looking down the optical axis."""
    return Light(position=offset, direction=(0.0, 0.0, 1.0), color=color, intensity=intensity,
                 inner_deg=30.0, outer_deg=75.0)

"""Procedural tissue surfaces: height fields with anatomy-like folds, tissue colours and vessels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter, map_coordinates, zoom
from scipy.spatial import cKDTree

from surftrack.instruments.part import Material
from surftrack.render import Renderer

# Linear-RGB base colours: pink peritoneum, red muscle, pale fat, liver-like brown-red.
TISSUE_PALETTE = np.array([
    [0.74, 0.26, 0.24], [0.62, 0.14, 0.12], [0.82, 0.52, 0.34], [0.50, 0.14, 0.12], [0.72, 0.32, 0.30],
])


@dataclass(eq=False)
class Tissue:
    """A tissue surface in its own frame: x, y across, z = depth offset (+z points away from a camera that
    looks down +z). Colour comes from ``texture`` (uint8 RGB, row 0 at y = -extent/2) at per-vertex ``uv``;
    ``height`` is the fine height field (texture resolution) the coarser mesh samples."""

    mesh: trimesh.Trimesh
    texture: np.ndarray
    uv: np.ndarray
    material: Material
    height: np.ndarray   # (ny, nx) height field, mm
    extent: tuple[float, float]

    def add_to(self, renderer: Renderer) -> int:
        """Upload into ``renderer`` (smooth normals, textured, no amodal mask); returns the instance id."""
        return renderer.add_mesh(self.mesh, self.material, amodal=False, uv=self.uv, texture=self.texture,
                                 crease_deg=180.0, name="tissue")

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Surface z at tissue-frame (x, y) by bilinear interpolation (edge values outside)."""
        ny, nx = self.height.shape
        w, h = self.extent
        gx = (np.asarray(x) + w / 2) / w * (nx - 1)
        gy = (np.asarray(y) + h / 2) / h * (ny - 1)
        return map_coordinates(self.height, [np.ravel(gy), np.ravel(gx)], order=1, mode="nearest").reshape(np.shape(x))


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Gaussian-filtered white noise scaled to [-1, 1]. Wide kernels are applied on a coarser grid and
    interpolated back (the result is band-limited anyway), which keeps big patches fast."""
    f = max(1, int(sigma // 3))
    if f == 1:
        n = gaussian_filter(rng.standard_normal(shape), sigma, mode="reflect")
    else:
        small = (shape[0] // f + 2, shape[1] // f + 2)
        n = zoom(gaussian_filter(rng.standard_normal(small), sigma / f, mode="reflect"), f, order=3)
        n = n[: shape[0], : shape[1]]
    return n / (np.abs(n).max() + 1e-12)


def _vessels(rng: np.random.Generator, w: float, h: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Points along random smooth curves (a walk with momentum), and each point's vessel radius."""
    pts, radii = [], []
    for _ in range(count):
        p = rng.uniform([-w / 2, -h / 2], [w / 2, h / 2])
        ang = rng.uniform(0, 2 * np.pi)
        r0 = rng.uniform(0.8, 2.2)
        steps = int(rng.integers(60, 200))
        for s in range(steps):
            ang += rng.normal(0.0, 0.12)
            p = p + 0.8 * np.array([np.cos(ang), np.sin(ang)])
            pts.append(p.copy())
            radii.append(r0 * (1.0 - 0.6 * s / steps))
            if rng.random() < 0.01:  # a branch: restart nearby with a thinner radius
                ang += rng.choice([-1, 1]) * rng.uniform(0.5, 1.0)
                r0 *= 0.7
    return np.asarray(pts), np.asarray(radii)


def procedural_tissue(rng: np.random.Generator, extent: tuple[float, float] = (280.0, 230.0),
                      spacing: float = 2.5, texel: float = 0.5, fold_depth: float = 14.0, vessels: int = 6) -> Tissue:
    """A random tissue patch ``extent`` mm wide with folds up to ``fold_depth`` mm deep and vessels.

    Geometry is a grid of about ``spacing`` mm (folds are far wider, so it need not be fine); colour,
    vessels and fine relief live in a texture of ``texel`` mm per pixel.
    """
    w, h = extent
    step = max(1, int(round(spacing / texel)))
    nx, ny = int(round(w / texel / step)) * step + 1, int(round(h / texel / step)) * step + 1
    spacing = texel
    xs, ys = np.linspace(-w / 2, w / 2, nx), np.linspace(-h / 2, h / 2, ny)
    X, Y = np.meshgrid(xs, ys)
    # Folds: a few elongated ridges and valleys, plus broad undulation and fine texture.
    Z = np.zeros_like(X)
    for _ in range(int(rng.integers(3, 7))):
        c = rng.uniform([-w / 2, -h / 2], [w / 2, h / 2])
        a = rng.uniform(0, np.pi)
        u = (X - c[0]) * np.cos(a) + (Y - c[1]) * np.sin(a)
        v = -(X - c[0]) * np.sin(a) + (Y - c[1]) * np.cos(a)
        su, sv = rng.uniform(25, 70), rng.uniform(6, 18)
        Z += rng.uniform(-1, 1) * fold_depth * np.exp(-0.5 * ((u / su) ** 2 + (v / sv) ** 2))
    Z += 0.35 * fold_depth * _smooth_noise(rng, Z.shape, sigma=18.0 / spacing)
    Z += 0.6 * _smooth_noise(rng, Z.shape, sigma=1.5 / spacing)
    # Colour: a palette mix varying across the patch, darker in valleys, with vessels on top.
    k = rng.choice(len(TISSUE_PALETTE), size=2, replace=False)
    mix = 0.5 + 0.5 * _smooth_noise(rng, Z.shape, sigma=25.0 / spacing)
    col = TISSUE_PALETTE[k[0]] * mix[..., None] + TISSUE_PALETTE[k[1]] * (1 - mix[..., None])
    col = col * (1.0 + 0.12 * _smooth_noise(rng, Z.shape, sigma=2.0 / spacing))[..., None]
    col *= (1.0 - 0.25 * np.clip(Z / max(fold_depth, 1e-6), 0, 1))[..., None]
    if vessels:
        vp, vr = _vessels(rng, w, h, vessels)
        d, idx = cKDTree(vp).query(np.stack([X.ravel(), Y.ravel()], -1), distance_upper_bound=6.0)
        near = np.isfinite(d)
        strength = np.zeros(X.size)
        # Soft profile at least one grid spacing wide, so vessels do not alias into dotted lines.
        width = np.maximum(vr[idx[near]], spacing)
        strength[near] = np.exp(-((d[near] / width) ** 2))
        vessel_col = np.array([0.45, 0.06, 0.10]) if rng.random() < 0.7 else np.array([0.30, 0.12, 0.35])
        s = strength.reshape(X.shape)[..., None] * 0.8
        col = col * (1 - s) + vessel_col * s
    texture = (np.clip(col, 0, 1) * 255).astype(np.uint8)
    Xc, Yc, Zc = X[::step, ::step], Y[::step, ::step], Z[::step, ::step]
    vertices = np.stack([Xc.ravel(), Yc.ravel(), Zc.ravel()], axis=-1)
    # Texture row 0 is y = -h/2; the renderer uploads rows flipped, so GL's v runs from the last row up.
    uv = np.stack([(Xc.ravel() + w / 2) / w, 1.0 - (Yc.ravel() + h / 2) / h], axis=-1)
    ny, nx = Xc.shape
    i = np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]
    i = i.ravel()
    # Faces wound so that their normals face -z (towards a camera looking down +z).
    faces = np.concatenate([np.stack([i, i + nx, i + 1], -1), np.stack([i + 1, i + nx, i + nx + 1], -1)])
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    material = Material(color=(1.0, 1.0, 1.0), metallic=0.0, roughness=float(rng.uniform(0.25, 0.45)))
    return Tissue(mesh, texture, uv, material, Z, (w, h))

"""Correspondence fields from RENDERED object coordinates: a ground truth for testing and benchmarking the
solver without a trained network.

The part is rendered at a known pose, cropped exactly as :class:`~surftrack.pose.PoseEstimator` crops a
detection box (the box of its rendered silhouette), and every silhouette pixel of the grid gets a
correspondence distribution: a Gaussian (``sigma_mm``) around the surface sample nearest its rendered
object coordinate plus Gaussian noise (``noise_mm``); a fraction ``outliers`` of the pixels point at
random surface samples instead. Written as queries and keys, ``q = [c / sigma^2, 1]`` and
``k = [p, -|p|^2 / (2 sigma^2)]``, so ``q . k = -|c - p|^2 / (2 sigma^2)`` up to a per-pixel constant:
the field is built by the same :func:`~surftrack.pose.correspondence.build_field` as the network's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from surftrack.geometry import PinholeCamera, box_from_bop, crop_affine, square_crop_box
from surftrack.instruments.part import Part
from surftrack.model.surfsurg6d import PartInfo, surface_bank
from surftrack.pose.correspondence import CorrField, build_field, grid_camera
from surftrack.pose.preset import Preset
from surftrack.pose.surface import SurfaceBank
from surftrack.synth.bop_writer import bbox_xywh


@dataclass
class RenderedProblem:
    field: CorrField
    bank: SurfaceBank
    K_grid: torch.Tensor
    box_side: float          # detection box's longer side in grid pixels
    R: np.ndarray            # true pose
    t: np.ndarray
    box: tuple[float, float, float, float]


def rendered_problem(part: Part, pose: np.ndarray, camera: PinholeCamera, preset: Preset, noise_mm: float = 0.1,
                     outliers: float = 0.3, sigma_mm: float = 0.4, crop_size: int = 224, box_scale: float = 1.2,
                     seed: int = 0, device: str | torch.device = "cpu") -> RenderedProblem:
    """See the module docstring. ``pose``: 4x4 model-to-camera (mm); the part must be in view."""
    from surftrack.render import Renderer

    info = PartInfo.from_part(1, "", part)
    coords, normals = surface_bank(info, preset.n_samples, seed=0)
    pts = coords.astype(np.float64) * info.radius + info.center
    keys = np.c_[pts, -(pts ** 2).sum(1) / (2 * sigma_mm ** 2)]
    bank = SurfaceBank.from_arrays(pts, normals, keys, info.center, info.radius, part.mesh.area, device)
    T = np.asarray(pose, np.float64)
    full = Renderer(camera.width, camera.height)
    crop = Renderer(crop_size, crop_size)
    try:
        iid = full.add_mesh(part.mesh)
        visible = full.render(camera, {iid: T}, lights=[], modalities={"instance"}).instance == iid
        if not visible.any():
            raise ValueError("the part is not in view")
        box = box_from_bop(bbox_xywh(visible))
        _, ccam = crop_affine(camera, square_crop_box(box, box_scale), (crop_size, crop_size))
        cid = crop.add_mesh(part.mesh)
        res = crop.render(ccam, {cid: T}, lights=[], modalities={"instance", "xyz"})
    finally:
        full.release()
        crop.release()
    d = preset.stride
    mask = (res.instance == cid)[::d, ::d]  # grid pixel i is crop pixel d * i
    g = mask.shape[0]
    active = np.flatnonzero(mask)
    rng = np.random.default_rng(seed)
    xyz = res.xyz[::d, ::d].reshape(-1, 3)[active].astype(np.float64)
    _, j = cKDTree(pts).query(xyz + rng.normal(0.0, noise_mm, xyz.shape))
    bad = rng.random(len(j)) < outliers
    j[bad] = rng.integers(0, len(pts), int(bad.sum()))
    query = np.zeros((4, g * g), np.float32)
    query[:3, active] = (pts[j] / sigma_mm ** 2).T
    query[3] = 1.0
    mask_logit = torch.from_numpy(np.where(mask, 6.0, -6.0).astype(np.float32)).to(device)
    gen = torch.Generator(device=device)
    gen.manual_seed(seed)
    field = build_field(mask_logit, torch.from_numpy(query).view(4, g, g).to(device), bank.keys, preset.alpha, d,
                        preset.mask_threshold, preset.min_active, preset.max_active, 4 * preset.n_hypotheses, gen)
    return RenderedProblem(field, bank, grid_camera(ccam.K, d), crop_size / box_scale / d, T[:3, :3].copy(),
                           T[:3, 3].copy(), box)

"""Scores of pose hypotheses against a correspondence field, all hypotheses at once.

A prefix of the part's surface samples is projected with every hypothesis into the grid. Samples whose
normal faces away from the camera are dropped; a per-hypothesis z-buffer (``scatter_reduce`` amin on the
flat index ``hypothesis * G + pixel``) drops the samples deeper than the nearest sample of their pixel by
more than ``depth_tol_px`` pixels' worth of depth (z / f; a slanted surface spans that much depth within
one pixel). The score is a per-pixel average over the G grid pixels of a log-likelihood ratio::

    score = 1/G * [ sum_c log p_bg(c) + integral over the predicted silhouette of (mask(c) + corr(c)) ]
    mask(c) = log p_fg(c) - log p_bg(c)          (p_fg = sigmoid(mask logit), each log floored at mask_floor)
    corr(c) = max(log(N * softmax_j(q_c . k_j)[j]), corr_floor)  at active pixels, 0 elsewhere

with j the surface point seen at c: ``corr`` is the correspondence log-likelihood against a uniform guess
(0 = no information). The integral is a Monte-Carlo sum over the visible samples, each weighted by the
pixel area its share of the surface projects to, ``(area / M) * fx * fy * |n . X| / z^3`` (X the
camera-frame point, n its normal). Counting pixels hit instead is biased by the sparse sampling (empty
pixels inside the silhouette favour poses that project larger) and is noisy (the hole pattern changes with
every small pose change); the weighted sum uses the same samples for every hypothesis and changes
smoothly with the pose. Visibility needs dense samples: with about one visible sample per pixel,
occluded samples show through the gaps and the visible area comes out ~10-15 % too large (about equally
for nearby poses); with ~8 samples per active pixel it is within a few percent (the 3x3 neighbourhood
test that would close the gaps fails on slanted surfaces). So the solver scores every hypothesis with
``prescore_density`` samples per active pixel and rescores the ``rescore_top`` best (and every refined
pose) with ``score_density``; both within [``min_score_samples``, bank size].

A sample's weight is capped at ``SAMPLE_AREA_CAP`` times the grid's pixels per sample (G / M):
a pose that brings a surface point to within a millimetre of the lens gives that one sample thousands of
pixels' worth of area, all read at the single pixel it lands on (a real case: a shaft estimate at
z = 0.1 mm scoring 30.6 against the true pose's 0.6, which then dragged the instrument fit). Where the
samples are that sparse the Monte-Carlo sum no longer measures the silhouette. The cap binds only where
the part's whole surface at that sample's depth would cover the grid many times over (the true pose's
largest weight in that crop: 1.5 G / M).
"""

from __future__ import annotations

import math

import torch

from surftrack.pose.correspondence import CorrField
from surftrack.pose.preset import Preset
from surftrack.pose.surface import SurfaceBank


_TABLE_MAX = 1 << 22
#: the most grid pixels one surface sample may stand for, in units of the grid's pixels per sample
SAMPLE_AREA_CAP = 16.0


def score_poses(R: torch.Tensor, t: torch.Tensor, field_: CorrField, bank: SurfaceBank, K_grid: torch.Tensor,
                preset: Preset, density: float | None = None) -> torch.Tensor:
    """Scores (H,) float64 of poses ``R`` (H, 3, 3), ``t`` (H, 3) (model-to-camera, mm); see the module
    docstring. ``K_grid``: intrinsics of the grid; ``density``: samples per active pixel (default
    ``preset.score_density``)."""
    dev = field_.query.device
    H = int(R.shape[0])
    out = torch.empty(H, dtype=torch.float64, device=dev)
    if H == 0:
        return out
    g, G = field_.g, field_.g * field_.g
    M = score_sample_count(preset.score_density if density is None else density, preset.min_score_samples,
                           len(field_.active), len(bank))
    P, Nrm = bank.points[:M].T.contiguous(), bank.normals[:M].T.contiguous()  # (3, M)
    nP = (P * Nrm).sum(0)
    contrast, s_bg = field_.mask_terms(preset.mask_floor)
    contrast = contrast.float()
    K = K_grid.to(dev, torch.float32)
    fpix = float(K[0, 0] + K[1, 1]) / 2.0
    w0 = bank.area / M * float(K[0, 0] * K[1, 1])
    w_cap = SAMPLE_AREA_CAP * G / M
    chunk = max(1, int(preset.score_chunk) // M)
    tol = preset.depth_tol_px / fpix
    # Correspondence log-ratios of every (active pixel, sample) pair when that table is small (the
    # prescoring pass), else computed for the visible pairs only.
    table = None
    if len(field_.active) * M <= _TABLE_MAX and H * M > _TABLE_MAX:
        table = (field_.query @ field_.keys[:M].T).sub_(field_.lse[:, None]).add_(math.log(field_.n_samples))
        table = table.clamp_(min=preset.corr_floor).view(-1)
    for s in range(0, H, chunk):
        Rc, tc = R[s:s + chunk].float(), t[s:s + chunk].float()
        h = Rc.shape[0]
        uvz = torch.matmul(K @ Rc, P).add_((tc @ K.T)[:, :, None])  # (h, 3, M): (u z, v z, z)
        z = uvz[:, 2]
        nx = torch.addmm(nP[None], torch.einsum("hji,hj->hi", Rc, tc), Nrm)  # n_cam . X_cam = n . (p + R^T t)
        front = (nx < 0) & (z > 1e-3)
        iz = torch.where(front, z, torch.ones_like(z)).reciprocal_()
        ix = uvz[:, 0].mul(iz).add_(0.5).floor_()
        iy = uvz[:, 1].mul(iz).add_(0.5).floor_()
        ok = front & (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g)
        pix = torch.where(ok, iy.mul_(g).add_(ix), 0.0).long()
        flat = torch.where(ok, pix + torch.arange(0, h * G, G, device=dev)[:, None], h * G)
        zz = torch.where(ok, z, math.inf)
        zbuf = torch.full((h * G + 1,), math.inf, device=dev)
        zbuf.scatter_reduce_(0, flat.view(-1), zz.view(-1), "amin")
        vis = ok & (zz <= torch.take(zbuf, flat).addcmul_(zz, torch.full_like(zz, tol)))
        # projected pixel area of each visible sample's share of the surface: (area / M) fx fy |n . X| / z^3
        w = torch.where(vis, nx.mul_(iz * iz * iz).mul_(-w0).clamp_(max=w_cap), 0.0)
        total = (w * torch.take(contrast, pix)).sum(1, dtype=torch.float64)
        rows = torch.take(field_.pos, pix)
        idx = torch.nonzero((vis & (rows >= 0)).view(-1))[:, 0]
        if len(idx):
            r, m = rows.view(-1)[idx], idx % M
            ratio = table[r * M + m] if table is not None else field_.corr_ratio(r, m, preset.corr_floor)
            total.index_add_(0, idx // M, (w.view(-1)[idx] * ratio).double())
        out[s:s + h] = (total + s_bg) / G
    return out


def score_sample_count(density: float, minimum: int, n_active: int, n_bank: int) -> int:
    return int(min(max(density * n_active, minimum), n_bank))

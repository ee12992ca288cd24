"""Pose hypotheses: 4-point correspondence sets drawn from ``corr ** alpha``, solved by the batched P3P,
pruned by point spread, the 4th point, plausible depth and surface normals facing the camera."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from surftrack.pose.correspondence import CorrField
from surftrack.pose.p3p import p4p
from surftrack.pose.preset import Preset
from surftrack.pose.surface import SurfaceBank

_PAIRS = torch.tensor([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


@dataclass
class Hypotheses:
    """Surviving poses (float64, model-to-camera, mm) and how many remained after each stage."""

    R: torch.Tensor
    t: torch.Tensor
    counts: dict[str, int] = field(default_factory=dict)
    relaxed: bool = False  # nothing survived the pruning: these are the unpruned valid solutions


def draw_correspondences(field_: CorrField, n: int, generator: torch.Generator | None = None
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` draws of (active row, surface sample) from the joint distribution ``corr ** alpha``: a pixel
    by its row sum, then the next sample of that pixel's pre-drawn pool (cyclically, if a pixel is drawn
    more often than its pool holds)."""
    lw = field_.pixel_log_weights()
    w = torch.exp(lw - lw.max())
    if not bool(torch.isfinite(w).all()) or float(w.sum()) <= 0:
        w = torch.ones_like(w)
    rows = torch.multinomial(w, n, replacement=True, generator=generator)
    order = torch.argsort(rows, stable=True)
    srt = rows[order]
    rank = torch.empty_like(rows)
    rank[order] = torch.arange(n, device=rows.device) - torch.searchsorted(srt, srt)
    return rows, field_.pool[rows, rank % field_.pool.shape[1]]


def _min_pair_dist(x: torch.Tensor) -> torch.Tensor:
    """(H, 4, D) -> (H,) smallest distance between two of the 4 points."""
    p = _PAIRS.to(x.device)
    return torch.linalg.vector_norm(x[:, p[:, 0]] - x[:, p[:, 1]], dim=-1).amin(-1)


def sample_hypotheses(field_: CorrField, bank: SurfaceBank, K_grid: torch.Tensor, box_side: float,
                      preset: Preset, generator: torch.Generator | None = None) -> Hypotheses:
    """Draw ``preset.n_hypotheses`` 4-point sets, solve them and prune; at most ``preset.max_scored``
    survivors are returned. ``K_grid``: grid intrinsics (3, 3); ``box_side``: the detection box's longer
    side in grid pixels (for the plausible depth range)."""
    dev = field_.query.device
    n = int(preset.n_hypotheses)
    rows, samples = draw_correspondences(field_, 4 * n, generator)
    rows, samples = rows.view(n, 4), samples.view(n, 4)
    uv = field_.active_xy()[rows]  # (n, 4, 2) float64
    P = bank.points[samples].double()
    counts = {"drawn": n}
    keep = _min_pair_dist(uv) >= preset.min_spread_2d * math.sqrt(len(field_.active))
    keep &= _min_pair_dist(P) >= preset.min_spread_3d * bank.radius
    idx = torch.nonzero(keep)[:, 0]
    counts["spread"] = int(len(idx))
    K = K_grid.to(dev, torch.float64)
    R, t, err, valid = p4p(uv[idx], P[idx], K)
    counts["solved"] = int(valid.sum())
    # Plausible depth of the part centre from the box: a sphere of radius r spans ~ 2 r f / z pixels.
    f = float(K[0, 0] + K[1, 1]) / 2.0
    z_est = f * 2.0 * bank.radius / max(float(box_side), 1e-6)
    c = torch.as_tensor(bank.center, dtype=torch.float64, device=dev)
    zc = (R[:, 2] * c).sum(-1) + t[:, 2]
    lo, hi = preset.depth_range
    plausible = valid & (err <= preset.max_4th_error) & (zc >= lo * z_est) & (zc <= hi * z_est + bank.radius)
    # The 4 surface points must face the camera: (R n) . (R p + t) / |R p + t| <= slack.
    Pi = P[idx]
    X = torch.einsum("hij,hkj->hki", R, Pi) + t[:, None]
    Nc = torch.einsum("hij,hkj->hki", R, bank.normals[samples[idx]].double())
    cos = (Nc * X).sum(-1) / torch.linalg.vector_norm(X, dim=-1).clamp(min=1e-9)
    plausible &= (cos <= preset.normal_slack).all(-1)
    counts["plausible"] = int(plausible.sum())
    relaxed = counts["plausible"] == 0
    sel = torch.nonzero(valid if relaxed else plausible)[:, 0][: preset.max_scored]
    counts["scored"] = int(len(sel))
    return Hypotheses(R[sel], t[sel], counts, relaxed)

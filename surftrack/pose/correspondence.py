"""Correspondence distributions of one crop on the downsampled grid (SurfEmb's inference).

The network's mask logits and queries are average-pooled by ``stride`` with a window centred on crop
pixel ``stride * i`` (so grid pixel i IS crop pixel ``stride * i`` geometrically and the grid camera is
``diag(1/stride, 1/stride, 1) @ K_crop``). For every *active* grid pixel a (mask probability above the
threshold) and every surface sample j::

    corr(a, j) = softmax_j(q_a . k_j) * sigmoid(mask_a)

Hypotheses are drawn from ``corr ** alpha``. The (A, N) matrix is never stored: it is swept once in row
chunks that stay in cache (CPU) or in one piece (GPU), giving per active pixel the log-normalisers, the
arg-max sample and a pool of surface samples drawn from its row of ``corr ** alpha`` (hypotheses then
pick pixels by their total weight and take the next sample of the pixel's pool). Logits that scoring
needs later are recomputed as ``q_a . k_j`` for the pairs it looks at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F


def pool_to_grid(mask_logit: torch.Tensor, query: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, S, S) mask logits and (B, E, S, S) queries -> (B, g, g) and (B, E, g, g), g = (S - 1) // stride + 1,
    by centred average pooling (window 2 * (stride // 2) + 1, padding excluded from the average)."""
    if stride == 1:
        return mask_logit, query
    k, p = 2 * (stride // 2) + 1, stride // 2
    pool = lambda x: F.avg_pool2d(x, k, stride, p, count_include_pad=False)  # noqa: E731
    return pool(mask_logit[:, None])[:, 0], pool(query)


def grid_camera(K_crop, stride: int) -> torch.Tensor:
    """Intrinsics (3, 3) float64 of the grid whose pixel i is crop pixel ``stride * i``."""
    K = torch.as_tensor(K_crop, dtype=torch.float64).clone()
    K[:2] /= float(stride)
    return K


def _chunk_rows(n_cols: int, device: torch.device) -> int:
    # CPU: ~256k logits (1 MB) per chunk stays in L2 across the passes; GPU: everything at once.
    return 1 << 30 if device.type == "cuda" else max(8, (1 << 18) // max(n_cols, 1))


@dataclass
class CorrField:
    """The correspondence distribution of one crop; see the module docstring. Grid pixels are flat
    indices ``y * g + x``; ``active`` (A,) are those with correspondences, ``pos`` (G,) maps a grid pixel
    to its row in ``active`` (-1 if inactive). Per active pixel: ``query`` (A, E), ``log_pm`` = log
    sigmoid(mask), ``lse`` = logsumexp_j(q . k_j), ``lse_alpha`` = logsumexp_j(alpha q . k_j), ``best``
    = arg-max surface sample and ``pool`` (A, P) samples drawn with replacement from the row's
    ``corr ** alpha``."""

    g: int
    stride: int
    alpha: float
    mask_logit: torch.Tensor
    active: torch.Tensor
    pos: torch.Tensor
    query: torch.Tensor
    keys: torch.Tensor
    log_pm: torch.Tensor
    lse: torch.Tensor
    lse_alpha: torch.Tensor
    best: torch.Tensor
    pool: torch.Tensor

    @property
    def n_samples(self) -> int:
        return int(self.keys.shape[0])

    def active_xy(self) -> torch.Tensor:
        """(A, 2) float64 grid coordinates (x, y) of the active pixels."""
        return torch.stack([self.active % self.g, self.active // self.g], -1).to(torch.float64)

    def mask_terms(self, floor: float) -> tuple[torch.Tensor, float]:
        """Per-pixel ``log p(fg) - log p(bg)`` (G,) and ``sum log p(bg)`` over the grid, logs floored."""
        fg = F.logsigmoid(self.mask_logit).clamp(min=floor)
        bg = F.logsigmoid(-self.mask_logit).clamp(min=floor)
        return fg - bg, float(bg.sum())

    def corr_ratio(self, rows: torch.Tensor, samples: torch.Tensor, floor: float) -> torch.Tensor:
        """``log(N * softmax_j(q_a . k_j)[j])`` floored at ``floor``, for active rows a and samples j."""
        logit = (self.query[rows] * self.keys[samples]).sum(-1)
        return (logit - self.lse[rows] + math.log(self.n_samples)).clamp(min=floor)

    def pixel_log_weights(self) -> torch.Tensor:
        """log sum_j corr(a, j) ** alpha per active pixel (A,)."""
        return self.alpha * (self.log_pm - self.lse) + self.lse_alpha


def select_active(mask_logit: torch.Tensor, threshold: float, min_active: int, max_active: int) -> torch.Tensor:
    """Flat indices (sorted) of the grid pixels with sigmoid(mask) > ``threshold``, completed to
    ``min_active`` and cut to ``max_active`` by mask confidence."""
    flat = mask_logit.reshape(-1)
    lt = math.log(threshold / (1.0 - threshold))
    above = flat > lt
    n = int(above.sum())
    k = min(max(n, min_active), max_active, flat.numel())
    if k == n:
        return torch.nonzero(above)[:, 0]
    return torch.topk(flat, k, sorted=False).indices.sort().values


def build_field(mask_grid: torch.Tensor, query_grid: torch.Tensor, keys: torch.Tensor, alpha: float, stride: int,
                threshold: float = 0.5, min_active: int = 16, max_active: int = 3000, n_draws: int = 40000,
                generator: torch.Generator | None = None) -> CorrField:
    """Field of one crop from the pooled network output: ``mask_grid`` (g, g) logits, ``query_grid``
    (E, g, g), the part's surface keys (N, E). ``n_draws``: correspondences the hypotheses will draw
    (sizes the per-pixel sample pools, :func:`pool_size`)."""
    g = int(mask_grid.shape[-1])
    # An fp16 overflow must not reach multinomial: on CUDA a NaN there is a device-side assert.
    mask = torch.nan_to_num(mask_grid.reshape(-1).float(), nan=-30.0, posinf=30.0, neginf=-30.0)
    active = select_active(mask, threshold, min_active, max_active)
    Q = torch.nan_to_num(query_grid.reshape(query_grid.shape[0], -1)[:, active].T.float(), nan=0.0,
                         posinf=1e4, neginf=-1e4).contiguous()
    keys = keys.float()
    kT = keys.T.contiguous()
    A, dev = len(active), Q.device
    lse, lse_a = torch.empty(A, device=dev), torch.empty(A, device=dev)
    best = torch.empty(A, dtype=torch.long, device=dev)
    draws = torch.empty(A, pool_size(n_draws, A), dtype=torch.long, device=dev)
    step = _chunk_rows(keys.shape[0], dev)
    for s in range(0, A, step):
        L = Q[s:s + step] @ kT
        m, best[s:s + step] = L.max(1)
        # exp(-50) relative to the best sample is nothing, and denormal floats (below ~1e-38, where
        # alpha * (L - m) < -87) make exp ~6x slower on the CPU.
        L.sub_(m[:, None]).clamp_(min=-50.0)
        Ea = torch.exp(L * alpha)  # two exps are cheaper than exp + pow on the CPU
        lse[s:s + step] = m + L.exp_().sum(1).log()
        lse_a[s:s + step] = alpha * m + Ea.sum(1).log()
        draws[s:s + step] = torch.multinomial(Ea, draws.shape[1], replacement=True, generator=generator)
    pos = torch.full((g * g,), -1, dtype=torch.long, device=dev)
    pos[active] = torch.arange(A, device=dev)
    return CorrField(g, int(stride), float(alpha), mask, active, pos, Q, keys, F.logsigmoid(mask[active]),
                     lse, lse_a, best, draws)


def pool_size(n_draws: int, n_active: int) -> int:
    """Samples to pre-draw per active pixel: about twice a pixel's share of ``n_draws``, within [8, 256]."""
    return int(min(256, max(8, math.ceil(2.0 * n_draws / max(n_active, 1)))))

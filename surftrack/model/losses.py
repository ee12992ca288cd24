"""Training losses of SurfEmb and SurfSurg6D (plain torch).

Equation numbers are those of the SurfSurg6D paper (Shen et al.,
*SurfSurg6D: Geometry Consistent Dense Correspondence for Textureless Surgical Instrument Pose
Estimation*); its own text confirms them ("Compared to Eq.5 [the baseline] ... the penalized one in Eq.7"):

* Eq. 3  -- InfoNCE over ``[<q, k+>, <q, k-_1>, ..., <q, k-_M>]``               -> :func:`info_nce`
* Eq. 4  -- binary cross-entropy of the mask logit                               -> :func:`mask_bce`
* Eq. 5  -- baseline ``L = L_InfoNCE + L_M`` (the SurfEmb objective)
* Eq. 6  -- penalty ``p_ij(alpha) = 1 - alpha * log(||c_j - c_i|| + 1)``          -> :func:`pen_log_weights`
* Eq. 7  -- penalised InfoNCE, ``p_ij`` multiplies ``exp(<q_i, k_j>)`` in the
  denominator                                                                    -> :func:`pen_nce`
* Eq. 8/9 -- geometry-embedding consistency with ``w_ij = max(m, exp(-lambda d_ij))`` -> :func:`consistency_loss`
* Eq. 10 -- ``L(alpha, beta) = L_penNCE(alpha) + L_M + beta * L_con``            -> :func:`surfsurg6d_loss`

Conventions: logits are RAW dot products -- no L2 normalisation and no
temperature (SurfEmb; the query norm acts as a confidence). Surface coordinates are NORMALISED object
coordinates ``(p - centre) / radius`` of the mesh's bounding sphere, so they lie in the unit ball and every
pairwise distance is ``<= 2``.

Exactness guarantees: ``pen_log_weights(alpha=0)`` is exactly zero and ``surfsurg6d_loss(alpha=0, beta=0)``
returns a total that is bit-for-bit ``mask_bce + info_nce_batched`` (the SurfEmb baseline).
"""

from __future__ import annotations

import math
import numbers

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "ALPHA_MAX",
    "consistency_loss",
    "info_nce",
    "info_nce_batched",
    "mask_bce",
    "pairwise_distances",
    "pen_log_weights",
    "pen_nce",
    "surfsurg6d_loss",
]

#: Largest diameter of the unit ball: the maximum distance between two normalised coordinates.
MAX_NORMALISED_DISTANCE = 2.0
#: Exclusive upper bound on the penNCE ``alpha``: ``p_ij = 1 - alpha * ln(d + 1) > 0`` for all
#: ``d <= 2`` iff ``alpha < 1 / ln(3) ~= 0.9102``.
ALPHA_MAX = 1.0 / math.log(1.0 + MAX_NORMALISED_DISTANCE)


# ----------------------------------------------------------------------------------------------- checks
def _check_float(name: str, t: Tensor) -> None:
    if not isinstance(t, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if not t.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {t.dtype}")


def _check_ndim(name: str, t: Tensor, ndim: int, layout: str) -> None:
    _check_float(name, t)
    if t.dim() != ndim:
        raise ValueError(f"{name} must have shape {layout} ({ndim} dims), got {tuple(t.shape)}")


def _check_scalar(name: str, value, *, low: float | None = None, high: float | None = None,
                  high_inclusive: bool = True) -> float:
    if isinstance(value, Tensor):
        if value.numel() != 1:
            raise ValueError(f"{name} must be a scalar, got a tensor of shape {tuple(value.shape)}")
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if low is not None and value < low:
        raise ValueError(f"{name} must be >= {low}, got {value}")
    if high is not None and (value > high if high_inclusive else value >= high):
        raise ValueError(f"{name} must be {'<=' if high_inclusive else '<'} {high}, got {value}")
    return value


def _check_alpha(alpha, floor: float = 0.0) -> float:
    """Validated alpha: any alpha >= 0 with a positive ``floor`` on p_ij, else 0 <= alpha < 1/ln 3."""
    if isinstance(alpha, Tensor):
        if alpha.numel() != 1:
            raise ValueError(f"alpha must be a scalar, got a tensor of shape {tuple(alpha.shape)}")
        alpha = alpha.item()
    if isinstance(alpha, bool) or not isinstance(alpha, numbers.Real):
        raise TypeError(f"alpha must be a real number, got {type(alpha).__name__}")
    alpha = float(alpha)
    if not 0.0 <= floor < 1.0:
        raise ValueError(f"penNCE floor must be in [0, 1), got {floor!r}")
    if floor > 0.0 and 0.0 <= alpha < float("inf"):
        return alpha
    if not (0.0 <= alpha < ALPHA_MAX):  # also rejects NaN
        raise ValueError(
            f"penNCE alpha must satisfy 0 <= alpha < 1/ln(3) = {ALPHA_MAX:.6f} so that "
            f"p_ij = 1 - alpha*ln(||c_j - c_i|| + 1) > 0 for every pair of normalised coordinates "
            f"(distances <= {MAX_NORMALISED_DISTANCE:g}); got alpha = {alpha!r}")
    return alpha


# ---------------------------------------------------------------------------------------------- helpers
def pairwise_distances(a: Tensor, b: Tensor) -> Tensor:
    """Euclidean distances ``D[..., i, j] = ||a[..., i, :] - b[..., j, :]||``.

    Shapes: ``a`` (..., N, D), ``b`` (..., M, D) -> (..., N, M); leading dims broadcast.

    Uses :func:`torch.cdist` in its exact (non-matmul) mode: no cancellation error, and its backward
    returns a zero (sub)gradient where a distance is exactly 0, so duplicate points and ``i = j`` give
    finite gradients.
    """
    return torch.cdist(a, b, p=2.0, compute_mode="donot_use_mm_for_euclid_dist")


# --------------------------------------------------------------------------------------------- InfoNCE
def info_nce_batched(q: Tensor, k_pos: Tensor, k_neg: Tensor,
                     neg_log_weight: Tensor | None = None) -> Tensor:
    """SurfEmb InfoNCE (paper Eq. 3), optionally with log-weighted negatives (Eq. 7), over a batch.

    Shapes:
        q:              (B, N, E) query embeddings of N sampled query pixels per image.
        k_pos:          (B, N, E) key embeddings of the pixels' true surface points.
        k_neg:          (B, M, E) key embeddings of M negative surface points, shared by all N queries
                        of the same image.
        neg_log_weight: (B, N, M) or None. ``log w_ij`` ADDED to the negative logits, i.e. a
                        multiplication of ``exp(l_neg_ij)`` by ``w_ij`` in the softmax denominator.
    Returns:
        scalar: the mean over all B*N queries (all images hold N queries, so this equals the mean of the
        per-image means).

    Formula (raw dot products, no normalisation, no temperature)::

        l_pos_i  = <q_i, k+_i>                      l_neg_ij = <q_i, k-_j> + neg_log_weight_ij
        loss_i   = -log( exp(l_pos_i) / (exp(l_pos_i) + sum_j exp(l_neg_ij)) )
                 = logsumexp([l_pos_i, l_neg_i1, ..., l_neg_iM]) - l_pos_i

    which is the cross-entropy of ``[l_pos, l_neg]`` with target class 0. With ``neg_log_weight =
    log p_ij`` this is ``L_penNCE`` (Eq. 7); with ``None`` it is ``L_InfoNCE`` (Eq. 3).
    """
    _check_ndim("q", q, 3, "(B, N, E)")
    _check_ndim("k_pos", k_pos, 3, "(B, N, E)")
    _check_ndim("k_neg", k_neg, 3, "(B, M, E)")
    if k_pos.shape != q.shape:
        raise ValueError(f"k_pos must have the shape of q {tuple(q.shape)} (B, N, E), got {tuple(k_pos.shape)}")
    B, N, E = q.shape
    if k_neg.shape[0] != B or k_neg.shape[2] != E:
        raise ValueError(f"k_neg must have shape (B={B}, M, E={E}), got {tuple(k_neg.shape)}")
    if N == 0:
        raise ValueError("q holds no queries (N = 0): the mean over queries is undefined")
    M = k_neg.shape[1]
    l_pos = (q * k_pos).sum(-1, keepdim=True)          # (B, N, 1)
    l_neg = torch.bmm(q, k_neg.transpose(1, 2))         # (B, N, M)
    if neg_log_weight is not None:
        _check_ndim("neg_log_weight", neg_log_weight, 3, "(B, N, M)")
        if neg_log_weight.shape != (B, N, M):
            raise ValueError(f"neg_log_weight must have shape (B={B}, N={N}, M={M}), "
                             f"got {tuple(neg_log_weight.shape)}")
        l_neg = l_neg + neg_log_weight
    logits = torch.cat([l_pos, l_neg], dim=-1)          # (B, N, 1 + M), class 0 = positive
    return (torch.logsumexp(logits, dim=-1) - l_pos.squeeze(-1)).mean()


def info_nce(q: Tensor, k_pos: Tensor, k_neg: Tensor, neg_log_weight: Tensor | None = None) -> Tensor:
    """SurfEmb InfoNCE (paper Eq. 3) for the queries of ONE image.

    Shapes: ``q`` (N, E), ``k_pos`` (N, E), ``k_neg`` (M, E) shared by all queries, optional
    ``neg_log_weight`` (N, M) added to the negative logits. Returns a scalar, the mean over the N queries
    of ``-log(exp(<q_i,k+_i>) / (exp(<q_i,k+_i>) + sum_j exp(<q_i,k-_j> + neg_log_weight_ij)))``.
    See :func:`info_nce_batched` (this is that function with B = 1).
    """
    _check_ndim("q", q, 2, "(N, E)")
    _check_ndim("k_pos", k_pos, 2, "(N, E)")
    _check_ndim("k_neg", k_neg, 2, "(M, E)")
    if neg_log_weight is not None:
        _check_ndim("neg_log_weight", neg_log_weight, 2, "(N, M)")
        neg_log_weight = neg_log_weight.unsqueeze(0)
    return info_nce_batched(q.unsqueeze(0), k_pos.unsqueeze(0), k_neg.unsqueeze(0), neg_log_weight)


# ----------------------------------------------------------------------------------------------- penNCE
def pen_log_weights(c_query: Tensor, c_neg: Tensor, alpha: float, *, check: bool = True,
                    floor: float = 0.0) -> Tensor:
    """Log of the SurfSurg6D hard-negative penalty weights (paper Eq. 6).

    Shapes: ``c_query`` (..., N, 3) normalised object coordinates of the queries' TRUE surface points
    ``c_i``; ``c_neg`` (..., M, 3) normalised coordinates ``c_j`` of the negatives (leading dims
    broadcast). Returns ``log p_ij`` with shape (..., N, M), where (Eq. 6)::

        p_ij(alpha) = 1 - alpha * log(||c_j - c_i|| + 1)        (natural log)

    ``p_ij`` multiplies ``exp(<q_i, k_j>)`` in the InfoNCE denominator (Eq. 7); adding ``log p_ij`` to the
    negative logits is the same thing in log space.

    Direction: ``p_ij`` DEcreases with distance. A spatially near, non-matching point (a HARD negative:
    similar-looking surface) has ``d ~ 0`` and ``p ~ 1``, i.e. it keeps its full InfoNCE weight, while a far
    (EASY) negative gets ``p < 1`` and contributes less to the denominator. This is the paper's "penalizing
    the contribution of easy negatives in the softmax denominator", i.e. hard negatives are up-weighted
    RELATIVE to easy ones; no weight ever exceeds 1.

    ``alpha`` must satisfy ``0 <= alpha < 1/ln(3) ~= 0.910`` (:data:`ALPHA_MAX`): normalised coordinates lie
    in the unit ball, distances are ``<= 2`` and ``p_ij > 0`` for all of them iff ``alpha * ln(3) < 1``;
    otherwise :class:`ValueError`. (The paper's experiments quote alpha = 1, for which ``p_ij <= 0`` once
    ``d >= e - 1 ~= 1.72``, where Eq. 7 is undefined -- hence the stricter bound.) ``alpha = 0`` returns
    exact zeros, so penNCE(0) is InfoNCE bit-for-bit.

    ``floor`` > 0 replaces that bound by ``p_ij = max(p_ij, floor)``, which admits any alpha >= 0: the
    paper's alpha = 1 needs it (``configs/train/paper.yaml`` uses floor 0.01). ``floor = 0`` keeps Eq. 6
    exactly.

    With ``check=True`` (default) a non-positive ``p_ij`` -- only possible if coordinates are NOT
    normalised (distance > 2) -- raises :class:`ValueError` instead of silently giving NaN/-inf. This costs
    one host-device sync; pass ``check=False`` inside compiled / CUDA-graph code.
    """
    alpha = _check_alpha(alpha, floor)
    _check_float("c_query", c_query)
    _check_float("c_neg", c_neg)
    if c_query.dim() < 2 or c_query.shape[-1] != 3:
        raise ValueError(f"c_query must have shape (..., N, 3), got {tuple(c_query.shape)}")
    if c_neg.dim() < 2 or c_neg.shape[-1] != 3:
        raise ValueError(f"c_neg must have shape (..., M, 3), got {tuple(c_neg.shape)}")
    try:
        lead = torch.broadcast_shapes(c_query.shape[:-2], c_neg.shape[:-2])
    except RuntimeError as e:
        raise ValueError(f"leading dims of c_query {tuple(c_query.shape)} and c_neg {tuple(c_neg.shape)} "
                         f"do not broadcast") from e
    out_shape = (*lead, c_query.shape[-2], c_neg.shape[-2])
    dtype = torch.promote_types(c_query.dtype, c_neg.dtype)
    if alpha == 0.0:
        return torch.zeros(out_shape, dtype=dtype, device=c_query.device)
    d = pairwise_distances(c_query, c_neg)             # (..., N, M)
    p = 1.0 - alpha * torch.log1p(d)
    if floor > 0.0:
        p = p.clamp_min(floor)
    if check and p.numel() > 0 and not bool((p > 0).all()):
        raise ValueError(
            f"penNCE weight p_ij <= 0 (max distance {d.max().item():.4g} > 2): c_query / c_neg must be "
            f"NORMALISED object coordinates (unit ball) for alpha = {alpha}")
    return torch.log(p)


def pen_nce(q: Tensor, k_pos: Tensor, k_neg: Tensor, c_query: Tensor, c_neg: Tensor, alpha: float,
            *, check: bool = True, floor: float = 0.0) -> Tensor:
    """Penalised InfoNCE ``L_penNCE(alpha)`` (paper Eq. 7), batched.

    Shapes: ``q``, ``k_pos`` (B, N, E); ``k_neg`` (B, M, E); ``c_query`` (B, N, 3) normalised coordinates
    of the queries' true surface points; ``c_neg`` (B, M, 3) those of the negatives. Returns a scalar::

        L = mean_{b,i} -log( exp(<q_i,k+_i>) / (exp(<q_i,k+_i>) + sum_j p_ij exp(<q_i,k-_j>)) ),
        p_ij = 1 - alpha * log(||c_j - c_i|| + 1)

    = ``info_nce_batched(q, k_pos, k_neg, pen_log_weights(c_query, c_neg, alpha))``; ``alpha = 0`` is
    exactly :func:`info_nce_batched` (no weights are added at all). ``floor``: see :func:`pen_log_weights`.
    """
    alpha = _check_alpha(alpha, floor)
    _check_ndim("c_query", c_query, 3, "(B, N, 3)")
    _check_ndim("c_neg", c_neg, 3, "(B, M, 3)")
    _check_ndim("q", q, 3, "(B, N, E)")
    _check_ndim("k_neg", k_neg, 3, "(B, M, E)")
    if c_query.shape[:2] != q.shape[:2]:
        raise ValueError(f"c_query must have shape (B, N, 3) = ({q.shape[0]}, {q.shape[1]}, 3) "
                         f"matching q {tuple(q.shape)}, got {tuple(c_query.shape)}")
    if c_neg.shape[:2] != k_neg.shape[:2]:
        raise ValueError(f"c_neg must have shape (B, M, 3) = ({k_neg.shape[0]}, {k_neg.shape[1]}, 3) "
                         f"matching k_neg {tuple(k_neg.shape)}, got {tuple(c_neg.shape)}")
    log_w = None if alpha == 0.0 else pen_log_weights(c_query, c_neg, alpha, check=check, floor=floor).to(q.dtype)
    return info_nce_batched(q, k_pos, k_neg, log_w)


# ------------------------------------------------------------------------------------------ consistency
def consistency_loss(coords: Tensor, emb: Tensor, lam: float = 10.0, m: float = 0.01,
                     normalize: bool = True) -> Tensor:
    """Geometry-embedding consistency of the key field ``L_con`` (paper Eqs. 8-9).

    Shapes: ``coords`` (..., P, 3) normalised object coordinates ``c_i`` of P surface points; ``emb``
    (..., P, E) their key embeddings ``E_i = M_phi(c_i)``; the leading dims must be equal (a batch).
    Returns a scalar: the mean over the leading dims of::

        L_con = 2 / (P (P - 1)) * sum_{i<j} w_ij * (||c_i - c_j|| - ||E_i - E_j||)^2      (Eq. 8)
        w_ij  = max(m, exp(-lam * ||c_i - c_j||))                                          (Eq. 9)

    Paper defaults ``lam = 10``, ``m = 0.01`` (distances in normalised units; in mm nearly every weight
    would sit at the floor ``m``).

    ``normalize`` (default True): the paper states (below Eq. 2) that "both E_i and E~_i are normalized
    embeddings", so ``E`` is L2-normalised (``F.normalize``, eps 1e-12) before ``||E_i - E_j||``; both
    distances then lie in [0, 2]. Note the InfoNCE terms here deliberately use RAW dot products (SurfEmb);
    the normalisation is applied only inside this loss. ``normalize=False`` uses the raw key embeddings.

    Only pairs ``i < j`` enter (upper triangle, ``i = j`` excluded). Distances come from
    :func:`pairwise_distances`, whose backward gives a zero subgradient at distance 0, so gradients are
    finite also for duplicate points (``i != j`` with identical coordinates/embeddings). Cost: two
    (..., P, P) distance matrices, no (P, P, E) intermediate.
    """
    _check_float("coords", coords)
    _check_float("emb", emb)
    lam = _check_scalar("lam", lam, low=0.0)
    m = _check_scalar("m", m, low=0.0, high=1.0)
    if coords.dim() < 2 or coords.shape[-1] != 3:
        raise ValueError(f"coords must have shape (..., P, 3), got {tuple(coords.shape)}")
    if emb.dim() != coords.dim() or emb.shape[:-1] != coords.shape[:-1]:
        raise ValueError(f"emb must have shape (..., P, E) with the leading dims and P of coords "
                         f"{tuple(coords.shape)}, got {tuple(emb.shape)}")
    P = coords.shape[-2]
    if P < 2:
        raise ValueError(f"consistency_loss needs at least 2 points (P >= 2), got P = {P}")
    if normalize:
        emb = F.normalize(emb, p=2.0, dim=-1, eps=1e-12)
    dc = pairwise_distances(coords, coords)            # (..., P, P)
    de = pairwise_distances(emb, emb)                  # (..., P, P)
    iu, ju = torch.triu_indices(P, P, offset=1, device=coords.device).unbind(0)
    dc = dc[..., iu, ju]                               # (..., P(P-1)/2), pairs i < j
    de = de[..., iu, ju].to(dc.dtype)
    w = torch.clamp(torch.exp(-lam * dc), min=m)       # max(m, exp(-lam d))
    return (w * (dc - de).square()).mean()


# --------------------------------------------------------------------------------------------- mask BCE
def mask_bce(logits: Tensor, target: Tensor) -> Tensor:
    """Binary cross-entropy of the mask logit (paper Eq. 4), averaged over ALL pixels.

    Shapes: ``logits`` (...) raw mask logits (e.g. (B, H, W)); ``target`` the same shape, {0, 1} (bool,
    integer or float; soft targets in [0, 1] are accepted). Returns the scalar
    ``-mean_u [y_u log sigmoid(x_u) + (1 - y_u) log(1 - sigmoid(x_u))]`` computed stably with
    :func:`torch.nn.functional.binary_cross_entropy_with_logits`.
    """
    _check_float("logits", logits)
    if not isinstance(target, Tensor):
        raise TypeError(f"target must be a torch.Tensor, got {type(target).__name__}")
    if target.shape != logits.shape:
        raise ValueError(f"target must have the shape of logits {tuple(logits.shape)}, got {tuple(target.shape)}")
    if logits.numel() == 0:
        raise ValueError("mask_bce got empty tensors")
    return F.binary_cross_entropy_with_logits(logits, target.to(logits.dtype), reduction="mean")


# ------------------------------------------------------------------------------------------------ total
def surfsurg6d_loss(mask_logits: Tensor, mask_target: Tensor,
                    q: Tensor, k_pos: Tensor, k_neg: Tensor,
                    c_query: Tensor, c_neg: Tensor,
                    key_coords: Tensor | None = None, key_emb: Tensor | None = None,
                    alpha: float = 0.0, beta: float = 0.0,
                    lam: float = 10.0, m: float = 0.01, normalize: bool = True,
                    check: bool = True, pen_floor: float = 0.0) -> dict[str, Tensor]:
    """Full SurfSurg6D objective ``L(alpha, beta) = L_penNCE(alpha) + L_M + beta * L_con`` (paper Eq. 10).

    Shapes:
        mask_logits, mask_target: (B, H, W) (any equal shapes) -> :func:`mask_bce` (Eq. 4).
        q, k_pos:   (B, N, E) query embeddings and keys of their true surface points.
        k_neg:      (B, M, E) keys of the M negatives of each image.
        c_query:    (B, N, 3) normalised coordinates of the queries' true surface points.
        c_neg:      (B, M, 3) normalised coordinates of the negatives.
        key_coords, key_emb: (B, P, 3), (B, P, E) the surface points over which the consistency loss is
                    computed. Default (both None): the sampled negatives ``(c_neg, k_neg)`` -- the set
                    ``V~`` of sampled surface points the paper's Eq. 8 sums over (uniform by area, so
                    pairs cover the whole surface). Pass e.g. ``cat([c_neg, c_query], 1)`` /
                    ``cat([k_neg, k_pos], 1)`` to include the positives.
        alpha:      penNCE strength, 0 <= alpha < 1/ln 3 (see :func:`pen_log_weights`).
        beta:       weight of the consistency loss, >= 0.
        lam, m, normalize: see :func:`consistency_loss`.
    Returns:
        dict with scalar tensors ``"mask"`` (L_M), ``"nce"`` (L_penNCE(alpha); plain InfoNCE if alpha = 0),
        ``"con"`` (L_con; an exact 0 that is NOT computed when beta = 0) and ``"total"``.

    Exactness: with ``alpha = beta = 0`` no weights are added and the consistency term is skipped, so
    ``total`` is bit-for-bit ``mask_bce(mask_logits, mask_target) + info_nce_batched(q, k_pos, k_neg)``,
    the SurfEmb baseline (Eq. 5).
    """
    alpha = _check_alpha(alpha, pen_floor)
    beta = _check_scalar("beta", beta, low=0.0)
    if (key_coords is None) != (key_emb is None):
        raise ValueError("pass both key_coords and key_emb, or neither (then the negatives are used)")
    l_mask = mask_bce(mask_logits, mask_target)
    l_nce = pen_nce(q, k_pos, k_neg, c_query, c_neg, alpha, check=check, floor=pen_floor)
    total = l_mask + l_nce
    if beta != 0.0:
        if key_coords is None:
            key_coords, key_emb = c_neg, k_neg
        l_con = consistency_loss(key_coords, key_emb, lam=lam, m=m, normalize=normalize)
        total = total + beta * l_con
    else:
        l_con = torch.zeros((), dtype=l_nce.dtype, device=l_nce.device)
    return {"mask": l_mask, "nce": l_nce, "con": l_con, "total": total}

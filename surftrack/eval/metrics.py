"""Pose, threshold-curve and mask metrics on numpy arrays.

The pose errors follow the definitions of bop_toolkit's ``bop_toolkit_lib/pose_error.py`` (Hodan et al.,
"BOP: Benchmark for 6D Object Pose Estimation", ECCV 2018, and "BOP Challenge 2020 on 6D Object
Localization", ECCVW 2020); ADD / ADD-S are from Hinterstoisser et al., ACCV 2012, and the area under the
accuracy-threshold curve is the VOCap of the YCB-Video toolbox (Xiang et al., "PoseCNN", RSS 2018).

Conventions: poses are model-to-camera, ``x_cam = R @ x_model + t``; points are (N, 3) in mm in the object
frame; ``R`` is 3x3, ``t`` has shape (3,) or (3, 1) in mm; ``K`` is the 3x3 pinhole camera matrix in
pixels (OpenCV axes, points must lie in front of the camera, z > 0). Errors are returned as Python floats.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Union

import numpy as np
from scipy.spatial import ConvexHull, cKDTree
from scipy.spatial.distance import pdist

from surftrack.geometry import project_points, se3, transform_points

#: A symmetry is either a mapping {"R": 3x3, "t": (3,) or (3, 1)} (bop_toolkit's
#: ``misc.get_symmetry_transformations`` format) or a 4x4 homogeneous matrix, both in the object frame.
Symmetry = Union[Mapping[str, np.ndarray], np.ndarray]


# ----------------------------------------------------------------------------------------- input checks
def _rotation(R: np.ndarray, name: str) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 rotation matrix, got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError(f"{name} contains non-finite values")
    return R


def _translation(t: np.ndarray, name: str) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64)
    if t.shape not in ((3,), (3, 1), (1, 3)):
        raise ValueError(f"{name} must be a translation of shape (3,) or (3, 1), got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} contains non-finite values")
    return t.reshape(3)


def _points(pts: np.ndarray, name: str = "pts") -> np.ndarray:
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty (N, 3) array of model points, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name} contains non-finite values")
    return pts


def _camera(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be a 3x3 camera matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise ValueError("K contains non-finite values")
    return K


def _errors(errors: Iterable[float], name: str = "errors") -> np.ndarray:
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    if e.size == 0:
        raise ValueError(f"{name} is empty")
    if np.any(np.isnan(e)) or np.any(e < 0):
        raise ValueError(f"{name} must be non-negative (inf allowed for failures), NaN or negative found")
    return e


def _symmetries(syms: Sequence[Symmetry] | None) -> list[tuple[np.ndarray, np.ndarray]]:
    if syms is None:
        return [(np.eye(3), np.zeros(3))]
    out = []
    for i, s in enumerate(syms):
        if isinstance(s, Mapping):
            if "R" not in s or "t" not in s:
                raise ValueError(f"symmetry {i} must have keys 'R' and 't'")
            out.append((_rotation(s["R"], f"syms[{i}]['R']"), _translation(s["t"], f"syms[{i}]['t']")))
        else:
            T = np.asarray(s, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"symmetry {i} must be a {{'R', 't'}} mapping or a 4x4 matrix, got {T.shape}")
            out.append((_rotation(T[:3, :3], f"syms[{i}][:3, :3]"), _translation(T[:3, 3], f"syms[{i}][:3, 3]")))
    if not out:
        raise ValueError("syms is empty; pass None for an object without symmetries (identity only)")
    return out


# ---------------------------------------------------------------------------------------------- helpers
def _posed(pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Model points (N, 3) checked and mapped to the camera: ``x' = R x + t`` (bop_toolkit
    ``misc.transform_pts_Rt``)."""
    return transform_points(se3(_rotation(R, "R"), _translation(t, "t")), _points(pts))


def _pixels(pts: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of model points: ``u ~ K (R x + t)``, divided by depth
    (bop_toolkit ``misc.project_pts``)."""
    return project_points(_camera(K), _posed(pts, R, t))


# ------------------------------------------------------------------------------------------ pose errors
def add(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray, pts: np.ndarray) -> float:
    """ADD, Average Distance of model points (Hinterstoisser et al. 2012; bop_toolkit ``add``):

    ``e = mean_x || (R_e x + t_e) - (R_g x + t_g) ||`` in the units of ``pts`` (mm).
    """
    p_e = _posed(pts, R_e, t_e)
    p_g = _posed(pts, R_g, t_g)
    return float(np.linalg.norm(p_e - p_g, axis=1).mean())


def adds(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray, pts: np.ndarray) -> float:
    """ADD-S / ADI, Average Distance to the closest model point, for indistinguishable views
    (Hinterstoisser et al. 2012; bop_toolkit ``adi``):

    ``e = mean_{x1} min_{x2} || (R_g x1 + t_g) - (R_e x2 + t_e) ||``, the nearest neighbours searched with
    a cKDTree built on the estimated points (as bop_toolkit). ``adds <= add`` always.
    """
    p_e = _posed(pts, R_e, t_e)
    p_g = _posed(pts, R_g, t_g)
    dists, _ = cKDTree(p_e).query(p_g, k=1)
    return float(np.mean(dists))


def re(R_e: np.ndarray, R_g: np.ndarray) -> float:
    """Rotation error in degrees, the geodesic angle (bop_toolkit ``re``):

    ``e = arccos((tr(R_e R_g^T) - 1) / 2)``, the cosine clipped to [-1, 1] against round-off.
    """
    R_e = _rotation(R_e, "R_e")
    R_g = _rotation(R_g, "R_g")
    cos = 0.5 * (np.trace(R_e @ R_g.T) - 1.0)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def te(t_e: np.ndarray, t_g: np.ndarray) -> float:
    """Translation error ``e = || t_e - t_g ||`` in the units of t (mm) (bop_toolkit ``te``)."""
    return float(np.linalg.norm(_translation(t_g, "t_g") - _translation(t_e, "t_e")))


def mssd(
    R_e: np.ndarray,
    t_e: np.ndarray,
    R_g: np.ndarray,
    t_g: np.ndarray,
    pts: np.ndarray,
    syms: Sequence[Symmetry] | None = None,
) -> float:
    """MSSD, Maximum Symmetry-aware Surface Distance (BOP 2020; bop_toolkit ``mssd``):

    ``e = min_{S in syms} max_x || (R_e x + t_e) - (R_g (R_S x + t_S) + t_g) ||`` (mm).
    ``syms`` None means no symmetry (the identity only).
    """
    p_e = _posed(pts, R_e, t_e)
    R_g = _rotation(R_g, "R_g")
    t_g = _translation(t_g, "t_g")
    errs = []
    for R_s, t_s in _symmetries(syms):
        p_g = _posed(pts, R_g @ R_s, R_g @ t_s + t_g)
        errs.append(np.linalg.norm(p_e - p_g, axis=1).max())
    return float(min(errs))


def mspd(
    R_e: np.ndarray,
    t_e: np.ndarray,
    R_g: np.ndarray,
    t_g: np.ndarray,
    K: np.ndarray,
    pts: np.ndarray,
    syms: Sequence[Symmetry] | None = None,
) -> float:
    """MSPD, Maximum Symmetry-aware Projection Distance in pixels (BOP 2020; bop_toolkit ``mspd``):

    ``e = min_{S in syms} max_x || pi(K, R_e, t_e, x) - pi(K, R_g R_S, R_g t_S + t_g, x) ||``.
    ``syms`` None means no symmetry (the identity only).
    """
    q_e = _pixels(pts, K, R_e, t_e)
    R_g = _rotation(R_g, "R_g")
    t_g = _translation(t_g, "t_g")
    errs = []
    for R_s, t_s in _symmetries(syms):
        q_g = _pixels(pts, K, R_g @ R_s, R_g @ t_s + t_g)
        errs.append(np.linalg.norm(q_e - q_g, axis=1).max())
    return float(min(errs))


def proj(R_e: np.ndarray, t_e: np.ndarray, R_g: np.ndarray, t_g: np.ndarray, K: np.ndarray, pts: np.ndarray) -> float:
    """Projection error, the 2D-projection metric of Brachmann et al. 2016 (bop_toolkit ``proj``):

    ``e = mean_x || pi(K, R_e, t_e, x) - pi(K, R_g, t_g, x) ||`` in pixels.
    """
    q_e = _pixels(pts, K, R_e, t_e)
    q_g = _pixels(pts, K, R_g, t_g)
    return float(np.linalg.norm(q_e - q_g, axis=1).mean())


# ------------------------------------------------------------------------------------------- diameters
def diameter_max_pairwise(pts: np.ndarray) -> float:
    """Object diameter, BOP convention: the largest distance between two model points
    ``max_{i,j} || x_i - x_j ||`` (bop_toolkit ``misc.calc_pts_diameter``, ``models_info.json``).

    Evaluated on the convex-hull vertices (the farthest pair always lies on the hull); falls back to all
    points when the hull is degenerate (fewer than 4 points, coplanar or collinear).
    """
    pts = _points(pts)
    if pts.shape[0] == 1:
        return 0.0
    cand = pts
    if pts.shape[0] > 64:
        try:
            cand = pts[ConvexHull(pts).vertices]
        except Exception:  # scipy.spatial.QhullError on flat / degenerate point sets
            cand = pts
    return float(pdist(cand).max())


def diameter_bbox_diagonal(pts: np.ndarray) -> float:
    """Object "diameter", SurgRIPE convention: the diagonal of the axis-aligned bounding box of the model
    points in the object frame, ``|| max_i x_i - min_i x_i ||``. It is >= the BOP max-pairwise diameter.
    """
    pts = _points(pts)
    return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))


# ---------------------------------------------------------------------------- threshold rates and curves
def add_threshold_rate(errors: Iterable[float], diameter: float, frac: float = 0.1) -> float:
    """ADD-10 style accuracy: fraction of poses with ``error < frac * diameter`` (STRICT ``<``;
    Hinterstoisser et al. 2012 use 10% of the diameter). Say which diameter is passed:
    :func:`diameter_max_pairwise` (BOP) or :func:`diameter_bbox_diagonal` (SurgRIPE).
    """
    e = _errors(errors)
    if not np.isfinite(diameter) or diameter <= 0:
        raise ValueError(f"diameter must be a positive finite number, got {diameter}")
    if not np.isfinite(frac) or frac <= 0:
        raise ValueError(f"frac must be a positive finite number, got {frac}")
    return float(np.mean(e < frac * diameter))


def threshold_rate(errors: Iterable[float], threshold: float) -> float:
    """Fraction of errors strictly below ``threshold`` (e.g. 5 deg / 5 cm style criteria)."""
    e = _errors(errors)
    return float(np.mean(e < threshold))


def auc(errors: Iterable[float], max_threshold: float = 5.0) -> float:
    """Area under the accuracy-threshold curve of ADD (or ADD-S) errors on [0, max_threshold], normalised to
    [0, 1]: the VOCap of the YCB-Video toolbox (Xiang et al. 2018, ``evaluate_poses_keyframe.m`` /
    the PoseCNN / DenseFusion Python port).

    With the n errors sorted, ``e_(1) <= ... <= e_(n)``, and those above ``max_threshold`` dropped, the
    curve is sampled at ``rec = [0, e_(1), ..., e_(m), max]`` with accuracies ``prec = [0, 1/n, ..., m/n,
    m/n]``, made monotone, and integrated with right-endpoint rectangles over the distinct ``rec``:

    ``AUC = sum_i (rec_i - rec_{i-1}) * prec_i / max``.

    The rectangle rule credits each pose already on the interval that ends at its own error, so VOCap
    equals the exact mean of ``accuracy(ADD < d)`` over d uniform in [0, max],
    ``(1/n) sum_i max(0, max - e_i) / max``, plus ``e_(m) / (n max)`` (``e_(m)`` the largest error <= max).
    The toolbox definition is kept for comparability with published numbers. Infinite errors (failures)
    count as misses.
    """
    e = _errors(errors)
    if not np.isfinite(max_threshold) or max_threshold <= 0:
        raise ValueError(f"max_threshold must be a positive finite number, got {max_threshold}")
    n = e.size
    rec = np.sort(e)
    prec = np.arange(1, n + 1, dtype=np.float64) / n
    keep = rec <= max_threshold  # the toolbox sets errors > max to inf and drops non-finite entries
    rec, prec = rec[keep], prec[keep]
    if rec.size == 0:
        return 0.0
    mrec = np.concatenate(([0.0], rec, [max_threshold]))
    mpre = np.maximum.accumulate(np.concatenate(([0.0], prec, [prec[-1]])))
    i = np.flatnonzero(mrec[1:] != mrec[:-1]) + 1
    return float(np.sum((mrec[i] - mrec[i - 1]) * mpre[i]) / max_threshold)


# ----------------------------------------------------------------------------------------------- masks
def dice(mask_a: np.ndarray, mask_b: np.ndarray) -> float:
    """Dice coefficient (Sorensen-Dice) of two binary masks of the same shape:

    ``D = 2 |A & B| / (|A| + |B|)``, defined as 1.0 when both masks are empty.
    """
    a = np.asarray(mask_a)
    b = np.asarray(mask_b)
    if a.shape != b.shape:
        raise ValueError(f"masks must have the same shape, got {a.shape} and {b.shape}")
    a = a.astype(bool)
    b = b.astype(bool)
    total = int(a.sum()) + int(b.sum())
    if total == 0:
        return 1.0
    return float(2.0 * np.logical_and(a, b).sum() / total)

"""Bounded refinement of the best hypothesis and the final inlier PnP, on the arg-max correspondences.

Each active grid pixel contributes its most likely surface sample. A refinement round takes the pixels
that the current pose reprojects within ``inlier_px``, runs a few Levenberg-Marquardt iterations
(``cv2.solvePnPRefineLM``) from the current pose, and keeps the result only if the step stays within
``max_step_deg`` / ``max_step_radius`` part radii and the score improves (SurfEmb's unbounded BFGS
refiner is known to diverge on custom data, its issue #30). The final inlier PnP alternates inlier
selection and LM (``final_rounds`` times) from the kept pose; it is kept unless it leaves the same bounds
or lowers the score by more than ``score_tol``. That tolerance is absolute on the per-pixel score: the
Monte-Carlo score moves by a few hundredths between poses a fraction of a degree apart, while the
least-squares fit to hundreds of inliers is the more precise of the two, and a diverging fit loses far
more (half a millimetre sideways costs about 0.3).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from surftrack.geometry import project_points, se3, transform_points
from surftrack.pose.preset import Preset


@dataclass
class Refined:
    R: np.ndarray
    t: np.ndarray
    score: float
    n_inliers: int
    rounds_kept: int
    final_kept: bool


def reprojection_errors(R: np.ndarray, t: np.ndarray, pts: np.ndarray, uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel distances (A,) between model points ``pts`` (A, 3) mm projected at (R, t) through ``K`` and
    their pixels ``uv`` (A, 2); inf for points not in front of the camera."""
    X = transform_points(se3(R, t), pts)
    err = np.linalg.norm(project_points(K, X) - uv, axis=1)
    return np.where(X[:, 2] > 1e-6, err, np.inf)


def lm_refine(R: np.ndarray, t: np.ndarray, pts: np.ndarray, uv: np.ndarray, K: np.ndarray,
              iters: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``iters`` LM iterations of the reprojection error from (R, t); None if OpenCV fails."""
    rvec, _ = cv2.Rodrigues(np.asarray(R, np.float64))
    tvec = np.asarray(t, np.float64).reshape(3, 1).copy()
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(iters), 1e-10)
    try:
        rvec, tvec = cv2.solvePnPRefineLM(np.ascontiguousarray(pts, np.float64), np.ascontiguousarray(uv, np.float64),
                                          np.asarray(K, np.float64), None, rvec, tvec, crit)
    except cv2.error:
        return None
    R2, _ = cv2.Rodrigues(rvec)
    t2 = tvec.reshape(3)
    if not (np.all(np.isfinite(R2)) and np.all(np.isfinite(t2))):
        return None
    return R2, t2


def _within(R0, t0, R1, t1, preset: Preset, radius: float) -> bool:
    cos = np.clip((np.trace(R0 @ R1.T) - 1.0) / 2.0, -1.0, 1.0)
    return bool(np.degrees(np.arccos(cos)) <= preset.max_step_deg
                and np.linalg.norm(t1 - t0) <= preset.max_step_radius * radius)


def refine_pose(R: np.ndarray, t: np.ndarray, score: float, pts: np.ndarray, uv: np.ndarray, K: np.ndarray,
                radius: float, preset: Preset, score_fn: Callable[[np.ndarray, np.ndarray], float]
                ) -> Refined:
    """Refine (R, t) with score ``score``. ``pts`` (A, 3) mm / ``uv`` (A, 2) grid px: the arg-max
    correspondences; ``K``: grid intrinsics; ``score_fn(R, t)`` scores one pose."""
    thr = preset.inlier_px
    kept = 0
    for _ in range(preset.refine_rounds):
        inl = reprojection_errors(R, t, pts, uv, K) < thr
        if inl.sum() < preset.min_inliers:
            break
        cand = lm_refine(R, t, pts[inl], uv[inl], K, preset.lm_iters)
        if cand is None or not _within(R, t, *cand, preset, radius):
            break
        s = score_fn(*cand)
        if not s > score:
            break
        (R, t), score, kept = cand, s, kept + 1
    final = False
    Rf, tf = R, t
    for _ in range(preset.final_rounds):  # inliers -> LM until the inlier set settles
        inl = reprojection_errors(Rf, tf, pts, uv, K) < thr
        if inl.sum() < preset.min_inliers:
            break
        cand = lm_refine(Rf, tf, pts[inl], uv[inl], K, preset.final_lm_iters)
        if cand is None or not _within(R, t, *cand, preset, radius):
            break
        Rf, tf = cand
        final = True
    if final:
        s = score_fn(Rf, tf)
        if s >= score - preset.score_tol:
            R, t, score = Rf, tf, s
        else:
            final = False
    n_inl = int((reprojection_errors(R, t, pts, uv, K) < thr).sum())
    return Refined(np.asarray(R, np.float64), np.asarray(t, np.float64), float(score), n_inl, kept, final)

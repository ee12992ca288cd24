"""Test-time crop views: one detection box seen through several shifted crops, each solved on its own, and
the poses merged into one.

A part's pose from one crop carries a large random error: a different solver seed alone moves a 100-image
ADD-10 by several points, and the network's correspondences change with where the part sits in the crop.
Crops whose centres are shifted by a few percent of their side see the same pixels at other places of
the network's input and are solved with other random draws, so their errors are partly independent.
:func:`merge_views` keeps the poses that agree in rotation with the one most others agree with (a
mode: a view that flipped the part or locked onto a wrong hypothesis is left out) and averages them:
the chordal mean of their rotations and the mean of their translations.

The offsets (:func:`view_offsets`) are fixed, not random: view 0 is the unshifted crop, then the four
diagonal shifts, then the four axis-aligned ones.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from surftrack.geometry import rotation_angle_deg

#: Crop-centre offsets in units of the shift, in the order views are added.
VIEW_PATTERN = ((0, 0), (1, 1), (-1, -1), (1, -1), (-1, 1), (1, 0), (-1, 0), (0, 1), (0, -1))
MAX_VIEWS = len(VIEW_PATTERN)


def view_offsets(views: int, shift: float) -> list[tuple[float, float]]:
    """The (dx, dy) crop-centre offsets of ``views`` crops, in units of the crop's side (``shift`` each)."""
    if not 1 <= int(views) <= MAX_VIEWS:
        raise ValueError(f"views must be between 1 and {MAX_VIEWS}, got {views}")
    return [(dx * float(shift), dy * float(shift)) for dx, dy in VIEW_PATTERN[:int(views)]]


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (n, 3, 3): the rotation nearest their arithmetic mean."""
    U, _, Vt = np.linalg.svd(np.sum(np.asarray(Rs, np.float64), axis=0))
    d = 1.0 if np.linalg.det(U @ Vt) >= 0 else -1.0
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def merge_views(Rs: Sequence[np.ndarray], ts: Sequence[np.ndarray], scores: Sequence[float],
                radius_deg: float) -> tuple[np.ndarray, np.ndarray, float, int, np.ndarray]:
    """One pose from the poses of one box's views: ``(R, t, score, reference, members)``.

    ``reference`` is the index of the view with the most views within ``radius_deg`` of its rotation
    (itself included; ties go to the higher score), ``members`` the indices of the views within
    ``radius_deg`` of it. R is their chordal mean rotation, t their mean translation, score their mean."""
    Rs = np.asarray(Rs, np.float64).reshape(-1, 3, 3)
    ts = np.asarray(ts, np.float64).reshape(-1, 3)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if not len(Rs) == len(ts) == len(scores) >= 1:
        raise ValueError(f"need one rotation, translation and score per view, got {len(Rs)}, {len(ts)}, "
                         f"{len(scores)}")
    close = rotation_angle_deg(Rs[:, None], Rs[None, :]) < float(radius_deg)
    support = close.sum(axis=1).astype(np.float64)
    finite = np.where(np.isfinite(scores), scores, -np.inf)
    order = np.lexsort((-finite, -support))  # most support first, then the highest score
    ref = int(order[0])
    members = np.flatnonzero(close[ref])
    return (mean_rotation(Rs[members]), ts[members].mean(axis=0), float(np.mean(scores[members])), ref,
            members)

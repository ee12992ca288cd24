"""The trocar (remote centre of motion) of a tracked instrument, located from its measured shaft axes.

A laparoscopic or robotic instrument enters through a trocar: however it moves, its shaft axis passes
through that point, fixed in the camera frame while the endoscope holds still. :class:`Trocar` collects
the shaft axes of independent measurements (the estimator's poses of the shaft on keyframes), locates
the point closest to them (robust least squares, Cauchy in each axis's standard deviation at the point,
started from the best of the points where pairs of axes meet) with its covariance, and gives the
constraint "the axis passes through it" as a 2D measurement of an axis (:meth:`Trocar.residual`), which
:class:`~surftrack.track.instrument.InstrumentKalman` fuses on every frame. The point's error is one
error shared by all frames, fused each frame as if new: the state grows more certain across its shaft
than it should (the floor bounds that). When the constraint is refused ``patience`` times in a row
(the camera moved, or the first estimate was wrong), the point and the axes behind it are forgotten
and located again from the axes that follow; likewise when that many new axes in a row miss it.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from scipy.optimize import least_squares

from surftrack.geometry.transforms import skew
from surftrack.instruments import estimate_trocar

__all__ = ["Trocar"]


class Trocar:
    """The trocar of one instrument instance (camera frame, mm).

    ``after``: axes needed before the point is used; ``history``: axes kept (the latest);
    ``axis_std_mm``, ``axis_std_deg``: an axis measurement's position and direction uncertainty (a point
    ``s`` mm along it is off by ``sqrt(std_mm^2 + (s std_rad)^2)``: far from the measured part the
    direction's error dominates); ``floor_mm``: how far a real shaft strays from the point (the trocar's
    play in the abdominal wall, the model's error), added to the constraint's standard deviation;
    ``max_std_mm``: a point less certain than this across the axes is not used; ``patience``: refusals
    of the constraint, or new axes missing the point, in a row after which it is forgotten;
    ``behind_mm``: the trocar lies at least this far behind each measured axis point (proximal, where
    the shaft comes from: an instrument that barely moves has axes that all pass near its own parts
    too, a minimum the point must not fall into)."""

    def __init__(self, after: int = 8, history: int = 200, axis_std_mm: float = 3.0, axis_std_deg: float = 5.0,
                 floor_mm: float = 2.0, max_std_mm: float = 20.0, patience: int = 10, behind_mm: float = 20.0):
        self.after, self.floor_mm = after, floor_mm
        self.axis_var_mm2, self.axis_var_rad2 = axis_std_mm ** 2, math.radians(axis_std_deg) ** 2
        self.max_std_mm, self.patience, self.behind_mm = max_std_mm, patience, behind_mm
        self.axes: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=history)
        self.point: np.ndarray | None = None
        self.cov: np.ndarray | None = None
        self.refused = 0
        self.missed: list[tuple[np.ndarray, np.ndarray]] = []  # the latest axes in a row that missed the point

    def add_axis(self, origin: np.ndarray, direction: np.ndarray) -> None:
        """A measured shaft axis: the line through ``origin`` (3,) mm (the measured part's axis point)
        along ``direction`` (3,); the point is located again from all kept axes."""
        d = np.asarray(direction, np.float64)
        axis = (np.asarray(origin, np.float64).copy(), d / np.linalg.norm(d))
        if self.point is not None:
            # axes that keep missing the point (beyond 3 of their standard deviations) mean the camera
            # moved: after ``patience`` in a row, only those are kept and the point is located afresh
            v = self.point - axis[0]
            s = float(axis[1] @ v)
            miss = np.linalg.norm(v - axis[1] * s) > 3.0 * math.sqrt(self.axis_var_mm2 + s * s * self.axis_var_rad2)
            self.missed = self.missed + [axis] if miss else []
            if len(self.missed) >= self.patience:
                self.axes = deque(self.missed, maxlen=self.axes.maxlen)
                self.missed, self.point, self.cov = [], None, None
                if len(self.axes) >= self.after:
                    self._locate()
                return
        self.axes.append(axis)
        if len(self.axes) >= self.after:
            self._locate()

    def _offsets(self, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(each axis's offset (n, 3) to ``c`` across it, in its standard deviations at ``c``; ``c``'s
        position along each axis (n,) mm; those standard deviations (n,) mm)."""
        O = np.array([o for o, _ in self.axes])
        D = np.array([d for _, d in self.axes])
        V = c - O
        s = np.einsum("ij,ij->i", V, D)
        sd = np.sqrt(self.axis_var_mm2 + s * s * self.axis_var_rad2)
        return (V - D * s[:, None]) / sd[:, None], s, sd

    def _normalised(self, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(each axis's distance from ``c`` in its own standard deviations, those variances mm^2)."""
        off, _, sd = self._offsets(c)
        return np.linalg.norm(off, axis=1), sd * sd

    def _locate(self) -> None:
        """The point minimising the axes' robust (Cauchy, in standard deviations) distances, each axis
        measured in its own standard deviation at the point, started from the best of the points where
        pairs of axes pass closest (a plain least-squares start is dragged by wrong axes towards the
        measured parts, near which every axis passes); its covariance the inverse of the information,
        scaled up by the residuals' excess over their variances."""
        c = self._start()
        if c is None:
            self.point = self.cov = None
            return
        def scaled(p: np.ndarray) -> np.ndarray:
            off, s, sd = self._offsets(p)
            ahead = np.maximum(s + self.behind_mm, 0.0) / sd  # in front of where it may be
            return np.concatenate([off.ravel(), ahead])

        c = least_squares(scaled, c, loss="cauchy", f_scale=2.0, x_scale=10.0).x
        r, var = self._normalised(c)
        robust = 1.0 / (1.0 + (r / 2.0) ** 2)
        A = sum(w / v * (np.eye(3) - np.outer(d, d)) for w, v, (_, d) in zip(robust, var, self.axes))
        excess = max(float(np.sum(robust * r ** 2)) / max(2.0 * float(robust.sum()) - 3.0, 1.0), 1.0)
        cov = excess * np.linalg.inv(A)
        # what matters is the point's spread across the axes (along them it is free): the largest one
        d_mean = np.mean([d for _, d in self.axes], axis=0)
        d_mean /= np.linalg.norm(d_mean)
        Pp = np.eye(3) - np.outer(d_mean, d_mean)
        if not np.all(np.isfinite(cov)) or math.sqrt(max(np.linalg.eigvalsh(Pp @ cov @ Pp)[-1], 0.0)) > self.max_std_mm:
            self.point = self.cov = None
            return
        self.point, self.cov = c, 0.5 * (cov + cov.T)

    def _start(self, pairs: int = 64) -> np.ndarray | None:
        """The point nearest two axes, over random pairs at least 1 deg apart, with the lowest robust
        cost over all axes (None when no pair pivots that much)."""
        axes = list(self.axes)
        if len(axes) < 2:
            return None
        rng = np.random.default_rng(len(axes))  # repeatable
        best, best_cost = None, math.inf
        for _ in range(pairs):
            i, j = rng.choice(len(axes), 2, replace=False)
            (o1, d1), (o2, d2) = axes[i], axes[j]
            if abs(float(d1 @ d2)) > math.cos(math.radians(1.0)):
                continue
            c = estimate_trocar([(_frame(d1), o1), (_frame(d2), o2)])
            if np.median([d @ (c - o) for o, d in axes]) > -self.behind_mm:
                continue
            cost = float(np.sum(np.log1p((self._normalised(c)[0] / 2.0) ** 2)))
            if cost < best_cost:
                best, best_cost = c, cost
        return best

    def residual(self, origin: np.ndarray, direction: np.ndarray, R: np.ndarray, a: np.ndarray, u: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The constraint on an axis through ``origin`` along unit ``direction`` that is the line through
        ``a`` along ``u`` in a part's frame (rotation ``R``; body perturbations): (y (2,), J (2, 6), cov
        (2, 2) mm^2) with ``h = U (I - d d^T)(c - o)`` the point's offset from the axis in two directions
        ``U`` across it, ``y = -h`` the innovation (what the offset must change by; 0 when the axis passes
        through the point) and ``J`` the derivative of ``h`` in the part's pose error (position mm, body
        rotation rad). None while the point is unknown."""
        if self.point is None:
            return None
        d = direction
        U = _frame(d)[:, :2].T  # two unit vectors across the axis
        v = self.point - origin
        s = float(d @ v)
        J = np.zeros((2, 6))
        # o moves with the position step and with the rotation about the part's origin (lever a), d with
        # the rotation; their parts along d vanish under U (U d = 0)
        J[:, 0:3] = -U
        J[:, 3:6] = U @ R @ (skew(a) + s * skew(u))
        cov = U @ self.cov @ U.T + np.eye(2) * self.floor_mm ** 2
        return -(U @ v), J, cov

    def refuse(self) -> None:
        """The state refused the constraint (gated out): after ``patience`` in a row, forget the point."""
        self.refused += 1
        if self.refused >= self.patience:
            self.axes.clear()
            self.point = self.cov = None
            self.refused, self.missed = 0, []

    def accept(self) -> None:
        self.refused = 0


def _frame(d: np.ndarray) -> np.ndarray:
    """A rotation whose z axis is the unit ``d``: an axis as :func:`~surftrack.instruments.estimate_trocar`
    takes it (with a point of the line as the translation)."""
    x = np.cross(d, [1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.cross(d, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(d, x), d], axis=1)



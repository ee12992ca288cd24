"""Error-state constant-velocity Kalman filter for one rigid part's pose (model-to-camera, mm, radians).

State (12): ``[t (3), v (3), dtheta (3), omega (3)]`` in mm, mm/s, rad, rad/s. filterpy's
:class:`~filterpy.kalman.KalmanFilter` does the linear algebra; the nominal rotation ``R_ref`` is kept
outside the filter (never a quaternion in a filterpy state, notes section 5).

Conventions
-----------
* Rotation error is a RIGHT / body perturbation: ``R = R_ref @ so3_exp(dtheta)``. The measurement residual
  is therefore ``so3_log(R_ref.T @ R_meas)`` (a small vector even when the absolute rotation passes through
  pi, so there is no wrap-around problem) and ``omega`` is the body-frame angular velocity:
  ``R(t + dt) = R(t) @ so3_exp(omega * dt)``.
* Translation ``t`` and velocity ``v`` are in the camera frame: ``t(t + dt) = t + v * dt``.
* Predict: the nominal is propagated exactly (``R_ref <- R_ref exp(omega dt)``, so constant-velocity motion
  is extrapolated exactly); the error transition for ``dtheta`` is ``exp(-omega dt)`` (i.e.
  ``R(omega dt)^T``) and ``d dtheta / d omega = I dt`` (right Jacobian approximated by identity). The error
  mean stays 0 after the nominal is moved.
* Process noise: white-noise acceleration model per axis,
  ``Q = q * [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` with ``q = accel_std_mm_s2**2`` (mm^2/s^3) for (t, v) and
  ``q = ang_accel_std_rad_s2**2`` (rad^2/s^3) for (dtheta, omega).
* Update: measurement ``z = [t_meas, so3_log(R_ref^T R_meas)]`` with ``H = [[I 0 0 0], [0 0 I 0]]``
  (measurement covariance 6x6: position mm^2 first, rotation rad^2 second). After the update ``dtheta`` is
  injected (``R_ref <- R_ref exp(dtheta)``) and reset to 0; the covariance reset uses the first-order
  reset Jacobian ``G = I - 0.5 [dtheta]_x`` on the rotation block (``P <- G P G^T``; for the small
  corrections seen in tracking this is within a hair of the identity approximation).
* Gating: ``d2 = y^T S^-1 y`` with ``S = H P H^T + R`` evaluated BEFORE the update (filterpy's
  ``mahalanobis`` is computed after the update and is not used). ``d2 > gate_chi2`` (chi2(6) 99.9 % =
  22.46) rejects the measurement; ``rejections_in_a_row`` counts consecutive rejections of counted
  measurements so the caller can re-initialise from the estimator (``lost`` once it reaches
  ``max_rejections``). ``init`` is never gated.

Time comes from real timestamps in seconds (variable frame rate); ``predict`` raises on ``dt <= 0``.

For smoothing (:mod:`.smoother`) the filter keeps what the backward pass needs: ``prior`` (the prediction
into the current frame, with its error-state transition) and :meth:`PoseKalman.snapshot` (the filtered
state). ``init`` starts a new segment (no prior: the smoother does not link across it);
:meth:`PoseKalman.restart` takes a measurement the filter would have gated out by widening the prior,
which keeps the link.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from surftrack.geometry.transforms import skew, so3_exp, so3_log, so3_right_jacobian

CHI2_6DOF_999 = 22.46


#: KalmanConfig settings for which 0 switches the behaviour off (every other one must be positive).
_ZERO_MEANS_OFF = frozenset({"coast_tau_s"})


@dataclass
class KalmanConfig:
    """Noise settings; defaults aimed at da Vinci instruments seen by an endoscope at ~30 fps.

    * ``accel_std_mm_s2 = 30``: instruments mostly glide (synthetic clips: median speed 2-8 mm/s, median
      acceleration 1-25 mm/s^2) with occasional fast moves (p90 acceleration 180-410 mm/s^2, peaks
      ~1000). The white-noise acceleration level sets how much the filter and above all the smoother
      average: with ~3 mm estimator noise, 200 left smoothed path lengths 1.3-2x the truth; 30 suits an
      estimate on every frame, 60 one every 6 frames without measurements between (tuning clip seed 3,
      docs/results/2026-12-02-tracking.md). A fast move beyond it is caught by the gate
      (``max_rejections`` estimates in a row that disagree restart the pose).
    * ``ang_accel_std_rad_s2 = 3``: wrist / shaft roll reaches ~1-3 rad/s; 5 let the estimator's shaft roll
      flips through on the tuning clip.
    * ``meas_pos_std_mm = 3``, ``meas_rot_std_deg = 3``: the covariance of a measurement given without
      one (``init`` / ``update`` with ``meas_cov=None``). The tracker always passes its own (the
      estimator's: TrackConfig ``est_*_std``; the silhouette's and flow's from their fits).
    * ``init_vel_std_mm_s = 100``, ``init_omega_std_rad_s = 2``: uncertainty of the unknown initial
      velocities.
    * ``gate_chi2 = 22.46``: chi2 with 6 dof at 99.9 %; ``max_rejections = 8`` consecutive rejections of
      counted measurements (the estimator's, ``update(counts=True)``) mark the track as lost (re-initialise
      from the estimator): the estimator's single outliers (a flipped jaw, the shaft's roll) come in short
      runs, a real fast move persists.
    * ``coast_tau_s = 0.1``: while a part goes unmeasured (every estimate gated out, no silhouette fit),
      its velocities decay with this time constant instead of carrying it on: a track that has started to
      drift (a jaw turning away at 7-8 deg a frame while its estimates are rejected) would otherwise go on
      drifting at that rate, and the smoother then spreads the jump back to the truth over the path.
      13 held-out runs: ADD-10 +3 to +5 points per part on average; path ratio mean 1.93 -> 1.40
      (docs/decisions.md).
      0: constant velocity throughout.
    """

    accel_std_mm_s2: float = 30.0
    ang_accel_std_rad_s2: float = 3.0
    meas_pos_std_mm: float = 3.0
    meas_rot_std_deg: float = 3.0
    gate_chi2: float = CHI2_6DOF_999
    init_vel_std_mm_s: float = 100.0
    init_omega_std_rad_s: float = 2.0
    max_rejections: int = 8
    coast_tau_s: float = 0.1

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v, kind = getattr(self, f.name), type(f.default)
            if (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                    or (kind is int and not float(v).is_integer())):
                raise ValueError(f"{f.name} must be {'an integer' if kind is int else 'a finite number'}, got {v!r}")
            setattr(self, f.name, kind(v))
            if f.name in _ZERO_MEANS_OFF:
                if v < 0:
                    raise ValueError(f"{f.name} must be >= 0 (0: off), got {v}")
            elif (v < 1) if kind is int else (v <= 0):
                raise ValueError(f"{f.name} must be {'>= 1' if kind is int else '> 0'}, got {v}")

    def meas_cov(self) -> np.ndarray:
        """Default 6x6 measurement covariance (mm^2 then rad^2)."""
        r = np.radians(self.meas_rot_std_deg)
        return np.diag([self.meas_pos_std_mm**2] * 3 + [r**2] * 3)


@functools.lru_cache(maxsize=8)
def _chi2_999(dof: int) -> float:
    """chi2 quantile at 99.9 % for ``dof`` degrees of freedom."""
    from scipy.stats import chi2

    return float(chi2.ppf(0.999, dof))


def white_noise_q(dt: float, q: float, axes: int = 3) -> np.ndarray:
    """(2 axes, 2 axes) white-noise-acceleration covariance of ``axes`` positions followed by their rates."""
    i = np.eye(axes)
    return q * np.block([[dt**3 / 3.0 * i, dt**2 / 2.0 * i], [dt**2 / 2.0 * i, dt * i]])


def gate_limit(config: KalmanConfig, dof: int) -> float:
    """The gate for a measurement of ``dof`` dimensions: ``gate_chi2`` (6 dof) scaled by chi2(dof) /
    chi2(6), both at 99.9 %."""
    return config.gate_chi2 * _chi2_999(dof) / CHI2_6DOF_999


def speed_std(velocity: np.ndarray, cov: np.ndarray) -> float:
    """The standard deviation (mm/s) of the speed of a point moving at ``velocity`` (3,) mm/s with that
    velocity's covariance ``cov`` (3, 3): along the velocity, what a path length integrates (at rest,
    along the widest axis)."""
    v = np.asarray(velocity, np.float64)
    n = float(np.linalg.norm(v))
    if n < 1e-6:  # at rest the speed's spread is the velocity's, in its widest direction
        return float(np.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0)))
    u = v / n
    return float(np.sqrt(max(float(u @ cov @ u), 0.0)))


def pose_transition(omega: np.ndarray, dt: float, config: KalmanConfig,
                    decay: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(F, Q), 12x12: the error-state transition and process noise of a pose ``[t, v, dtheta, omega]``
    over ``dt`` s with body angular velocity ``omega`` (see the module docstring); ``decay``: the factor
    the velocities keep over the step (1: constant velocity)."""
    F = np.eye(12)
    F[0:3, 3:6] = np.eye(3) * dt
    F[3:6, 3:6] = np.eye(3) * decay
    F[6:9, 6:9] = so3_exp(-omega * dt)
    F[6:9, 9:12] = np.eye(3) * dt
    F[9:12, 9:12] = np.eye(3) * decay
    Q = np.zeros((12, 12))
    Q[0:6, 0:6] = white_noise_q(dt, config.accel_std_mm_s2**2)
    Q[6:12, 6:12] = white_noise_q(dt, config.ang_accel_std_rad_s2**2)
    return F, Q


def inject_rotation(R_ref: np.ndarray, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R_ref, x, P) after moving the rotation error ``x[6:9]`` into the nominal ``R_ref`` and resetting
    it to 0, the covariance through the first-order reset Jacobian on the rotation block."""
    x = x.copy()
    dtheta = x[6:9].copy()
    x[6:9] = 0.0
    G = np.eye(len(x))
    G[6:9, 6:9] = np.eye(3) - 0.5 * skew(dtheta)
    P = G @ P @ G.T
    return R_ref @ so3_exp(dtheta), x, 0.5 * (P + P.T)


def change_chart(R_from: np.ndarray, x: np.ndarray, P: np.ndarray,
                 R_to: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, P) of the error state ``x`` (12,), or an instrument's (12 + 2n,), covariance ``P`` to match,
    about nominal ``R_from`` (3, 3), re-expressed about the nominal ``R_to``: the rotation error becomes
    ``log(R_to^T R_from exp(x_rot))`` and its covariance goes through the first-order Jacobian of that
    map, ``J_r(d)^-1 J_r(x_rot)`` (the other components are the same in either chart)."""
    x_rot = np.asarray(x, np.float64)[6:9]
    d = so3_log(R_to.T @ R_from @ so3_exp(x_rot))
    J = np.eye(len(x))
    J[6:9, 6:9] = np.linalg.solve(so3_right_jacobian(d), so3_right_jacobian(x_rot))
    x = np.array(x, np.float64)
    x[6:9] = d
    P = J @ P @ J.T
    return x, 0.5 * (P + P.T)


@dataclass(frozen=True)
class FilterPrior:
    """The prediction into a frame: error-state transition ``F`` (12, 12) from the previous frame's
    filtered state, predicted nominal rotation ``R`` (3, 3), error state ``x`` (12,) and covariance
    ``P`` (12, 12) (process noise and any widening by :meth:`PoseKalman.restart` included); an
    instrument's state (:class:`~.instrument.InstrumentKalman`) has 12 + 2n entries, its joints and their
    rates after a part's 12. ``restarted``: a restart widened ``P`` and cut the pose loose from the rates
    (zero covariance between them)."""

    F: np.ndarray
    R: np.ndarray
    x: np.ndarray
    P: np.ndarray
    restarted: bool = False


@dataclass(frozen=True)
class FilterStep:
    """One frame of a part's filter: ``time`` (s), filtered nominal rotation ``R`` (3, 3), error state
    ``x`` (12,) ``[t mm, v mm/s, dtheta = 0, omega rad/s]`` and covariance ``P`` (12, 12) (an instrument's
    state: 12 + 2n, :class:`FilterPrior`); ``prior``: the prediction into this frame, or None where a
    segment starts (first pose, re-initialisation).
    ``revises``: the filtered steps of earlier frames, oldest first, that replace the ones the filter
    gave them before a restart in hindsight (:func:`refilter`); the smoother swaps them in. ``revised``:
    this step is one of them (or smoothed from one)."""

    time: float
    R: np.ndarray
    x: np.ndarray
    P: np.ndarray
    prior: FilterPrior | None
    revises: tuple[FilterStep, ...] = ()
    revised: bool = False

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """``(R (3, 3), t (3,) mm)``, model-to-camera."""
        return self.R @ so3_exp(self.x[6:9]), self.x[0:3].copy()

    @property
    def pose_cov(self) -> np.ndarray:
        """6x6 covariance of (t mm, body rotation rad)."""
        return _H @ self.P @ _H.T


def pose_and_rate_index(dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The pose coordinates and their rates, in the same order, of an error state of ``dim`` entries: a
    part's ``[t, v, dtheta, omega]`` (12) or an instrument's ``[t, v, dtheta, omega, q (n), qdot (n)]``
    (12 + 2n; :class:`~.instrument.InstrumentKalman`), the joints counted with the pose."""
    n, odd = divmod(dim - 12, 2)
    if dim < 12 or odd:
        raise ValueError(f"an error state has 12 + 2n entries, got {dim}")
    return np.r_[0:3, 6:9, 12:12 + n], np.r_[3:6, 9:12, 12 + n:dim]


def cut_pose_from_rates(P: np.ndarray) -> np.ndarray:
    """A copy of the covariance ``P`` (12 + 2n square, :func:`pose_and_rate_index`) without the covariance
    between the pose (and joints) and the rates (a restart: a jump says nothing about the velocities)."""
    P = np.array(P, np.float64)
    pose, rates = pose_and_rate_index(len(P))
    P[np.ix_(pose, rates)] = 0.0
    P[np.ix_(rates, pose)] = 0.0
    return P

_H = np.zeros((6, 12))
_H[0:3, 0:3] = np.eye(3)
_H[3:6, 6:9] = np.eye(3)


def refilter(config: KalmanConfig, frames: Sequence[tuple[float, tuple | None]],
             last_ungated: bool = False) -> tuple[PoseKalman, list[FilterStep]]:
    """A fresh filter run over ``frames``: per frame ``(time s, (R (3, 3), t (3,) mm, covariance 6x6) or
    None)``, the first with a measurement (the filter starts there), then predicted frame to frame and
    updated where measured (gated as usual, the last frame's ungated with ``last_ungated``; velocities
    coast after an unmeasured frame). Returns the filter at the last frame and its step on every frame.
    This is how a track found wrong is restarted in hindsight: from the estimates it refused, as far back
    as they go."""
    if not frames or frames[0][1] is None:
        raise ValueError("refilter needs a measurement on its first frame")
    kf = PoseKalman(config)
    t0, (R0, p0, cov0) = frames[0]
    kf.init(R0, p0, t0, cov0)
    steps, measured = [kf.snapshot()], True
    for k, (time, meas) in enumerate(frames[1:], 2):
        kf.predict(time, coast=not measured)
        measured = meas is not None and kf.update(meas[0], meas[1], meas[2],
                                                  gate=not (last_ungated and k == len(frames)))
        steps.append(kf.snapshot())
    return kf, steps


class PoseKalman:
    """12-state error-state constant-velocity pose filter (see the module docstring for conventions).

    Usage: ``kf.init(R, t, time)`` with the estimator's first pose, then per frame ``kf.predict(time)``
    followed by ``kf.update(R_meas, t_meas)`` (returns False when gated out); ``kf.pose`` is the estimate.
    """

    H = _H

    def __init__(self, config: KalmanConfig | None = None):
        self.config = config if config is not None else KalmanConfig()
        self.kf = KalmanFilter(dim_x=12, dim_z=6)
        self.kf.H = _H.copy()
        self.R_ref = np.eye(3)
        self.time: float | None = None
        self.rejections_in_a_row = 0
        self.last_d2: float | None = None
        self.prior: FilterPrior | None = None  # the prediction into the current frame (None after init)

    # ------------------------------------------------------------------ state
    @property
    def initialized(self) -> bool:
        return self.time is not None

    @property
    def lost(self) -> bool:
        """True once ``max_rejections`` consecutive measurements were gated out."""
        return self.rejections_in_a_row >= self.config.max_rejections

    @property
    def x(self) -> np.ndarray:
        """The 12-vector error state [t, v, dtheta, omega] (copy; dtheta is 0 between calls)."""
        return self.kf.x.reshape(12).copy()

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Current estimate ``(R 3x3, t (3,) mm)``."""
        self._require_init()
        x = self.kf.x.reshape(12)
        return self.R_ref @ so3_exp(x[6:9]), x[0:3].copy()

    @property
    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """``(v (3,) mm/s camera frame, omega (3,) rad/s body frame)``."""
        x = self.kf.x.reshape(12)
        return x[3:6].copy(), x[9:12].copy()

    @property
    def covariance(self) -> np.ndarray:
        """12x12 error-state covariance (copy)."""
        return self.kf.P.copy()

    @property
    def pose_cov(self) -> np.ndarray:
        """6x6 covariance of the pose (position mm, body rotation rad)."""
        return _H @ self.kf.P @ _H.T

    @property
    def position_std_mm(self) -> np.ndarray:
        """Per-axis position standard deviation (3,) in mm."""
        return np.sqrt(np.diag(self.kf.P)[0:3])

    @property
    def rotation_std_deg(self) -> np.ndarray:
        """Per-axis (body frame) rotation standard deviation (3,) in degrees."""
        return np.degrees(np.sqrt(np.diag(self.kf.P)[6:9]))

    def _require_init(self) -> None:
        if self.time is None:
            raise RuntimeError("PoseKalman is not initialised; call init(R, t, time) first")

    # ------------------------------------------------------------------ init / predict
    def init(self, R: np.ndarray, t: np.ndarray, time: float, meas_cov: np.ndarray | None = None) -> None:
        """(Re-)initialise from a pose measurement; never gated. Velocities start at 0. Raises
        ``ValueError`` for a non-finite pose or covariance."""
        c = self.config
        meas_cov = c.meas_cov() if meas_cov is None else np.asarray(meas_cov, np.float64)
        if not (np.isfinite(R).all() and np.isfinite(t).all() and np.isfinite(meas_cov).all()):
            raise ValueError("cannot initialise a pose filter from a non-finite pose or covariance")
        self.R_ref = np.asarray(R, np.float64).copy()
        x = np.zeros(12)
        x[0:3] = np.asarray(t, np.float64).reshape(3)
        self.kf.x = x.reshape(12, 1)
        P = np.zeros((12, 12))
        P[0:3, 0:3] = meas_cov[0:3, 0:3]
        P[6:9, 6:9] = meas_cov[3:6, 3:6]
        P[0:3, 6:9] = meas_cov[0:3, 3:6]
        P[6:9, 0:3] = meas_cov[3:6, 0:3]
        P[3:6, 3:6] = np.eye(3) * c.init_vel_std_mm_s**2
        P[9:12, 9:12] = np.eye(3) * c.init_omega_std_rad_s**2
        self.kf.P = P
        self.time = float(time)
        self.rejections_in_a_row = 0
        self.last_d2 = None
        self.prior = None

    def snapshot(self) -> FilterStep:
        """The current filtered state with the prediction that led to it (copies)."""
        self._require_init()
        return FilterStep(self.time, self.R_ref.copy(), self.kf.x.reshape(12).copy(), self.kf.P.copy(), self.prior)

    def _transition(self, dt: float, coast: bool = False) -> tuple[np.ndarray, np.ndarray]:
        tau = self.config.coast_tau_s
        decay = math.exp(-dt / tau) if coast and tau > 0 else 1.0
        return pose_transition(self.kf.x.reshape(12)[9:12], dt, self.config, decay)

    def _dt(self, time: float) -> float:
        self._require_init()
        return float(time) - self.time

    def predict(self, time: float, coast: bool = False) -> None:
        """Propagate to ``time`` (seconds); raises ``ValueError`` unless ``time`` is after the last time.
        ``coast``: the part went unmeasured since the last frame; its velocities decay with
        ``config.coast_tau_s`` (when set) instead of carrying a pose that nothing confirms further."""
        dt = self._dt(time)
        if not dt > 0:
            raise ValueError(f"predict needs a positive dt, got {dt!r} (time {time!r} after {self.time!r})")
        x = self.kf.x.reshape(12)
        R_next = self.R_ref @ so3_exp(x[6:9]) @ so3_exp(x[9:12] * dt)
        F, Q = self._transition(dt, coast)
        self.kf.predict(F=F, Q=Q)
        xn = self.kf.x.reshape(12).copy()
        xn[6:9] = 0.0  # the nominal carries the rotation; error mean is 0 relative to R_next
        self.kf.x = xn.reshape(12, 1)
        self.R_ref = R_next
        self.time = float(time)
        self.prior = FilterPrior(F, R_next.copy(), xn.copy(), self.kf.P.copy())

    def restart(self, R_meas: np.ndarray, t_meas: np.ndarray, meas_cov: np.ndarray, widen: np.ndarray) -> None:
        """Take a pose measurement the filter disbelieves (it would be gated out, or the filter is
        overconfident): go back to this frame's prediction, add ``widen`` (6x6, mm^2 then rad^2) to its
        pose covariance and drop the pose-rate correlations (a jump of this step alone), and fuse the
        measurement ungated. Unlike
        ``init`` this keeps the velocities and the link to the previous frames for the smoother. Without
        a prediction into this frame (just initialised) it is ``init``."""
        if self.prior is None:
            self.init(R_meas, t_meas, self.time, meas_cov)
            return
        # the pose block widened and cut loose from the rates: a jump says nothing about the velocities
        # (through the prior's pose-velocity correlation it would turn into a velocity that runs away)
        P = cut_pose_from_rates(self.prior.P + _H.T @ np.asarray(widen, np.float64) @ _H)
        self.prior = FilterPrior(self.prior.F, self.prior.R, self.prior.x, P, restarted=True)
        self.R_ref = self.prior.R.copy()
        self.kf.x = self.prior.x.reshape(12, 1).copy()
        self.kf.P = P.copy()
        self.update(R_meas, t_meas, meas_cov, gate=False)

    def predicted_pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Constant-velocity extrapolation to ``time`` (>= current time) without changing the filter."""
        dt = self._dt(time)
        if dt < 0:
            raise ValueError(f"cannot predict backwards (dt = {dt!r})")
        x = self.kf.x.reshape(12)
        return self.R_ref @ so3_exp(x[6:9]) @ so3_exp(x[9:12] * dt), x[0:3] + x[3:6] * dt

    # ------------------------------------------------------------------ measurement
    def _innovation(self, R_meas, t_meas, meas_cov, basis: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        self._require_init()
        meas_cov = self.config.meas_cov() if meas_cov is None else np.asarray(meas_cov, np.float64)
        x = self.kf.x.reshape(12)
        z = np.concatenate([np.asarray(t_meas, np.float64).reshape(3),
                            so3_log(self.R_ref.T @ np.asarray(R_meas, np.float64))])
        H = _H if basis is None else basis @ _H
        if basis is not None:
            z = basis @ z
        y = z - H @ x
        S = H @ self.kf.P @ H.T + meas_cov
        return z, y, S, H

    def gate(self, R_meas: np.ndarray, t_meas: np.ndarray, meas_cov: np.ndarray | None = None) -> float:
        """Squared Mahalanobis distance of the measurement against the current (prior) state."""
        _, y, S, _ = self._innovation(R_meas, t_meas, meas_cov)
        return float(y @ np.linalg.solve(S, y))

    def update(self, R_meas: np.ndarray, t_meas: np.ndarray, meas_cov: np.ndarray | None = None,
               gate: bool = True, basis: np.ndarray | None = None, counts: bool = True) -> bool:
        """Fuse a pose measurement at the current filter time. Returns False (state untouched) when gated.

        ``basis`` (m x 6): fuse only these m combinations of the pose (position mm, body rotation rad),
        ``meas_cov`` then being their m x m covariance: a measurement that sees some directions of the
        pose and not others (a silhouette: the lateral position, hardly the depth) claims nothing about
        the rest. The gate ``gate_chi2`` is then scaled by chi2(m) / chi2(6), both at 99.9 %. ``counts``:
        whether its outcome counts towards ``rejections_in_a_row`` (``lost``): the pose estimator's do, a
        silhouette fit's or flow's (the track's own evidence, which fails where the image does) do not."""
        if basis is not None and meas_cov is None:
            raise ValueError("a measurement of some pose directions (basis) needs their covariance")
        meas_cov = self.config.meas_cov() if meas_cov is None else np.asarray(meas_cov, np.float64)
        if not (np.isfinite(R_meas).all() and np.isfinite(t_meas).all() and np.isfinite(meas_cov).all()):
            self.rejections_in_a_row += counts  # a non-finite measurement is never fused, gated or not
            self.last_d2 = math.inf
            return False
        z, y, S, H = self._innovation(R_meas, t_meas, meas_cov, basis)
        d2 = float(y @ np.linalg.solve(S, y))
        self.last_d2 = d2
        limit = self.config.gate_chi2 if basis is None else gate_limit(self.config, len(z))
        if not math.isfinite(d2) or (gate and d2 > limit):
            self.rejections_in_a_row += counts
            return False
        self.kf.update(z.reshape(-1, 1), R=meas_cov, H=H)
        self.R_ref, x, self.kf.P = inject_rotation(self.R_ref, self.kf.x.reshape(12), self.kf.P)
        self.kf.x = x.reshape(12, 1)
        if counts:
            self.rejections_in_a_row = 0
        return True

    def step(self, time: float, R_meas: np.ndarray | None, t_meas: np.ndarray | None,
             meas_cov: np.ndarray | None = None, gate: bool = True) -> bool:
        """``init`` on the first call, else ``predict(time)`` then ``update`` (skipped when R_meas is None)."""
        if not self.initialized:
            if R_meas is None:
                raise RuntimeError("the first step needs a measurement")
            self.init(R_meas, t_meas, time, meas_cov)
            return True
        self.predict(time)
        if R_meas is None:
            return False
        return self.update(R_meas, t_meas, meas_cov, gate)

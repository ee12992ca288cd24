"""Fit an instrument's articulated configuration (base pose + joints) to the poses of its parts.

Given per-frame part poses (any subset of the rigid parts, model-to-camera, mm), :func:`fit_configuration`
finds the base pose and the :class:`JointState` whose forward kinematics reproduce them best, by robust
nonlinear least squares over

* the base pose, 5 numbers: the pitch-point origin (3, mm) and the shaft direction (2, a tangent
  perturbation of the initial one). The base frame's rotation about the shaft is not free: zero roll is
  defined by :func:`rcm_base_pose`'s convention (base x = the component of ``roll_reference``, by
  default the camera's +z, orthogonal to the shaft), which is how the synthetic clips build it. A sixth,
  free base rotation would make ``roll`` meaningless (any roll could be absorbed by the base);
* the joints that the data determine (roll, pitch, yaw, opening; bounded by the joint limits).

Residuals per used part ``p`` (weights ``w_p``, ``v_p``): ``[sqrt(w_p) L log(R_fk^T R_p), sqrt(v_p) (t_fk
- t_p)]`` in mm (``v_p = w_p`` unless a translation weight is given), where ``L``
(``FitConfig.rotation_scale_mm``) turns radians into millimetres; with a trocar point ``c`` the
remote-centre-of-motion residual ``sqrt(w_c) * (I - d d^T)(c - o)`` (its norm is the distance, mm, from
the trocar to the shaft axis through ``o`` along ``d``). Loss: ``soft_l1`` with scale
``FitConfig.f_scale_mm``.

Observability. Missing parts leave some joints undetermined: with only the shaft, pitch, yaw and opening
do not act on anything seen; with only one jaw, yaw and opening act through their sum alone; without the
shaft and without a trocar, roll, pitch and the shaft direction trade off against each other. Before
solving, the Jacobian of the residuals at the initial estimate is tested: a joint whose column lies in
the span of the others is reported ``observed[name] = False``. Enough of those, distal first (opening,
yaw, pitch, roll), are then HELD at their reference value (the warm start ``init``, else 0 clipped to
the limits) to leave a problem with a unique solution; the other unobserved joints of a coupled group
are solved given the held ones (e.g. with one jaw: opening held, yaw = jaw angle - opening / 2).

Initialisation (closed form): joint angles from the relative rotations of seen parent-child pairs
(``R_parent^T R_child`` about the joint axis) and of seen siblings on one axis (the two jaws give the
opening), a linear system in the joint variables whose undetermined unknowns stay at the reference;
then the base from the most proximal seen part's pose inverted through the chain, roll re-expressed in
the zero-roll convention (the turn nearest the reference roll), and the shaft direction pointed from the
trocar when one is given. If that start ends in a poor fit (residuals beyond the ``FitConfig``
thresholds), a small grid of the wrist angles no pair fixes is tried as well and the lowest cost kept.
Roll, whose limits span more than a turn, is solved unbounded and wrapped into its limits afterwards.

Zero roll is undefined when the shaft points along ``roll_reference`` (looking straight down the shaft):
near that, roll is poorly conditioned.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares

from surftrack.geometry import cross3, rotation_angle_deg, se3, se3_inv, so3_exp, so3_log, so3_right_jacobian
from surftrack.instruments.kinematics import JOINT_NAMES, JointState, rcm_base_pose
from surftrack.instruments.library import Instrument

__all__ = ["FitConfig", "JointFit", "estimate_trocar", "fit_configuration", "joints_from_poses"]

# Order in which joints of an undetermined group are held at their reference value.
HOLD_ORDER = ("opening", "yaw", "pitch", "roll")
# Fallback starts (degrees) for wrist joints that no seen parent-child pair fixes, and how many of the
# best of them (by initial cost) are solved when the closed-form start ends in a poor fit.
GRID = {"pitch": (-50.0, 0.0, 50.0), "yaw": (-50.0, 0.0, 50.0), "opening": (10.0, 50.0)}
GRID_STARTS = 4
_N_BASE = 5  # origin (3) + shaft direction tangent (2)


@dataclass(frozen=True)
class FitConfig:
    """Knobs of :func:`fit_configuration` (defaults in one place).

    ``rotation_scale_mm``: millimetres of residual per radian of part rotation error. It sets how much
    rotations count against translations; the ideal value is the ratio of the pose estimator's
    translation and rotation noise (2 mm vs 2 deg gives 57 mm). ``f_scale_mm``: ``soft_l1`` scale
    (residuals beyond it are down-weighted). ``trocar_weight``: weight of the RCM residual relative to a
    part with weight 1. ``max_rotation_deg`` / ``max_translation_mm``: a fit is ``ok`` only if every used
    part (and the trocar distance) stays within these. ``roll_reference``: the camera-frame direction that
    defines zero roll (see :func:`rcm_base_pose`; None = camera +z, as in the synthetic clips).
    ``observability_tol``: relative size below which a joint's Jacobian column counts as explained by
    the others.
    """

    rotation_scale_mm: float = 30.0
    f_scale_mm: float = 3.0
    trocar_weight: float = 1.0
    max_rotation_deg: float = 10.0
    max_translation_mm: float = 5.0
    roll_reference: tuple[float, float, float] | None = None
    observability_tol: float = 1e-5
    max_nfev: int = 200

    def __post_init__(self) -> None:
        for name in ("rotation_scale_mm", "f_scale_mm", "max_rotation_deg", "max_translation_mm",
                     "observability_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"FitConfig.{name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.trocar_weight) and self.trocar_weight >= 0):
            raise ValueError(f"FitConfig.trocar_weight must be >= 0, got {self.trocar_weight!r}")


@dataclass(frozen=True)
class JointFit:
    """Result of :func:`fit_configuration`.

    ``base_R``, ``base_t``: base (zero-roll shaft frame) to camera, mm. ``joints``: within the joint
    limits. ``observed``: per joint name, whether the used parts (and trocar) determine it;
    ``held``: joints kept at their reference value (warm start or 0) because they are not. ``residuals``:
    per used part ``(rotation error deg, translation error mm)`` of the fitted kinematics against the
    given pose. ``trocar_distance_mm``: distance from the trocar to the fitted shaft axis (None without a
    trocar). ``ok``: the solver converged and every residual is within the ``FitConfig`` thresholds.
    """

    base_R: np.ndarray
    base_t: np.ndarray
    joints: JointState
    observed: dict[str, bool]
    held: tuple[str, ...]
    residuals: dict[str, tuple[float, float]]
    parts_used: tuple[str, ...]
    trocar_distance_mm: float | None
    ok: bool
    message: str = ""
    nfev: int = 0

    @property
    def base_pose(self) -> np.ndarray:
        """4x4 base-to-camera pose (mm)."""
        return se3(self.base_R, self.base_t)

    @property
    def shaft_axis(self) -> tuple[np.ndarray, np.ndarray]:
        """(point, unit direction) of the shaft axis in the camera frame: base origin and base +z."""
        return self.base_t.copy(), self.base_R[:, 2].copy()

    @property
    def rms_mm(self) -> float:
        """Root mean square translation residual over the used parts, mm."""
        return float(np.sqrt(np.mean([t ** 2 for _, t in self.residuals.values()])))

    @property
    def rms_deg(self) -> float:
        """Root mean square rotation residual over the used parts, degrees."""
        return float(np.sqrt(np.mean([r ** 2 for r, _ in self.residuals.values()])))

    def part_poses(self, instrument: Instrument) -> dict[str, np.ndarray]:
        """Forward kinematics of the fit: every part's 4x4 pose (part-to-camera, mm)."""
        return instrument.forward(self.base_pose, self.joints)


# --------------------------------------------------------------------------------------------- helpers
def _as_rotation(R, what: str) -> np.ndarray:
    """The nearest rotation matrix to ``R`` (pose estimators may return slightly non-orthonormal ones)."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"{what}: rotation must be a finite 3x3 matrix, got shape {R.shape}")
    U, _, Vt = np.linalg.svd(R)
    out = U @ Vt
    if np.linalg.det(out) < 0:
        raise ValueError(f"{what}: rotation matrix has a negative determinant (a reflection)")
    return out


def _as_point(t, what: str) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"{what}: expected 3 finite values (mm), got {t!r}")
    return t


def _tangent_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1 = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


def _axis_angle(M: np.ndarray, axis: np.ndarray) -> float:
    """Angle of rotation ``M`` about unit ``axis`` (exact for ``M = Rot(axis, a)``; the part of ``M`` about
    that axis otherwise)."""
    s = 0.5 * axis @ np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    c = 0.5 * (np.trace(M) - axis @ M @ axis)
    return math.atan2(s, c)


def _nearest_turn(angle: float, ref: float, lo: float, hi: float) -> float:
    """``angle + 2 pi k`` closest to ``ref`` among those inside [lo, hi] (or closest to ``ref`` if none is)."""
    k0 = round((ref - angle) / (2 * math.pi))
    cands = [angle + 2 * math.pi * k for k in (k0 - 1, k0, k0 + 1)]
    inside = [a for a in cands if lo <= a <= hi]
    return min(inside or cands, key=lambda a: abs(a - ref))


def _limits(instrument: Instrument) -> dict[str, tuple[float, float]]:
    return {n: instrument.limits.ranges.get(n, (-math.inf, math.inf)) for n in JOINT_NAMES}


# --------------------------------------------------------------------------------------------- problem
class _Problem:
    """Residuals of one frame as a function of ``x = [origin (3), direction tangent (2), free joints]``."""

    def __init__(self, instrument: Instrument, names: list[str], R_obs: np.ndarray, t_obs: np.ndarray,
                 w: np.ndarray, trocar: np.ndarray | None, cfg: FitConfig):
        self.instrument, self.names, self.cfg = instrument, names, cfg
        self.R_obs, self.t_obs = R_obs, t_obs
        self.sw = np.sqrt(np.repeat(w, 3, axis=1))  # w (n, 2): rotation and translation weight per part
        self.trocar = trocar
        self.sw_trocar = math.sqrt(cfg.trocar_weight)
        self.ref = None if cfg.roll_reference is None else np.asarray(cfg.roll_reference, dtype=np.float64)
        self.d0 = np.array([0.0, 0.0, 1.0])
        self.e1, self.e2 = _tangent_basis(self.d0)
        self.q_ref = np.zeros(len(JOINT_NAMES))
        self.free = list(range(len(JOINT_NAMES)))
        chain = instrument.chain
        # per part: its joint's unit axis and angle coefficients (in JOINT_NAMES order), and the parts
        # from the root down to it (whose joints move it)
        self._joint_data = {n: (np.asarray(j.axis, dtype=np.float64) / np.linalg.norm(j.axis),
                                np.array([j.coefficients.get(k, 0.0) for k in JOINT_NAMES]))
                            for n, j in chain.joints.items()}
        self._ancestry: dict[str, list[str]] = {}
        for n in chain.order:
            parent = chain.joints[n].parent
            self._ancestry[n] = ([] if parent is None else self._ancestry[parent]) + [n]

    def set_direction(self, d0: np.ndarray) -> None:
        self.d0 = d0 / np.linalg.norm(d0)
        self.e1, self.e2 = _tangent_basis(self.d0)

    def base(self, x: np.ndarray) -> np.ndarray:
        o = x[:3]
        d = so3_exp(x[3] * self.e1 + x[4] * self.e2) @ self.d0
        return rcm_base_pose(o - d, o, self.ref)

    def joints(self, x: np.ndarray) -> np.ndarray:
        q = self.q_ref.copy()
        q[self.free] = x[_N_BASE:]
        return q

    def residuals(self, x: np.ndarray) -> np.ndarray:
        B = self.base(x)
        poses = self.instrument.forward(B, JointState(*self.joints(x)))
        T = np.stack([poses[n] for n in self.names])
        rot = so3_log(np.swapaxes(T[:, :3, :3], 1, 2) @ self.R_obs)
        r = np.concatenate([self.cfg.rotation_scale_mm * rot, T[:, :3, 3] - self.t_obs], axis=1) * self.sw
        out = [r.ravel()]
        if self.trocar is not None:
            d, o = B[:3, 2], B[:3, 3]
            v = self.trocar - o
            out.append(self.sw_trocar * (v - d * (d @ v)))
        return np.concatenate(out)

    def analytic_jacobian(self, x: np.ndarray) -> np.ndarray:
        """Jacobian of :meth:`residuals` at ``x`` (rows as the residuals, one column per entry of ``x``).

        Each parameter moves every part by a twist (camera frame): the origin translates them all, the
        direction tangent turns the base about its origin, a joint turns the parts below it about its
        axis. A part turned by ``w`` changes its rotation residual ``log(R^T R_obs)`` by
        ``-J_r^-1(log(R^T R_obs)) R_obs^T w``. Exact but for the base's turning rate per direction
        tangent, taken by central differences of the base alone (its zero-roll convention has no handy
        closed form; ~1e-9 relative). Differencing all the residuals instead was most of the fit's
        time; here it serves the observability test (one evaluation instead of two per parameter)."""
        B = self.base(x)
        q = np.asarray(self.joints(x))
        o = B[:3, 3]
        poses = self.instrument.forward(B, JointState(*q))
        # a part's joint axis in the camera frame (its rotation keeps its own axis) and the joint's point
        # (the part's origin)
        pivot = {n: (T[:3, :3] @ self._joint_data[n][0], T[:3, 3]) for n, T in poses.items()}
        h = 1e-6
        w_base = []
        for k in (3, 4):
            xp, xm = x.copy(), x.copy()
            xp[k] += h
            xm[k] -= h
            W = (self.base(xp)[:3, :3] - self.base(xm)[:3, :3]) @ B[:3, :3].T / (2 * h)
            w_base.append(0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]]))
        n_x = len(x)
        rows = []
        for i, name in enumerate(self.names):
            T = poses[name]
            t = T[:3, 3]
            omega = np.zeros((3, n_x))
            vel = np.zeros((3, n_x))
            vel[:, :3] = np.eye(3)
            for c, wb in enumerate(w_base):
                omega[:, 3 + c] = wb
                vel[:, 3 + c] = cross3(wb, t - o)
            for c, k in enumerate(self.free):
                for a in self._ancestry[name]:
                    coef = self._joint_data[a][1][k]
                    if coef != 0.0:
                        u, p = pivot[a]
                        omega[:, _N_BASE + c] += coef * u
                        vel[:, _N_BASE + c] += coef * cross3(u, t - p)
            phi = so3_log(T[:3, :3].T @ self.R_obs[i])
            D = -self.cfg.rotation_scale_mm * np.linalg.solve(so3_right_jacobian(phi), self.R_obs[i].T)
            rows.append(np.vstack([D @ omega, vel]) * self.sw[i][:, None])
        if self.trocar is not None:
            d = B[:3, 2]
            v = self.trocar - o
            P = np.eye(3) - np.outer(d, d)
            J = np.zeros((3, n_x))
            J[:, :3] = -P
            for c, wb in enumerate(w_base):
                dd = cross3(wb, d)
                J[:, 3 + c] = -dd * (d @ v) - d * (dd @ v)
            rows.append(self.sw_trocar * J)
        return np.vstack(rows)

    def jacobian(self, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
        """Central-difference Jacobian of :meth:`residuals` (the check on :meth:`analytic_jacobian`)."""
        cols = []
        for i in range(len(x)):
            dx = np.zeros_like(x)
            dx[i] = h
            cols.append((self.residuals(x + dx) - self.residuals(x - dx)) / (2 * h))
        return np.stack(cols, axis=1)


def _in_span(J: np.ndarray, k: int, others: Sequence[int], tol: float) -> bool:
    """Whether column ``k`` of ``J`` is (to ``tol`` relative) a combination of the columns ``others``."""
    c = J[:, k]
    n = np.linalg.norm(c)
    if n < 1e-12:
        return True
    A = J[:, list(others)]
    norms = np.linalg.norm(A, axis=0)
    A = A[:, norms > 1e-12] / norms[norms > 1e-12]
    if A.shape[1] == 0:
        return False
    coef = np.linalg.lstsq(A, c, rcond=None)[0]
    return bool(np.linalg.norm(c - A @ coef) < tol * n)


def _observability(J: np.ndarray, tol: float) -> tuple[dict[str, bool], list[str]]:
    """Observed flag per joint and the joints to hold (distal first) so the rest is determined.

    ``J`` has the 5 base columns first, then one column per joint in ``JOINT_NAMES`` order."""
    base = list(range(_N_BASE))
    col = {n: _N_BASE + i for i, n in enumerate(JOINT_NAMES)}
    observed = {n: not _in_span(J, col[n], base + [col[m] for m in JOINT_NAMES if m != n], tol)
                for n in JOINT_NAMES}
    free = list(JOINT_NAMES)
    held = []
    for n in HOLD_ORDER:
        if not observed[n] and _in_span(J, col[n], base + [col[m] for m in free if m != n], tol):
            free.remove(n)
            held.append(n)
    return observed, held


def _pair_relations(instrument: Instrument, poses: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Linear equations ``A q = b`` in the joint variables from the relative rotations of seen parts:
    a part and its parent (``R_parent^T R_part``, less the joint's fixed rotation, turns about the joint axis
    by the part's joint angle) and two siblings on the same joint frame and axis (their relative rotation is the difference of their
    angles, e.g. the jaw opening)."""
    chain = instrument.chain.joints
    rows, rhs = [], []

    def coeffs(name: str) -> np.ndarray:
        return np.array([chain[name].coefficients.get(n, 0.0) for n in JOINT_NAMES])

    def unit(axis) -> np.ndarray:
        a = np.asarray(axis, dtype=np.float64)
        return a / np.linalg.norm(a)

    def fixed(name: str) -> np.ndarray:
        return np.asarray(chain[name].rotation, dtype=np.float64).reshape(3, 3)

    seen = [n for n in instrument.chain.order if n in poses]
    for name in seen:
        j = chain[name]
        if j.parent in poses:
            rows.append(coeffs(name))
            rel = fixed(name).T @ poses[j.parent][:3, :3].T @ poses[name][:3, :3]
            rhs.append(_axis_angle(rel, unit(j.axis)))
    for i, a in enumerate(seen):
        for b in seen[i + 1:]:
            ja, jb = chain[a], chain[b]
            if (ja.parent is None or ja.parent != jb.parent or ja.parent in poses
                    or not np.allclose(ja.origin, jb.origin) or not np.allclose(unit(ja.axis), unit(jb.axis))
                    or not np.allclose(fixed(a), fixed(b))):
                continue
            rows.append(coeffs(b) - coeffs(a))
            rhs.append(_axis_angle(poses[a][:3, :3].T @ poses[b][:3, :3], unit(ja.axis)))
    return np.asarray(rows).reshape(-1, len(JOINT_NAMES)), np.asarray(rhs)


def _closed_form_joints(A: np.ndarray, b: np.ndarray, q_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint values solving ``A q = b`` (see :func:`_pair_relations`) with the undetermined ones kept at
    ``q_ref`` (a tiny ridge towards it), and a mask of the joints the equations determine."""
    if len(A) == 0:
        return q_ref.copy(), np.zeros(len(q_ref), dtype=bool)
    lam = 1e-6
    q = np.linalg.lstsq(np.vstack([A, lam * np.eye(len(q_ref))]), np.concatenate([b, lam * q_ref]), rcond=None)[0]
    P = np.linalg.pinv(A) @ A  # projector onto the row space of A
    determined = np.abs(np.diag(P) - 1.0) < 1e-9
    return q, determined


def joints_from_poses(instrument: Instrument, poses: Mapping[str, np.ndarray], q_ref: JointState) -> JointState:
    """The joint values the relative rotations of posed parts imply (``poses``: part -> 4x4 part-to-camera,
    any subset), in closed form: joints the parts do not determine keep ``q_ref``'s value; clipped to the
    limits. No base pose and no iterations: a fast start for trackers that refine it themselves."""
    known = {n: np.asarray(T, np.float64) for n, T in poses.items() if n in instrument.chain.joints}
    ref = np.array([getattr(q_ref, n) for n in JOINT_NAMES])
    A, b = _pair_relations(instrument, known)
    q, determined = _closed_form_joints(A, b, ref)
    q = np.where(determined, q, ref)
    limits = _limits(instrument)
    return JointState(*(float(np.clip(q[k], *limits[n])) for k, n in enumerate(JOINT_NAMES)))


def base_from_root(instrument: Instrument, root_pose: np.ndarray, q: JointState) -> tuple[np.ndarray, float]:
    """(base pose 4x4, roll rad): the zero-roll base frame and the roll that put the root part (the shaft)
    at ``root_pose`` (4x4 part-to-camera, mm); ``q``'s own roll is ignored."""
    q0 = np.array([0.0 if n == "roll" else getattr(q, n) for n in JOINT_NAMES])
    o, d, roll = _initial_base(instrument, {instrument.chain.order[0]: np.asarray(root_pose, np.float64)}, q0, None)
    return rcm_base_pose(o - d, o), roll


def _initial_base(instrument: Instrument, poses: dict[str, np.ndarray], q: np.ndarray,
                  roll_reference: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, float]:
    """(origin, shaft direction, roll correction) from the most proximal seen part inverted through the
    chain at joints ``q``; the roll correction re-expresses that base in the zero-roll convention."""
    first = next(n for n in instrument.chain.order if n in poses)
    chain_pose = instrument.chain.forward(np.eye(4), JointState(*q))[first]
    B_raw = poses[first] @ se3_inv(chain_pose)
    o, d = B_raw[:3, 3], B_raw[:3, 2]
    B = rcm_base_pose(o - d, o, roll_reference)
    M = B[:3, :3].T @ B_raw[:3, :3]  # a turn about the common z axis
    return o, d, math.atan2(M[1, 0], M[0, 0])


def _start(instrument: Instrument, poses: dict[str, np.ndarray], q: np.ndarray, q_ref: np.ndarray,
           trocar: np.ndarray | None, roll_reference: np.ndarray | None, lo: np.ndarray, hi: np.ndarray,
           roll_free: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Starting (origin, shaft direction, joints) for joint guess ``q``: the base from the most proximal
    seen part, roll from it in the zero-roll convention (the turn nearest the reference roll; unless
    roll is held), the direction towards the trocar when one is given."""
    q = q.copy()
    o, d, droll = _initial_base(instrument, poses, q, roll_reference)
    if roll_free:
        q[0] = _nearest_turn(q[0] + droll, q_ref[0], lo[0], hi[0])
    if trocar is not None and np.linalg.norm(o - trocar) > 1e-6:
        d = (o - trocar) / np.linalg.norm(o - trocar)
    return o, d, np.clip(q, lo, hi)


def _solve(prob: _Problem, start: tuple[np.ndarray, np.ndarray, np.ndarray], free: list[int],
           lo: np.ndarray, hi: np.ndarray):
    """Robust least squares from ``start`` over the base and the ``free`` joints (others fixed at the
    start's values); returns (solution, base 4x4, joints (4,))."""
    o, d, q = start
    prob.set_direction(d)
    prob.q_ref = q.copy()
    prob.free = free
    # Bounds: the joint limits, except for joints whose range covers a full turn (roll): those are
    # periodic, a bound would only stop the solver on its way round, and they are wrapped afterwards.
    # The direction tangent stays within a quarter turn of its start.
    periodic = hi - lo >= 2 * math.pi
    lo_f = np.where(periodic, -np.inf, lo)[free]
    hi_f = np.where(periodic, np.inf, hi)[free]
    lb = np.concatenate([np.full(3, -np.inf), [-math.pi / 2] * 2, lo_f])
    ub = np.concatenate([np.full(3, np.inf), [math.pi / 2] * 2, hi_f])
    span = np.where(np.isfinite(ub - lb), ub - lb, 1.0)
    x0 = np.clip(np.concatenate([o, [0.0, 0.0], q[free]]), lb + 1e-9 * span, ub - 1e-9 * span)
    # scipy's differenced Jacobian, not the analytic one: on good fits both end at the same poses, but on
    # fits that fail (parts 10-40 mm apart) the exact one converges further, and tracking's shaft lost 10
    # points of ADD-10 over 4 clips x 3 seeds with it (docs/decisions.md)
    sol = least_squares(prob.residuals, x0, bounds=(lb, ub), loss="soft_l1", f_scale=prob.cfg.f_scale_mm,
                        x_scale="jac", max_nfev=prob.cfg.max_nfev)
    return sol, prob.base(sol.x), prob.joints(sol.x)


def _errors(instrument: Instrument, B: np.ndarray, q: JointState, poses: dict[str, np.ndarray],
            trocar: np.ndarray | None) -> tuple[dict[str, tuple[float, float]], float | None]:
    """Per part (rotation deg, translation mm) between the kinematics at (B, q) and ``poses``, and the
    trocar's distance to the shaft axis (None without a trocar)."""
    fk = instrument.forward(B, q)
    res = {n: (float(rotation_angle_deg(fk[n][:3, :3], T[:3, :3])), float(np.linalg.norm(fk[n][:3, 3] - T[:3, 3])))
           for n, T in poses.items()}
    if trocar is None:
        return res, None
    v = trocar - B[:3, 3]
    return res, float(np.linalg.norm(v - B[:3, 2] * (B[:3, 2] @ v)))


def _within(residuals: dict[str, tuple[float, float]], trocar_dist: float | None, cfg: FitConfig) -> bool:
    ok = all(r <= cfg.max_rotation_deg and t <= cfg.max_translation_mm for r, t in residuals.values())
    return ok and (trocar_dist is None or trocar_dist <= cfg.max_translation_mm)


# --------------------------------------------------------------------------------------------- public
def fit_configuration(instrument: Instrument, part_poses: Mapping[str, tuple[np.ndarray, np.ndarray]],
                      weights: Mapping[str, float] | None = None, trocar_mm: np.ndarray | None = None,
                      init: JointFit | None = None, config: FitConfig | None = None,
                      translation_weights: Mapping[str, float] | None = None) -> JointFit:
    """Base pose and joint state of ``instrument`` (from :func:`load_instrument`) that best explain
    ``part_poses`` ({part name: (R 3x3, t mm)}, model-to-camera; any non-empty subset of the parts).

    ``weights``: per part (default 1; 0 drops the part). ``translation_weights``: per part, the weight of
    its translation residual where it differs from ``weights``, which then weighs its rotation residual
    only (parts whose rotations and translations are not equally reliable relative to each other).
    ``trocar_mm``: the remote centre of motion in the camera frame (mm), adds the shaft-axis-through-trocar
    residual. ``init``: the previous frame's fit, used as warm start and as the reference value of joints
    the data do not determine (see the module docstring). Raises ``ValueError`` for unknown part names,
    malformed poses or no usable part.
    """
    cfg = config or FitConfig()
    if not part_poses:
        raise ValueError("fit_configuration needs the pose of at least one part")
    weights = dict(weights or {})
    unknown = sorted((set(part_poses) | set(weights)) - set(instrument.part_names))
    if unknown:
        raise ValueError(f"unknown part(s) {unknown} for instrument {instrument.name!r}; "
                         f"parts are {list(instrument.part_names)}")
    poses: dict[str, np.ndarray] = {}
    w_list = []
    for name in instrument.part_names:  # chain order: parents first
        if name not in part_poses:
            continue
        w = float(weights.get(name, 1.0))
        if not (math.isfinite(w) and w >= 0):
            raise ValueError(f"weight of part {name!r} must be a finite number >= 0, got {w!r}")
        if w == 0:
            continue
        R, t = part_poses[name]
        poses[name] = se3(_as_rotation(R, f"part {name!r}"), _as_point(t, f"part {name!r} translation"))
        wt = float((translation_weights or {}).get(name, w))
        if not (math.isfinite(wt) and wt >= 0):
            raise ValueError(f"translation weight of part {name!r} must be a finite number >= 0, got {wt!r}")
        w_list.append((w, wt))
    if not poses:
        raise ValueError("every given part has weight 0: nothing to fit")
    trocar = None if trocar_mm is None else _as_point(trocar_mm, "trocar_mm")
    names = list(poses)
    limits = _limits(instrument)
    lo = np.array([limits[n][0] for n in JOINT_NAMES])
    hi = np.array([limits[n][1] for n in JOINT_NAMES])

    q_ref = np.array([getattr(init.joints, n) for n in JOINT_NAMES]) if init is not None else np.zeros(4)
    q_ref = np.clip(q_ref, lo, hi)
    roll_ref = None if cfg.roll_reference is None else np.asarray(cfg.roll_reference, dtype=np.float64)

    prob = _Problem(instrument, names, np.stack([poses[n][:3, :3] for n in names]),
                    np.stack([poses[n][:3, 3] for n in names]), np.asarray(w_list), trocar, cfg)

    # Closed-form start; observability is judged there, with every joint free.
    A, b = _pair_relations(instrument, poses)
    q_cf, determined = _closed_form_joints(A, b, q_ref)
    o0, d0, q0 = _start(instrument, poses, q_cf, q_ref, trocar, roll_ref, lo, hi)
    prob.set_direction(d0)
    prob.q_ref = q0.copy()
    observed, held = _observability(prob.analytic_jacobian(np.concatenate([o0, [0.0, 0.0], q0])),
                                     cfg.observability_tol)
    held_idx = [JOINT_NAMES.index(n) for n in held]
    free = [i for i in range(len(JOINT_NAMES)) if i not in held_idx]
    q_cf[held_idx] = q_ref[held_idx]

    def done(sol, B: np.ndarray, q: np.ndarray) -> bool:
        return sol.status > 0 and _within(*_errors(instrument, B, JointState(*q), poses, trocar), cfg)

    roll_free = 0 in free
    sol, B, q = _solve(prob, _start(instrument, poses, q_cf, q_ref, trocar, roll_ref, lo, hi, roll_free),
                       free, lo, hi)
    # A poor start (no seen parent-child pair fixes the wrist angles, or a cold start far from the
    # truth) can end in a local minimum: then also try a small grid of the joints the pairs leave open,
    # the best starts (by initial cost) first, and keep the lowest cost.
    grid_joints = [i for i in free if JOINT_NAMES[i] in GRID and not determined[i]]
    if not done(sol, B, q) and grid_joints:
        starts = []
        for values in itertools.product(*(GRID[JOINT_NAMES[i]] for i in grid_joints)):
            qg = q_cf.copy()
            qg[grid_joints] = np.radians(values)
            st = _start(instrument, poses, qg, q_ref, trocar, roll_ref, lo, hi, roll_free)
            prob.set_direction(st[1])
            prob.q_ref = st[2].copy()
            prob.free = list(range(len(JOINT_NAMES)))
            starts.append((float(np.sum(prob.residuals(np.concatenate([st[0], [0.0, 0.0], st[2]])) ** 2)), st))
        starts.sort(key=lambda c: c[0])
        for _, st in starts[:GRID_STARTS]:
            cand = _solve(prob, st, free, lo, hi)
            if cand[0].cost < sol.cost:
                sol, B, q = cand
            if done(sol, B, q):
                break
    for i in np.flatnonzero(hi - lo >= 2 * math.pi):
        q[i] = _nearest_turn(q[i], q_ref[i], lo[i], hi[i])

    joints = instrument.limits.clip(JointState(*q))
    residuals, trocar_dist = _errors(instrument, B, joints, poses, trocar)
    return JointFit(base_R=B[:3, :3].copy(), base_t=B[:3, 3].copy(), joints=joints, observed=observed,
                    held=tuple(held), residuals=residuals, parts_used=tuple(names),
                    trocar_distance_mm=trocar_dist,
                    ok=bool(sol.status > 0 and _within(residuals, trocar_dist, cfg)),
                    message=str(sol.message), nfev=int(sol.nfev))


def estimate_trocar(base_poses: Sequence[tuple[np.ndarray, np.ndarray]],
                    weights: Sequence[float] | None = None) -> np.ndarray:
    """Least-squares point (camera frame, mm) closest to the shaft axes of many frames, to locate an
    unknown trocar (remote centre of motion).

    ``base_poses``: per frame ``(R, t)`` of the base (e.g. ``(fit.base_R, fit.base_t)``); the axis is the
    line through ``t`` along ``R[:, 2]``. Solves ``sum_i w_i (I - d_i d_i^T) p = sum_i w_i (I - d_i d_i^T)
    t_i``. Raises ``ValueError`` when the axes are (nearly) parallel, i.e. the shaft did not pivot enough
    to locate the point.
    """
    if len(base_poses) < 2:
        raise ValueError("estimate_trocar needs the shaft axis of at least 2 frames")
    w = np.ones(len(base_poses)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(base_poses),) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be one finite value >= 0 per pose")
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for (R, t), wi in zip(base_poses, w):
        d = _as_rotation(R, "base pose")[:, 2]
        P = np.eye(3) - np.outer(d, d)
        A += wi * P
        b += wi * P @ _as_point(t, "base translation")
    ev = np.linalg.eigvalsh(A)
    if ev[0] < 1e-6 * max(ev[-1], 1e-12):
        raise ValueError("the shaft axes are (nearly) parallel: the trocar cannot be located from them")
    return np.linalg.solve(A, b)

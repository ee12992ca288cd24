"""One articulated state per instrument: the filter behind every tracked part of a described instrument.

:class:`InstrumentKalman` is an error-state constant-velocity filter of an instrument's configuration:
its root part's pose (the shaft: position, body rotation, which holds the roll) and the joints that move
the other parts relative to it (e.g. wrist pitch, wrist yaw, jaw opening), each with its rate. State
(``12 + 2n``): ``[t (3) mm, v (3) mm/s, dtheta (3) rad, omega (3) rad/s, q (n) rad, qdot (n) rad/s]``, the
first 12 with :class:`~.kalman.PoseKalman`'s conventions for the root (nominal rotation kept outside the
vector, right perturbations), so :func:`~.smoother.rts_smooth` smooths it unchanged. The parts are views
of this state through the forward kinematics (:class:`~.region.ArticulatedModel`): a part's pose
measurement updates the root and the joints together (an EKF update with the part's Jacobian), so the
wrist's keyframe corrects the shaft's roll and a jaw hidden behind the other tool keeps the pose the
rest of its instrument implies.

:class:`PartFilter` gives one part the interface of a :class:`~.kalman.PoseKalman` over the shared
state, so the tracker's per-part logic (keyframes, gating, restarts, occlusion) stays as it is.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from surftrack.geometry import se3, se3_inv
from surftrack.geometry.transforms import so3_exp, so3_log
from surftrack.instruments import Instrument, JointFit, JointState, base_from_root, joints_from_poses
from surftrack.instruments.kinematics import JOINT_NAMES
from surftrack.track.kalman import (FilterPrior, FilterStep, KalmanConfig, cut_pose_from_rates, gate_limit,
                                    inject_rotation, pose_and_rate_index, pose_transition, speed_std,
                                    white_noise_q)
from surftrack.track.region import ArticulatedModel
from surftrack.track.trocar import Trocar

_POSE = np.r_[0:3, 6:9]  # the root pose's error coordinates in the state (position mm, body rotation rad)


class InstrumentKalman:
    """The articulated state of one instrument instance (see the module docstring).

    ``names``: the instrument's part -> the name its pose goes by (its root part among them); the joints
    of the state are those that move these parts relative to the root. ``joint_accel_std_rad_s2``: the
    joints' white-noise acceleration; ``init_joint_std_deg``: the spread of a joint no measured part has
    pinned yet. ``trocar``: where given, the root's independent poses (:meth:`note_root_pose`) locate the
    instrument's trocar and, once located, every prediction is followed by the constraint that the shaft
    axis passes through it (:mod:`~.trocar`); it outlives the state (a scene's, not a track's)."""

    def __init__(self, instrument: Instrument, names: Mapping[str, str], config: KalmanConfig | None = None,
                 joint_accel_std_rad_s2: float = 2.0, init_joint_std_deg: float = 30.0,
                 trocar: Trocar | None = None):
        root = instrument.chain.order[0]
        if root not in names:
            raise ValueError(f"{instrument.name}: its root part {root!r} is not tracked; track its parts freely")
        self.instrument, self.names = instrument, dict(names)
        self.config = config if config is not None else KalmanConfig()
        self.root = root
        probe = ArticulatedModel(instrument, self.names, np.eye(3), np.zeros(3), JointState())
        self.joints = list(probe.joints)  # indices into JOINT_NAMES
        self.lo, self.hi = probe.lo[self.joints], probe.hi[self.joints]
        self.n = len(self.joints)
        self.dim = 12 + 2 * self.n
        self.joint_q = joint_accel_std_rad_s2 ** 2
        self.init_joint_var = math.radians(init_joint_std_deg) ** 2
        self.kf = KalmanFilter(dim_x=self.dim, dim_z=6)
        self.R_ref = np.eye(3)
        self.time: float | None = None
        self.prior: FilterPrior | None = None
        self.active: set[str] = set()  # names of the parts whose tracks are on this state
        self.q_ref = JointState()  # the last joints, a start for a re-initialisation
        self._model_cache: tuple | None = None
        self.trocar = trocar
        # the shaft axis in the root part's frame: the base's z axis through its origin (the pitch
        # point); the roll turns the root about that axis, so the line is the same at every roll
        F = instrument.forward(np.eye(4), JointState())[root]
        self.axis_point = -F[:3, :3].T @ F[:3, 3]
        self.axis_dir = F[:3, :3].T @ np.array([0.0, 0.0, 1.0])

    # ------------------------------------------------------------------ state
    @property
    def initialized(self) -> bool:
        return self.time is not None

    @property
    def q_index(self) -> np.ndarray:
        return np.arange(12, 12 + self.n)

    @property
    def pose_cols(self) -> np.ndarray:
        """The state's pose and joint error coordinates (position, rotation, joints) ..."""
        return pose_and_rate_index(self.dim)[0]

    @property
    def rate_cols(self) -> np.ndarray:
        """... and their rates, in the same order (velocity, angular velocity, joint rates)."""
        return pose_and_rate_index(self.dim)[1]

    @property
    def x(self) -> np.ndarray:
        return self.kf.x.reshape(self.dim).copy()

    def joint_state(self, x: np.ndarray | None = None) -> JointState:
        """The joints of state ``x`` (default: the current one); joints outside the state keep 0."""
        x = self.x if x is None else x
        q = np.zeros(len(JOINT_NAMES))
        q[self.joints] = np.clip(x[12:12 + self.n], self.lo, self.hi)
        return JointState(*q)

    def model(self, R: np.ndarray | None = None, x: np.ndarray | None = None) -> ArticulatedModel:
        """The forward kinematics at the state (``R`` nominal root rotation, ``x`` state; default the
        current one), its parameter vector 0 at that state."""
        return self._kinematics(R, x)[0]

    def _kinematics(self, R: np.ndarray | None = None, x: np.ndarray | None = None
                    ) -> tuple[ArticulatedModel, dict, dict]:
        """(model, part poses, their derivatives) at a state, kept for the last state asked for: the
        parts of one frame ask in turn."""
        R = self.R_ref if R is None else R
        x = self.x if x is None else x
        key = (R.tobytes(), x.tobytes())
        if self._model_cache is None or self._model_cache[0] != key:
            m = ArticulatedModel(self.instrument, self.names, R @ so3_exp(x[6:9]), x[0:3], self.joint_state(x))
            self._model_cache = (key, m, m.poses(np.zeros(m.size)), m.derivatives(np.zeros(m.size)))
        return self._model_cache[1:]

    def expand(self, D: np.ndarray, model: ArticulatedModel) -> np.ndarray:
        """A (k, 6 + m) derivative in ``model``'s parameters as (k, dim) in the state's error coordinates."""
        H = np.zeros((D.shape[0], self.dim))
        H[:, 0:3], H[:, 6:9] = D[:, 0:3], D[:, 3:6]
        for j, k in enumerate(model.joints):
            H[:, 12 + self.joints.index(k)] = D[:, 6 + j]
        return H

    def part_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """``name``'s pose (R (3, 3), t (3,) mm, model-to-camera) at the current state."""
        _, poses, _ = self._kinematics()
        R, t = poses[name]
        return R.copy(), t.copy()

    def part_jacobian(self, name: str) -> np.ndarray:
        """(6, dim): d(``name``'s pose step: position mm camera frame, body rotation rad) / d(state error)."""
        m, _, D = self._kinematics()
        return self.expand(D[name], m)

    # ------------------------------------------------------------------ init / predict
    def init(self, poses: Mapping[str, tuple[np.ndarray, np.ndarray]], time: float, meas_cov: np.ndarray) -> None:
        """Start the state from measured part poses (name -> (R, t)); never gated. Joints come from the
        parts' relative rotations in closed form (those no part pins keep the last known values, with
        ``init_joint_std_deg``), the root's pose from the root part or else through the chain from the
        most proximal measured part; every given pose is then fused with ``meas_cov`` (6x6)."""
        by_part = {p: se3(*poses[n]) for p, n in self.names.items() if n in poses}
        if not by_part:
            raise ValueError("an instrument state starts from at least one of its parts' poses")
        q = joints_from_poses(self.instrument, by_part, self.q_ref)
        first = next(p for p in self.instrument.chain.order if p in by_part)
        F = self.instrument.forward(np.eye(4), q)
        T_root = by_part[first] @ se3_inv(F[first]) @ F[self.root]
        x = np.zeros(self.dim)
        x[0:3] = T_root[:3, 3]
        qv = np.array([getattr(q, n) for n in JOINT_NAMES])
        x[12:12 + self.n] = qv[self.joints]
        c = self.config
        P = np.zeros((self.dim, self.dim))
        # a wide start, narrowed by fusing the poses themselves: the fused state then carries the
        # correlations between the root and the joints that the measured parts imply
        P[0:3, 0:3] = np.eye(3) * 50.0 ** 2
        P[6:9, 6:9] = np.eye(3) * math.radians(60.0) ** 2
        P[3:6, 3:6] = np.eye(3) * c.init_vel_std_mm_s ** 2
        P[9:12, 9:12] = np.eye(3) * c.init_omega_std_rad_s ** 2
        P[12:12 + self.n, 12:12 + self.n] = np.eye(self.n) * self.init_joint_var
        P[12 + self.n:, 12 + self.n:] = np.eye(self.n) * c.init_omega_std_rad_s ** 2
        self.R_ref = T_root[:3, :3].copy()
        self.kf.x = x.reshape(-1, 1)
        self.kf.P = P
        self.time = float(time)
        self.prior = None
        self._model_cache = None
        for n, (R, t) in poses.items():
            if n in self.names.values():
                self.update_part(n, R, t, meas_cov, gate=False)
        self.active = {n for n in poses if n in self.names.values()}

    def reset(self) -> None:
        """Forget the state (no part of the instrument is tracked any more)."""
        if self.initialized:
            self.q_ref = self.joint_state()
        self.time, self.prior, self.active, self._model_cache = None, None, set(), None

    def _transition(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The root's pose transition (:func:`~.kalman.pose_transition`) and the joints' constant rates."""
        F, Q = np.eye(self.dim), np.zeros((self.dim, self.dim))
        F[:12, :12], Q[:12, :12] = pose_transition(self.kf.x.reshape(self.dim)[9:12], dt, self.config)
        F[12:12 + self.n, 12 + self.n:] = np.eye(self.n) * dt
        Q[12:, 12:] = white_noise_q(dt, self.joint_q, self.n)
        return F, Q

    def predict(self, time: float) -> None:
        """Propagate to ``time`` (s); a no-op when the state is already there (the parts share one step)."""
        if not self.initialized:
            raise RuntimeError("the instrument state is not initialised")
        dt = float(time) - self.time
        if dt == 0.0:
            return
        if dt < 0:
            raise ValueError(f"predict needs a positive dt, got {dt!r}")
        x = self.kf.x.reshape(self.dim)
        R_next = self.R_ref @ so3_exp(x[6:9]) @ so3_exp(x[9:12] * dt)
        F, Q = self._transition(dt)
        self.kf.predict(F=F, Q=Q)
        xn = self.kf.x.reshape(self.dim).copy()
        xn[6:9] = 0.0
        # a joint carried past its limit stops there: the views, the innovations and the rates (the tool
        # tip's velocity) then agree on where it is
        q, rate = xn[12:12 + self.n], xn[12 + self.n:]
        rate[((q <= self.lo) & (rate < 0)) | ((q >= self.hi) & (rate > 0))] = 0.0
        xn[12:12 + self.n] = np.clip(q, self.lo, self.hi)
        self.kf.x = xn.reshape(-1, 1)
        self.R_ref, self.time = R_next, float(time)
        self.prior = FilterPrior(F, R_next.copy(), xn.copy(), self.kf.P.copy())
        self._model_cache = None
        self._constrain_to_trocar()

    def root_axis(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The shaft axis (a point mm, a unit direction; camera frame) of the root part at pose (R, t)."""
        return R @ self.axis_point + t, R @ self.axis_dir

    def _constrain_to_trocar(self) -> None:
        """Fuse "the shaft axis passes through the trocar" (2D, gated) once the trocar is located; a
        refusal counts towards forgetting it."""
        if self.trocar is None or self.trocar.point is None:
            return
        x = self.kf.x.reshape(self.dim)
        R = self.R_ref @ so3_exp(x[6:9])
        res = self.trocar.residual(*self.root_axis(R, x[0:3]), R, self.axis_point, self.axis_dir)
        if res is None:
            return
        y, J, cov = res
        H = np.zeros((2, self.dim))
        H[:, 0:3], H[:, 6:9] = J[:, 0:3], J[:, 3:6]
        ok, _ = self._fuse(y, H, cov, gate=True, dof=2)
        if ok:
            self.trocar.accept()
        else:
            self.trocar.refuse()

    # ------------------------------------------------------------------ measurements
    def _fuse(self, y: np.ndarray, H: np.ndarray, cov: np.ndarray, gate: bool, dof: int) -> tuple[bool, float]:
        """EKF update with innovation ``y`` (k,) = H dx + noise; gated at chi2(k) 99.9 % (scaled as the
        part filter's ``gate_chi2``) unless ``gate`` is False. Returns (fused, d2)."""
        x = self.kf.x.reshape(self.dim)
        S = H @ self.kf.P @ H.T + cov
        d2 = float(y @ np.linalg.solve(S, y))
        if not math.isfinite(d2) or (gate and d2 > gate_limit(self.config, dof)):
            return False, d2
        self.kf.update((y + H @ x).reshape(-1, 1), R=cov, H=H)
        self.R_ref, x, self.kf.P = inject_rotation(self.R_ref, self.kf.x.reshape(self.dim), self.kf.P)
        x[12:12 + self.n] = np.clip(x[12:12 + self.n], self.lo, self.hi)
        self.kf.x = x.reshape(-1, 1)
        self._model_cache = None
        return True, d2

    def update_part(self, name: str, R: np.ndarray, t: np.ndarray, meas_cov: np.ndarray, gate: bool = True,
                    basis: np.ndarray | None = None) -> tuple[bool, float]:
        """Fuse a pose measurement of part ``name`` (``meas_cov`` 6x6, or m x m for ``basis`` m x 6 as in
        :meth:`PoseKalman.update`). Returns (fused, squared Mahalanobis distance)."""
        R_p, t_p = self.part_pose(name)
        y = np.concatenate([np.asarray(t, np.float64) - t_p, so3_log(R_p.T @ np.asarray(R, np.float64))])
        H = self.part_jacobian(name)
        if basis is not None:
            y, H = basis @ y, basis @ H
        return self._fuse(y, H, np.asarray(meas_cov, np.float64), gate, len(y))

    def note_root_pose(self, R: np.ndarray, t: np.ndarray) -> None:
        """An independent measurement of the root's pose (the estimator's, fused): its shaft axis helps
        locate the trocar (flow's poses are not: their points were lifted with the state's own pose)."""
        if self.trocar is not None:
            self.trocar.add_axis(*self.root_axis(np.asarray(R, np.float64), np.asarray(t, np.float64)))

    def update_model(self, model: ArticulatedModel, step: np.ndarray, basis: np.ndarray, cov: np.ndarray,
                     gate: bool = True) -> tuple[bool, float]:
        """Fuse a measurement of ``model``'s parameters (made at this state: its 0 is the state's nominal):
        ``basis @ params = basis @ step`` with covariance ``cov`` (m x m), e.g. a region fit's."""
        if len(basis) == 0:
            return False, math.nan
        H = self.expand(basis, model)
        return self._fuse(basis @ step, H, np.asarray(cov, np.float64), gate, len(basis))

    def widen(self, pose_cov: np.ndarray, joint_var: float) -> None:
        """Add ``pose_cov`` (6x6) to the root pose's covariance and ``joint_var`` to every joint's, and cut
        the pose and joints loose from the rates (a jump says nothing about the velocities): for a
        measurement the state disbelieves (:meth:`PoseKalman.restart`). Applied to the current state, so
        the other parts' updates of this frame stay; the frame's prediction gets the same widening (as
        extra process noise for the smoother)."""
        def widened(P: np.ndarray) -> np.ndarray:
            P = P.copy()
            P[np.ix_(_POSE, _POSE)] += pose_cov
            P[12:12 + self.n, 12:12 + self.n] += np.eye(self.n) * joint_var
            return cut_pose_from_rates(P)

        self.kf.P = widened(self.kf.P)
        if self.prior is not None:
            self.prior = FilterPrior(self.prior.F, self.prior.R, self.prior.x, widened(self.prior.P), restarted=True)
        self._model_cache = None

    # ------------------------------------------------------------------ output
    def snapshot(self) -> FilterStep:
        """The filtered state with its prior (copies), for :func:`~.smoother.rts_smooth`."""
        return FilterStep(self.time, self.R_ref.copy(), self.x, self.kf.P.copy(), self.prior)

    def part_step(self, step: FilterStep, name: str) -> FilterStep:
        """Part ``name``'s view of the instrument step ``step`` (a 12-state :class:`FilterStep`: its pose,
        its velocity and angular velocity, their covariance, to first order; no prior)."""
        m, poses, D = self._kinematics(step.R, step.x)
        R, t = poses[name]
        J = self.expand(D[name], m)  # (6, dim) pose step / state error
        M = np.zeros((12, self.dim))  # the part's 12-state error as a linear map of the instrument's
        M[0:3], M[6:9] = J[0:3], J[3:6]
        M[3:6, self.rate_cols], M[9:12, self.rate_cols] = J[0:3, self.pose_cols], J[3:6, self.pose_cols]
        x = np.zeros(12)
        x[0:3] = t
        x[3:6], x[9:12] = M[3:6] @ step.x, M[9:12] @ step.x
        P = M @ step.P @ M.T
        return FilterStep(step.time, R.copy(), x, 0.5 * (P + P.T), None)


@dataclass(frozen=True)
class JointReading:
    """An instrument's joints read off its (smoothed) state: ``fit`` (base pose, all joints with the roll,
    as the per-frame fit reports them), per joint name its rate (rad/s) and standard deviation (rad), and
    the tool tip (R, t mm) with its position's 3x3 covariance (mm^2), its velocity (3,) mm/s in the camera
    frame and that velocity's 3x3 covariance ((mm/s)^2), each None without a tip."""

    fit: JointFit
    rates: dict[str, float]
    std: dict[str, float]
    tip: tuple[np.ndarray, np.ndarray] | None
    tip_cov: np.ndarray | None
    tip_velocity: np.ndarray | None = None
    tip_velocity_cov: np.ndarray | None = None

    @property
    def tip_speed_std(self) -> float | None:
        """The tip speed's standard deviation (mm/s) along its velocity (what a path length integrates)."""
        if self.tip_velocity_cov is None:
            return None
        return speed_std(self.tip_velocity, self.tip_velocity_cov)


def read_joints(kf: InstrumentKalman, step: FilterStep, parts: Sequence[str] | None = None) -> JointReading:
    """The joints, their rates and uncertainties, and the tool tip of instrument state ``step`` of ``kf``
    (no fit: the state is the instrument's configuration). ``parts``: the names of the parts posed on
    this frame (default all): the tool tip comes from those only."""
    inst = kf.instrument
    m, poses, _ = kf._kinematics(step.R, step.x)
    by_part = {p: se3(*poses[n]) for p, n in kf.names.items()}
    posed = {p: T for p, T in by_part.items() if parts is None or kf.names[p] in parts}
    q = kf.joint_state(step.x)
    base, roll = base_from_root(inst, by_part[kf.root], q)
    joints = JointState(**{**q.as_dict(), "roll": roll})
    # the roll is measured from a reference that follows the shaft's direction, so it moves with every
    # turn of the shaft, not only with turns about its axis: its gradient in the root's body rotation
    g, h = np.zeros(3), 1e-6
    for i in range(3):
        T = by_part[kf.root].copy()
        T[:3, :3] = T[:3, :3] @ so3_exp(np.eye(3)[i] * h)
        g[i] = math.remainder(base_from_root(inst, T, q)[1] - roll, 2 * math.pi) / h
    rates = {"roll": float(g @ step.x[9:12])}
    var = {"roll": float(g @ step.P[6:9, 6:9] @ g)}
    for j, k in enumerate(kf.joints):
        rates[JOINT_NAMES[k]] = float(step.x[12 + kf.n + j])
        var[JOINT_NAMES[k]] = float(step.P[12 + j, 12 + j])
    fit = JointFit(base[:3, :3], base[:3, 3], joints, {n: n in var for n in JOINT_NAMES},
                   tuple(n for n in JOINT_NAMES if n not in var), {}, tuple(posed), None, True)
    tip = inst.tool_tip(posed)
    tip_cov = tip_vel = tip_vel_cov = None
    if tip is not None:
        # the tip's position through the kinematics, differentiated numerically in the state's pose and joints
        h, J = 1e-5, np.zeros((3, m.size))
        for i in range(m.size):
            e = np.zeros(m.size)
            e[i] = h
            moved_poses = m.poses(e)
            moved = {p: se3(*moved_poses[kf.names[p]]) for p in posed}
            J[:, i] = (inst.tool_tip(moved)[1] - tip[1]) / h
        Js = J @ kf.expand(np.eye(m.size), m)  # (3, dim) in the state's error coordinates
        tip_cov = Js @ step.P @ Js.T
        # the tip moves as the state's rates move its pose and joints (first order, as part_step)
        Jr = Js[:, kf.pose_cols]
        tip_vel = Jr @ step.x[kf.rate_cols]
        tip_vel_cov = Jr @ step.P[np.ix_(kf.rate_cols, kf.rate_cols)] @ Jr.T
    return JointReading(fit, rates, {n: math.sqrt(max(v, 0.0)) for n, v in var.items()}, tip, tip_cov,
                        tip_vel, tip_vel_cov)


class PartFilter:
    """One part's window on an :class:`InstrumentKalman`, with :class:`~.kalman.PoseKalman`'s interface
    as the tracker uses it. A part's own gate count (``rejections_in_a_row``) stays per part: one part's
    estimator outliers do not lock out the others'."""

    def __init__(self, shared: InstrumentKalman, name: str, widen: np.ndarray | None = None,
                 widen_joint_deg: float = 30.0):
        """``widen`` (6x6, mm^2 then rad^2): what a measurement the state disbelieves adds to the root's
        predicted pose (:meth:`restart`, and a part joining a state that disagrees with it)."""
        self.shared, self.name = shared, name
        self.config = shared.config
        self.rejections_in_a_row = 0
        self.last_d2: float | None = None
        self._widen = np.diag([50.0 ** 2] * 3 + [math.radians(30.0) ** 2] * 3) if widen is None else widen
        self._widen_joint = math.radians(widen_joint_deg) ** 2

    @property
    def initialized(self) -> bool:
        return self.shared.initialized and self.name in self.shared.active

    @property
    def time(self) -> float | None:
        return self.shared.time

    @property
    def lost(self) -> bool:
        return self.rejections_in_a_row >= self.config.max_rejections

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self.shared.part_pose(self.name)

    @property
    def pose_cov(self) -> np.ndarray:
        """6x6 covariance of this part's pose (position mm, body rotation rad)."""
        J = self.shared.part_jacobian(self.name)
        return J @ self.shared.kf.P @ J.T

    @property
    def prior(self) -> FilterPrior | None:
        return self.shared.prior

    @prior.setter
    def prior(self, value: FilterPrior | None) -> None:  # None: a new segment (set_pose)
        self.shared.prior = value

    def init(self, R: np.ndarray, t: np.ndarray, time: float, meas_cov: np.ndarray | None = None) -> None:
        """Put this part on the state: start the state from it when none of its instrument's parts is
        tracked, else fuse it into the state the others hold, never gated out (gated, the state's drift
        while the part was away kept it out: docs/decisions.md). A measurement the gate would reject is
        a jump, fused as :meth:`restart` fuses one (fused plainly, a 100 deg disagreement became a roll
        rate that spun the instrument)."""
        cov = self.config.meas_cov() if meas_cov is None else meas_cov
        s = self.shared
        self.rejections_in_a_row, self.last_d2 = 0, None
        if s.initialized and self.name in s.active and s.time == time:
            return  # started together with the instrument (InstrumentKalman.init) this frame
        if not s.initialized or not (s.active - {self.name}):
            s.init({self.name: (R, t)}, time, cov)
            return
        if time > s.time:
            s.predict(time)
        ok, self.last_d2 = s.update_part(self.name, R, t, cov, gate=True)
        if not ok:
            self._jump(R, t, cov)
        s.active.add(self.name)

    def predict(self, time: float, coast: bool = False) -> None:
        self.shared.predict(time)  # the instrument's state: its other parts may well be measured

    def update(self, R_meas: np.ndarray, t_meas: np.ndarray, meas_cov: np.ndarray | None = None,
               gate: bool = True, basis: np.ndarray | None = None, counts: bool = True) -> bool:
        """As :meth:`PoseKalman.update`, through the instrument's state."""
        cov = self.config.meas_cov() if meas_cov is None else np.asarray(meas_cov, np.float64)
        if not (np.isfinite(R_meas).all() and np.isfinite(t_meas).all() and np.isfinite(cov).all()):
            self.rejections_in_a_row += counts
            self.last_d2 = math.inf
            return False
        ok, self.last_d2 = self.shared.update_part(self.name, R_meas, t_meas, cov, gate, basis)
        if counts:
            self.rejections_in_a_row = 0 if ok else self.rejections_in_a_row + 1
        return ok

    def restart(self, R_meas: np.ndarray, t_meas: np.ndarray, meas_cov: np.ndarray, widen: np.ndarray) -> None:
        """The estimator disagreed with this part's track ``max_rejections`` times in a row: widen the
        instrument's prediction and fuse the measurement ungated. The root part's disagreement widens the
        root's pose (by ``widen``) and the joints (by ``widen_joint_deg``); another part's only the joints,
        which is all it can tell apart from the rest of its instrument."""
        self._jump(R_meas, t_meas, meas_cov, widen)

    @property
    def is_root(self) -> bool:
        """This part is its instrument's root (the shaft)."""
        return self.name == self.shared.names[self.shared.root]

    def _jump(self, R: np.ndarray, t: np.ndarray, cov: np.ndarray, widen: np.ndarray | None = None) -> None:
        widen = self._widen if widen is None else widen
        self.shared.widen(widen if self.is_root else np.zeros((6, 6)), self._widen_joint)
        self.update(R, t, cov, gate=False)

    def snapshot(self) -> FilterStep:
        return self.shared.part_step(self.shared.snapshot(), self.name)

    def deactivate(self) -> None:
        """This part's track ended; the state is forgotten once no part of the instrument is tracked."""
        self.shared.active.discard(self.name)
        if not self.shared.active:
            self.shared.reset()

import numpy as np
import pytest

from surftrack.geometry import rotation_about, rotation_angle_deg, so3_exp, so3_log
from surftrack.track import CHI2_6DOF_999, KalmanConfig, PoseKalman


def _trajectory(n, rng, axis=(0.3, -0.5, 0.8), w=1.5, angle0=0.3, mean_dt=1 / 30):
    """Constant-velocity trajectory with variable frame times: rotation about a fixed world axis."""
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 1.5, n - 1) * mean_dt)])
    R0 = so3_exp(np.array([0.2, -0.4, 0.1]))
    t0 = np.array([10.0, -20.0, 120.0])
    v = np.array([30.0, -15.0, 8.0])
    Rs = np.stack([rotation_about(axis, angle0 + w * s) @ R0 for s in times])
    ts = t0 + times[:, None] * v
    return times, Rs, ts


def _noisy(Rs, ts, rng, pos_std=3.0, rot_std_deg=3.0):
    Rm = np.stack([R @ so3_exp(rng.normal(scale=np.radians(rot_std_deg), size=3)) for R in Rs])
    tm = ts + rng.normal(scale=pos_std, size=ts.shape)
    return Rm, tm


def _track(times, Rm, tm, config=None):
    kf = PoseKalman(config)
    Re, te, accepted = [], [], []
    for i, s in enumerate(times):
        if i == 0:
            kf.init(Rm[0], tm[0], s)
            accepted.append(True)
        else:
            kf.predict(s)
            accepted.append(kf.update(Rm[i], tm[i]))
        R, t = kf.pose
        Re.append(R)
        te.append(t)
    return kf, np.stack(Re), np.stack(te), np.array(accepted)


def _rms(Ra, ta, Rb, tb):
    pos = np.sqrt(np.mean(np.sum((ta - tb) ** 2, axis=1)))
    rot = np.sqrt(np.mean(rotation_angle_deg(Ra, Rb) ** 2))
    return pos, rot


def test_state_has_12_entries_no_quaternion():
    kf = PoseKalman()
    kf.init(np.eye(3), np.zeros(3), 0.0)
    assert kf.kf.x.size == 12 and kf.x.shape == (12,)
    assert kf.kf.P.shape == (12, 12)
    assert kf.kf.dim_z == 6


@pytest.mark.parametrize("config, factor", [
    (None, 0.8),  # defaults (sized for real, accelerating instrument motion)
    (KalmanConfig(accel_std_mm_s2=30.0, ang_accel_std_rad_s2=0.5), 0.55),  # tuned to this CV trajectory
])
def test_tracking_beats_raw_measurements(config, factor):
    rng = np.random.default_rng(0)
    times, Rs, ts = _trajectory(300, rng)
    Rm, tm = _noisy(Rs, ts, rng)
    kf, Re, te, acc = _track(times, Rm, tm, config)
    skip = 30  # let the velocity estimate converge
    raw_pos, raw_rot = _rms(Rm[skip:], tm[skip:], Rs[skip:], ts[skip:])
    kf_pos, kf_rot = _rms(Re[skip:], te[skip:], Rs[skip:], ts[skip:])
    print(f"RMS position raw {raw_pos:.2f} mm -> KF {kf_pos:.2f} mm; "
          f"rotation raw {raw_rot:.2f} deg -> KF {kf_rot:.2f} deg")
    assert acc.mean() > 0.98
    assert kf_pos < factor * raw_pos
    assert kf_rot < factor * raw_rot
    assert np.all(kf.position_std_mm < 3.0) and np.all(kf.rotation_std_deg < 3.0)
    # the estimated velocities agree with the truth (body-frame omega = R^T axis * w) within 4 sigma
    v, omega = kf.velocity
    sd = np.sqrt(np.diag(kf.covariance))
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    assert np.all(np.abs(v - [30.0, -15.0, 8.0]) < 4 * sd[3:6])
    assert np.all(np.abs(omega - Rs[-1].T @ axis * 1.5) < 4 * sd[9:12])


def test_predict_only_extrapolates_constant_velocity_exactly():
    rng = np.random.default_rng(1)
    times, Rs, ts = _trajectory(40, rng, w=2.0)
    kf = PoseKalman()
    kf.init(Rs[0], ts[0], times[0])
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    x = kf.kf.x.copy()
    x[3:6, 0] = [30.0, -15.0, 8.0]
    x[9:12, 0] = Rs[0].T @ axis * 2.0  # body-frame angular velocity of a fixed world-axis rotation
    kf.kf.x = x
    R_pred, t_pred = kf.predicted_pose(times[-1])
    assert np.allclose(t_pred, ts[-1], atol=1e-9)
    assert np.allclose(R_pred, Rs[-1], atol=1e-10)
    P_before = kf.covariance
    for s, R, t in zip(times[1:], Rs[1:], ts[1:]):
        kf.predict(s)
        Re, te = kf.pose
        assert np.allclose(te, t, atol=1e-9)
        assert np.allclose(Re, R, atol=1e-10)
    assert np.all(kf.x[6:9] == 0.0)
    # uncertainty grows without measurements
    assert np.all(np.diag(kf.covariance) >= np.diag(P_before) - 1e-12)
    assert np.all(kf.position_std_mm > np.sqrt(np.diag(P_before)[:3]))


def test_predicted_pose_does_not_mutate():
    kf = PoseKalman()
    kf.init(np.eye(3), np.ones(3), 1.0)
    x, P, R = kf.x, kf.covariance, kf.R_ref.copy()
    kf.predicted_pose(2.0)
    assert np.array_equal(kf.x, x) and np.array_equal(kf.covariance, P) and np.array_equal(kf.R_ref, R)
    assert kf.time == 1.0


@pytest.mark.parametrize("dt", [0.0, -0.01])
def test_nonpositive_dt_raises(dt):
    kf = PoseKalman()
    kf.init(np.eye(3), np.zeros(3), 5.0)
    with pytest.raises(ValueError):
        kf.predict(5.0 + dt)


def test_outlier_is_gated_and_normal_measurements_pass():
    rng = np.random.default_rng(2)
    times, Rs, ts = _trajectory(60, rng)
    Rm, tm = _noisy(Rs, ts, rng)
    kf, *_ = _track(times[:40], Rm[:40], tm[:40])
    assert kf.rejections_in_a_row == 0
    outliers = [
        (Rm[40], tm[40] + np.array([50.0, 0.0, 0.0])),           # 50 mm off
        (Rm[40] @ rotation_about([0, 0, 1], np.pi / 2), tm[40]),  # 90 deg off
        (Rm[40] @ rotation_about([1, 1, 0], np.pi / 2), tm[40] - 50.0),
    ]
    for k, (Ro, to) in enumerate(outliers, start=1):
        kf.predict(times[39 + k])
        x, P, R_ref = kf.x, kf.covariance, kf.R_ref.copy()
        assert kf.gate(Ro, to) > CHI2_6DOF_999
        assert kf.update(Ro, to) is False
        assert np.array_equal(kf.x, x) and np.array_equal(kf.covariance, P)
        assert np.array_equal(kf.R_ref, R_ref)
        assert kf.rejections_in_a_row == k
    assert not kf.lost
    # a normal measurement passes and resets the counter
    kf.predict(times[43])
    assert kf.gate(Rm[43], tm[43]) < CHI2_6DOF_999
    assert kf.update(Rm[43], tm[43]) is True
    assert kf.rejections_in_a_row == 0
    # gate=False forces the update
    kf.predict(times[44])
    assert kf.update(Rm[44], tm[44] + 50.0, gate=False) is True
    # a non-finite pose is never fused, gated or not
    kf.predict(times[45])
    x = kf.x
    for forced in (True, False):
        assert kf.update(Rm[45], tm[45] * np.nan, gate=forced) is False
        assert kf.update(Rm[45] * np.nan, tm[45], gate=forced) is False
    assert np.array_equal(kf.x, x) and np.isfinite(kf.covariance).all()
    with pytest.raises(ValueError, match="non-finite"):
        kf.init(Rm[45] * np.nan, tm[45], times[45])


def test_noise_settings_are_checked():
    for bad, msg in (({"meas_pos_std_mm": 0.0}, "meas_pos_std_mm must be > 0"),
                     ({"gate_chi2": float("nan")}, "gate_chi2 must be a finite number"),
                     ({"accel_std_mm_s2": "200"}, "accel_std_mm_s2 must be a finite number"),
                     ({"max_rejections": 0}, "max_rejections must be >= 1"),
                     ({"max_rejections": 2.5}, "max_rejections must be an integer")):
        with pytest.raises(ValueError, match=msg):
            KalmanConfig(**bad)
    assert KalmanConfig(max_rejections=3.0).max_rejections == 3


def test_lost_after_max_rejections_and_reinit():
    kf = PoseKalman(KalmanConfig(max_rejections=3))
    kf.init(np.eye(3), np.zeros(3), 0.0)
    for i in range(3):
        kf.predict(0.033 * (i + 1))
        assert kf.update(np.eye(3), np.array([100.0, 0, 0])) is False
    assert kf.lost
    kf.init(np.eye(3), np.array([100.0, 0, 0]), 0.2)
    assert not kf.lost and kf.rejections_in_a_row == 0


def test_only_counted_measurements_make_a_track_lost():
    """What counts towards ``lost`` is the estimator's disagreement: a gated-out measurement passed with
    ``counts=False`` (a silhouette fit, flow) neither adds a rejection nor, accepted, clears one."""
    kf = PoseKalman(KalmanConfig(max_rejections=3))
    kf.init(np.eye(3), np.zeros(3), 0.0)
    far, near = np.array([100.0, 0, 0]), np.array([0.1, 0, 0])
    kf.predict(0.033)
    assert kf.update(np.eye(3), far) is False and kf.rejections_in_a_row == 1
    for i in range(2, 6):
        kf.predict(0.033 * i)
        assert kf.update(np.eye(3), far, counts=False) is False
    assert kf.rejections_in_a_row == 1 and not kf.lost
    kf.predict(0.2)
    assert kf.update(np.eye(3), near, counts=False) is True and kf.rejections_in_a_row == 1
    for i in range(2):
        kf.predict(0.25 + 0.033 * i)
        kf.update(np.eye(3), far)
    assert kf.lost


def test_init_is_never_gated():
    kf = PoseKalman()
    kf.init(np.eye(3), np.zeros(3), 0.0)
    R_far = rotation_about([0, 1, 0], 3.0)
    t_far = np.array([500.0, -400.0, 900.0])
    assert kf.gate(R_far, t_far) > CHI2_6DOF_999
    kf.init(R_far, t_far, 0.1)  # re-initialisation from the estimator is accepted unconditionally
    R, t = kf.pose
    assert np.allclose(t, t_far) and rotation_angle_deg(R, R_far) < 1e-9
    # step() initialises on its first call without gating
    kf2 = PoseKalman()
    assert kf2.step(0.0, R_far, t_far) is True
    with pytest.raises(RuntimeError):
        PoseKalman().predict(1.0)


def test_rotation_wraparound_through_pi():
    rng = np.random.default_rng(3)
    axis = np.array([0.0, 0.6, 0.8])
    # absolute rotation (R0 = I, angle from 150 deg to ~250 deg): so3_log flips sign at 180 deg
    times = np.concatenate([[0.0], np.cumsum(rng.uniform(0.02, 0.045, 119))])
    w = np.radians(100) / times[-1]
    Rs = np.stack([rotation_about(axis, np.radians(150) + w * s) for s in times])
    ts = np.tile([0.0, 0.0, 100.0], (len(times), 1))
    rv = so3_log(Rs)
    assert np.any(rv @ axis > 0) and np.any(rv @ axis < 0)  # the rotation vector really wraps
    Rm, tm = _noisy(Rs, ts, rng, rot_std_deg=2.0)
    kf, Re, te, acc = _track(times, Rm, tm)
    assert acc.all()
    err = rotation_angle_deg(Re, Rs)
    raw = rotation_angle_deg(Rm, Rs)
    assert err[10:].max() < 8.0  # no jump when the rotation vector flips at 180 deg
    assert np.sqrt(np.mean(err[20:] ** 2)) < np.sqrt(np.mean(raw[20:] ** 2))


def test_gate_matches_hand_computation():
    rng = np.random.default_rng(4)
    times, Rs, ts = _trajectory(20, rng)
    Rm, tm = _noisy(Rs, ts, rng)
    kf, *_ = _track(times[:15], Rm[:15], tm[:15])
    kf.predict(times[15])
    meas_cov = np.diag([4.0, 9.0, 16.0, 1e-3, 2e-3, 3e-3])
    meas_cov[0, 1] = meas_cov[1, 0] = 1.0
    R_meas, t_meas = Rm[15] @ so3_exp([0.05, -0.02, 0.03]), tm[15] + [2.0, -1.0, 3.0]
    d2 = kf.gate(R_meas, t_meas, meas_cov)
    P = kf.covariance
    H = np.zeros((6, 12))
    H[0:3, 0:3] = np.eye(3)
    H[3:6, 6:9] = np.eye(3)
    y = np.concatenate([t_meas - kf.pose[1], so3_log(kf.pose[0].T @ R_meas)])
    S = H @ P @ H.T + meas_cov
    assert np.isclose(d2, y @ np.linalg.inv(S) @ y, rtol=1e-10)
    # gate does not mutate; update's d2 (before the update) equals gate's
    x = kf.x
    kf.update(R_meas, t_meas, meas_cov, gate=False)
    assert np.isclose(kf.last_d2, d2, rtol=1e-12)
    assert not np.array_equal(kf.x, x)


def test_default_config():
    c = KalmanConfig()
    assert c.gate_chi2 == pytest.approx(22.46)
    assert c.meas_cov().shape == (6, 6)
    assert np.isclose(c.meas_cov()[3, 3], np.radians(c.meas_rot_std_deg) ** 2)


def test_a_measurement_of_some_directions_leaves_the_others_alone():
    """A ``basis`` update (a silhouette seeing x, y and the in-plane turn, not the depth) equals the full
    update with an infinitely uncertain depth, and moves nothing it does not see."""
    rng = np.random.default_rng(5)
    times, Rs, ts = _trajectory(12, rng)
    Rm, tm = _noisy(Rs, ts, rng)
    kf, *_ = _track(times[:10], Rm[:10], tm[:10], KalmanConfig(accel_std_mm_s2=1e-6))  # no coupling by noise
    kf.predict(times[10])
    ref = PoseKalman(kf.config)
    ref.kf.x, ref.kf.P, ref.R_ref, ref.time = kf.kf.x.copy(), kf.kf.P.copy(), kf.R_ref.copy(), kf.time
    basis = np.zeros((3, 6))
    basis[0, 0] = basis[1, 1] = basis[2, 5] = 1.0
    R_meas, t_meas = kf.pose[0] @ so3_exp([0.0, 0.0, 0.05]), kf.pose[1] + [1.0, -2.0, 30.0]  # depth way off
    assert kf.update(R_meas, t_meas, np.diag([0.5, 0.5, 1e-3]), basis=basis)
    full = np.diag([0.5, 0.5, 1e12, 1e12, 1e12, 1e-3])
    assert ref.update(R_meas, t_meas, full, gate=False)
    np.testing.assert_allclose(kf.pose[1], ref.pose[1], atol=1e-4)
    np.testing.assert_allclose(kf.pose[0], ref.pose[0], atol=1e-7)
    # the depth came from the prediction (and its correlation with x, y), not the measurement's +30 mm
    assert abs(kf.pose[1][2] - t_meas[2]) > 25.0
    # the gate counts 3 degrees of freedom: chi2(3) 99.9 % = 16.27 rejects a d2 of 19 that 6 would pass
    kf.predict(times[11])
    cov = np.diag([0.5, 0.5, 1e-3])
    H = np.zeros((6, 12))
    H[0:3, 0:3] = np.eye(3)
    H[3:6, 6:9] = np.eye(3)
    S = basis @ H @ kf.kf.P @ H.T @ basis.T + cov
    y = np.array([1.0, 0.0, 0.0])
    y *= np.sqrt(19.0 / (y @ np.linalg.solve(S, y)))
    assert not kf.update(kf.pose[0], kf.pose[1] + [y[0], 0.0, 0.0], cov, basis=basis)
    assert np.isclose(kf.last_d2, 19.0) and 19.0 < CHI2_6DOF_999


def test_coasting_velocities_decay_and_the_prior_records_it():
    """A part that goes unmeasured (``coast``) keeps a decaying share of its velocities, so its pose stops
    short of where constant velocity would carry it; without ``coast`` (or with ``coast_tau_s`` 0) the
    prediction is constant velocity. The recorded prior's F holds the decay (the smoother reads it)."""
    tau, dt, n = 0.1, 1 / 30, 6
    v, w = np.array([30.0, -15.0, 8.0]), np.array([0.0, 0.0, 2.0])
    poses = {}
    for name, cfg, coast in (("cv", KalmanConfig(coast_tau_s=tau), False), ("off", KalmanConfig(coast_tau_s=0), True),
                             ("coast", KalmanConfig(coast_tau_s=tau), True)):
        kf = PoseKalman(cfg)
        kf.init(np.eye(3), np.zeros(3), 0.0)
        x = kf.kf.x.copy()
        x[3:6, 0], x[9:12, 0] = v, w
        kf.kf.x = x
        for k in range(1, n + 1):
            kf.predict(k * dt, coast=coast)
        poses[name] = (kf.pose, kf.x.copy(), kf.prior.F)
    (R_cv, t_cv), x_cv, F_cv = poses["cv"]
    assert np.allclose(t_cv, v * n * dt) and np.allclose(x_cv[3:6], v)
    assert np.allclose(poses["off"][0][1], t_cv) and np.allclose(poses["off"][2], F_cv)
    (R_c, t_c), x_c, F_c = poses["coast"]
    a = np.exp(-dt / tau)
    assert np.allclose(x_c[3:6], v * a ** n) and np.allclose(x_c[9:12], w * a ** n)
    assert np.allclose(t_c, v * dt * sum(a ** k for k in range(n)))  # each step moves by the velocity it starts with
    assert np.allclose(F_c[3:6, 3:6], np.eye(3) * a) and np.allclose(F_c[9:12, 9:12], np.eye(3) * a)
    assert rotation_angle_deg(R_c, np.eye(3)) < rotation_angle_deg(R_cv, np.eye(3))


def test_coast_time_constant_is_checked():
    with pytest.raises(ValueError, match="coast_tau_s must be >= 0"):
        KalmanConfig(coast_tau_s=-0.1)
    assert KalmanConfig(coast_tau_s=0).coast_tau_s == 0.0


def test_change_chart_follows_the_rotation_map():
    """The re-expressed covariance is the original one through the numerical Jacobian of moving a rotation
    error to the other chart, and leaving it unchanged would be measurably off ~29 deg apart."""
    from surftrack.track.kalman import change_chart

    rng = np.random.default_rng(5)
    R_from = so3_exp(np.array([0.3, -1.2, 2.0]))
    R_to = R_from @ so3_exp(np.array([0.35, 0.2, -0.3]))
    x = np.zeros(12)
    x[6:9] = [0.1, -0.05, 0.08]
    A = rng.normal(size=(12, 12))
    P = 1e-4 * (A @ A.T + np.eye(12))
    x2, P2 = change_chart(R_from, x, P, R_to)
    assert np.allclose(so3_exp(x2[6:9]), R_to.T @ R_from @ so3_exp(x[6:9]))
    J, h = np.eye(12), 1e-6
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        moved = [so3_log(R_to.T @ R_from @ so3_exp(x[6:9] + s * e)) for s in (1, -1)]
        J[6:9, 6 + i] = (moved[0] - moved[1]) / (2 * h)
    want = J @ P @ J.T
    assert np.allclose(P2, want, rtol=1e-6, atol=1e-12)
    assert np.abs(P - want).max() > 0.05 * np.abs(want).max()

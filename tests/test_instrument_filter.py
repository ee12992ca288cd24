"""The articulated instrument state (surftrack.track.instrument): it recovers the joints from exact and
noisy part poses, keeps a hidden part where the rest of its instrument puts it, and smooths."""

import math

import numpy as np
import pytest

from surftrack.geometry import rotation_angle_deg, se3, so3_exp
from surftrack.geometry.transforms import so3_log
from surftrack.instruments import JointState, fit_configuration, joints_from_poses, load_instrument
from surftrack.instruments.kinematics import rcm_base_pose
from surftrack.track.instrument import InstrumentKalman, PartFilter, read_joints
from surftrack.track.kalman import KalmanConfig
from surftrack.track.smoother import rts_smooth

FPS = 30.0
LND = load_instrument("lnd")
NAMES = {p: f"lnd.0.{p}" for p in LND.part_names}
MEAS = np.diag([1.0] * 3 + [math.radians(2.0) ** 2] * 3)


def _truth(n: int) -> list[tuple[dict, JointState]]:
    """``n`` frames of a moving LND: its shaft pivots about a trocar and rolls, the wrist pitches and
    yaws, the jaws open and close (1-2 s periods). Per frame: (name -> (R, t), joints)."""
    trocar = np.array([-60.0, -40.0, -30.0])
    out = []
    for k in range(n):
        s = k / FPS
        pitch_point = np.array([10 * math.sin(1.3 * s), 5 * math.cos(0.9 * s), 90.0 + 8 * math.sin(0.7 * s)])
        q = JointState(roll=0.6 * math.sin(1.1 * s), pitch=0.5 * math.sin(2.1 * s), yaw=0.4 * math.cos(1.7 * s),
                       opening=0.5 + 0.4 * math.sin(3.0 * s))
        F = LND.forward(rcm_base_pose(trocar, pitch_point), q)
        out.append(({NAMES[p]: (F[p][:3, :3], F[p][:3, 3]) for p in LND.part_names}, q))
    return out


def _noisy(poses: dict, rng: np.random.Generator, pos_mm: float, rot_deg: float) -> dict:
    return {n: (R @ so3_exp(rng.normal(0, math.radians(rot_deg), 3)), t + rng.normal(0, pos_mm, 3))
            for n, (R, t) in poses.items()}


def _joint_errors_deg(kf: InstrumentKalman, q: JointState) -> np.ndarray:
    est = kf.joint_state()
    return np.degrees([abs(getattr(est, j) - getattr(q, j)) for j in ("pitch", "yaw", "opening")])


def _run(truth, rng, pos_mm, rot_deg, parts=None):
    kf = InstrumentKalman(LND, NAMES, KalmanConfig(accel_std_mm_s2=100.0, ang_accel_std_rad_s2=5.0),
                          joint_accel_std_rad_s2=10.0)
    steps, errs = [], []
    for k, (poses, q) in enumerate(truth):
        seen = {n: p for n, p in _noisy(poses, rng, pos_mm, rot_deg).items() if parts is None or n in parts}
        if k == 0:
            kf.init(seen, 0.0, MEAS)
        else:
            kf.predict(k / FPS)
            for n, (R, t) in seen.items():
                kf.update_part(n, R, t, MEAS, gate=False)
        steps.append(kf.snapshot())
        errs.append(_joint_errors_deg(kf, q))
    return kf, steps, np.array(errs)


def test_recovers_joints_from_exact_part_poses():
    truth = _truth(45)
    kf, _, errs = _run(truth, np.random.default_rng(0), 0.0, 0.0)
    assert errs[0].max() < 0.5  # the start's closed form is exact
    assert errs[10:].max() < 0.5, errs[10:].max(axis=0)
    for n, (R, t) in truth[-1][0].items():
        R_e, t_e = kf.part_pose(n)
        assert np.linalg.norm(t_e - t) < 0.2 and rotation_angle_deg(R_e, R) < 0.5, n


def test_recovers_joints_from_noisy_part_poses_better_than_each_frame_alone():
    truth = _truth(90)
    rng = np.random.default_rng(1)
    _, _, errs = _run(truth, rng, 1.0, 2.0)
    # the closed form on each frame's noisy poses alone, for comparison
    rng = np.random.default_rng(1)
    single = []
    for poses, q in truth:
        noisy = _noisy(poses, rng, 1.0, 2.0)
        est = joints_from_poses(LND, {p: se3(*noisy[NAMES[p]]) for p in LND.part_names}, JointState())
        single.append(np.degrees([abs(getattr(est, j) - getattr(q, j)) for j in ("pitch", "yaw", "opening")]))
    med, med_single = np.median(errs[15:], axis=0), np.median(np.array(single)[15:], axis=0)
    assert (med < 2.0).all(), med
    assert (med < med_single).all(), (med, med_single)


def test_a_hidden_part_keeps_the_pose_its_instrument_implies():
    """Only the shaft and the wrist are seen after the start: the jaws follow them through the kinematics
    (their opening carried by the filter), instead of being lost."""
    truth = _truth(30)
    kf = InstrumentKalman(LND, NAMES)
    kf.init(truth[0][0], 0.0, MEAS)
    for k in range(1, len(truth)):
        kf.predict(k / FPS)
        for n in (NAMES["shaft"], NAMES["wrist"]):
            kf.update_part(n, *truth[k][0][n], MEAS, gate=False)
    R, t = truth[-1][0][NAMES["jaw_left"]]
    R_e, t_e = kf.part_pose(NAMES["jaw_left"])
    # the opening moved ~20 deg meanwhile, unseen: the jaw is placed by the wrist, off by its own turn at most
    assert np.linalg.norm(t_e - t) < 1.0
    assert rotation_angle_deg(R_e, R) < 25.0


def test_part_view_and_jacobian():
    truth = _truth(2)
    kf = InstrumentKalman(LND, NAMES)
    kf.init(truth[0][0], 0.0, MEAS)
    step = kf.snapshot()
    # give the state rates; the view's velocity and angular velocity are the part's pose changing by them
    x = step.x.copy()
    x[3:6], x[9:12], x[kf.q_index + kf.n] = [5.0, -3.0, 2.0], [0.2, -0.1, 0.3], [0.4, -0.2, 0.5]
    step = type(step)(step.time, step.R, x, step.P, step.prior)
    dt = 1e-6
    ahead = x.copy()
    ahead[0:3] += x[3:6] * dt
    ahead[kf.q_index] += x[kf.q_index + kf.n] * dt
    R_ahead = step.R @ so3_exp(x[9:12] * dt)
    for n in NAMES.values():
        view = kf.part_step(step, n)
        later = kf.part_step(type(step)(0.0, R_ahead, ahead, step.P, None), n)
        assert np.allclose(view.x[3:6], (later.x[0:3] - view.x[0:3]) / dt, atol=1e-3)
        assert np.allclose(view.x[9:12], so3_log(view.R.T @ later.R) / dt, atol=1e-3)
    for n in NAMES.values():
        view = kf.part_step(kf.snapshot(), n)
        R, t = kf.part_pose(n)
        assert np.allclose(view.pose[0], R) and np.allclose(view.pose[1], t)
        # the view's pose covariance is the state's through the part's Jacobian
        J = kf.part_jacobian(n)
        assert np.allclose(view.pose_cov, J @ kf.snapshot().P @ J.T)
    # the Jacobian against a finite step of the state
    h = 1e-6
    x0, R0 = kf.x, kf.R_ref.copy()
    J = kf.part_jacobian(NAMES["jaw_right"])
    for i in (0, 7, 12, 13, 14):
        d = np.zeros(kf.dim)
        d[i] = h
        x = x0 + d
        R_ref = R0 @ so3_exp(x[6:9])
        x[6:9] = 0.0
        m = kf.model(R_ref, x)
        Rp, tp = m.poses(np.zeros(m.size))[NAMES["jaw_right"]]
        Rb, tb = kf.part_pose(NAMES["jaw_right"])
        num = np.r_[(tp - tb) / h, so3_log(Rb.T @ Rp) / h]
        assert np.allclose(num, J[:, i], atol=1e-3), (i, num, J[:, i])


def test_smoothing_the_articulated_state_beats_filtering():
    truth = _truth(90)
    _, steps, _ = _run(truth, np.random.default_rng(2), 1.5, 3.0)
    smooth = rts_smooth(steps)
    kf = InstrumentKalman(LND, NAMES)
    q_index = kf.q_index

    def err(seq):
        return np.median([np.degrees(np.abs(s.x[q_index] - [q.pitch, q.yaw, q.opening])).mean()
                          for s, (_, q) in zip(seq[10:], truth[10:])])

    assert err(smooth) < 0.8 * err(steps), (err(smooth), err(steps))


def test_part_filters_share_the_state_and_restart_it():
    truth = _truth(3)
    kf = InstrumentKalman(LND, NAMES)
    views = {p: PartFilter(kf, NAMES[p]) for p in LND.part_names}
    views["wrist"].init(*truth[0][0][NAMES["wrist"]], 0.0, MEAS)
    assert views["wrist"].initialized and not views["shaft"].initialized
    views["shaft"].init(*truth[0][0][NAMES["shaft"]], 0.0, MEAS)  # joins the state
    assert kf.active == {NAMES["wrist"], NAMES["shaft"]}
    views["wrist"].predict(1 / FPS)
    views["shaft"].predict(1 / FPS)  # the shared state moves once per frame
    assert kf.time == pytest.approx(1 / FPS)
    # a far-off measurement is gated per part; the part's own count locks it out, not the others
    R, t = truth[1][0][NAMES["shaft"]]
    for _ in range(kf.config.max_rejections - 1):
        assert not views["shaft"].update(R, t + 40.0, MEAS)
    # a silhouette's or flow's outcome (counts=False) neither adds to the count nor clears it
    assert not views["shaft"].update(R, t + 40.0, MEAS, counts=False) and not views["shaft"].lost
    assert views["shaft"].update(R, t, MEAS, counts=False)
    assert views["shaft"].rejections_in_a_row == kf.config.max_rejections - 1
    assert not views["shaft"].update(R, t + 40.0, MEAS)
    assert views["shaft"].lost and not views["wrist"].lost
    # the root's restart moves the instrument there
    widen = np.diag([50.0 ** 2] * 3 + [0.5] * 3)
    views["shaft"].restart(R, t + 40.0, MEAS, widen)
    assert np.linalg.norm(views["shaft"].pose[1] - (t + 40.0)) < 2.0
    assert np.linalg.norm(views["wrist"].pose[1] - (truth[1][0][NAMES["wrist"]][1] + 40.0)) < 3.0
    # another part's restart (next frame) can only turn the joints: the root stays where it was
    views["shaft"].predict(2 / FPS)
    views["jaw_right"].init(*kf.part_pose(NAMES["jaw_right"]), 2 / FPS, MEAS)  # joins where the state has it
    shaft_t = views["shaft"].pose[1]
    R_j, t_j = views["jaw_right"].pose
    views["jaw_right"].restart(R_j @ so3_exp(np.radians([0.0, 25.0, 0.0])), t_j, MEAS, widen)
    assert np.linalg.norm(views["shaft"].pose[1] - shaft_t) < 1.0
    assert rotation_angle_deg(views["jaw_right"].pose[0], R_j) > 10.0
    views["jaw_right"].deactivate()
    views["wrist"].deactivate()
    views["shaft"].deactivate()
    assert not kf.initialized  # no part tracked: the state is forgotten


def test_joints_read_off_the_state_match_the_truth_and_the_fit():
    truth = _truth(40)
    kf, _, _ = _run(truth, np.random.default_rng(3), 0.0, 0.0)
    reading = read_joints(kf, kf.snapshot())
    poses, q = truth[-1]
    for j in ("roll", "pitch", "yaw", "opening"):
        assert abs(getattr(reading.fit.joints, j) - getattr(q, j)) < math.radians(0.5), j
        assert 0.0 < reading.std[j] < math.radians(5.0), j
    # the rates of joints moving as sin: the state carries them; the roll's reference follows the
    # shaft's direction, so the roll's rate comes from every turn of the shaft
    assert abs(reading.rates["opening"] - 0.4 * 3.0 * math.cos(3.0 * 39 / FPS)) < 0.3
    step = kf.snapshot()
    x = step.x.copy()
    x[9:12] = [0.3, -0.2, 0.5]  # a shaft turning about all three axes: the roll's rate is the roll's change
    step = type(step)(step.time, step.R, x, step.P, None)
    dt = 1e-6
    later = type(step)(step.time, step.R @ so3_exp(x[9:12] * dt), x, step.P, None)
    d_roll = math.remainder(read_joints(kf, later).fit.joints.roll - read_joints(kf, step).fit.joints.roll, 2 * math.pi)
    assert read_joints(kf, step).rates["roll"] == pytest.approx(d_roll / dt, abs=1e-3)
    # the same base pose and joints as the per-frame fit to the same part poses
    fit = fit_configuration(LND, {p: poses[NAMES[p]] for p in LND.part_names})
    assert np.allclose(fit.base_t, reading.fit.base_t, atol=0.05)
    assert rotation_angle_deg(fit.base_R, reading.fit.base_R) < 0.2
    tip = LND.tool_tip({p: se3(*poses[NAMES[p]]) for p in LND.part_names})
    assert np.linalg.norm(reading.tip[1] - tip[1]) < 0.1
    assert reading.tip_cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(reading.tip_cov) > 0)


def test_tool_tip_velocity_is_the_states_motion_through_the_kinematics():
    """The tip's velocity read off the state equals the tip's displacement when the state moves on at its
    own rates for a short time (shaft translating and turning, joints moving), and its covariance is a
    covariance (symmetric, positive definite)."""
    truth = _truth(40)
    kf, _, _ = _run(truth, np.random.default_rng(3), 0.0, 0.0)
    step = kf.snapshot()
    x = step.x.copy()
    x[3:6], x[9:12] = [20.0, -10.0, 5.0], [0.3, -0.2, 0.5]
    x[12 + kf.n:] = 0.4
    step = type(step)(step.time, step.R, x, step.P, None)
    dt = 1e-6
    xl = x.copy()
    xl[0:3] += x[3:6] * dt
    xl[12:12 + kf.n] += x[12 + kf.n:] * dt
    later = type(step)(step.time, step.R @ so3_exp(x[9:12] * dt), xl, step.P, None)
    now = read_joints(kf, step)
    moved = (read_joints(kf, later).tip[1] - now.tip[1]) / dt
    assert np.linalg.norm(moved) > 10.0
    assert np.allclose(now.tip_velocity, moved, atol=1e-2 * np.linalg.norm(moved))
    C = now.tip_velocity_cov
    assert np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)
    assert 0.0 < now.tip_speed_std <= math.sqrt(np.linalg.eigvalsh(C).max()) + 1e-9
    # the covariance is the spread of the tip's velocity over the state's rates drawn from theirs
    rates = kf.rate_cols
    draws = np.random.default_rng(0).multivariate_normal(np.zeros(len(rates)), step.P[np.ix_(rates, rates)], 300)
    vel = []
    for dv in draws:
        xs = x.copy()
        xs[rates] += dv
        vel.append(read_joints(kf, type(step)(step.time, step.R, xs, step.P, None)).tip_velocity)
    emp = np.cov(np.array(vel).T)
    assert np.trace(emp) == pytest.approx(np.trace(C), rel=0.2)


def test_a_restart_cuts_the_pose_and_the_joints_loose_from_their_rates():
    """``widen`` (a restart's jump) leaves no covariance between the pose and joints and any rate, in
    the state and in the frame's prediction (which the smoother re-makes), and widens the pose."""
    kf, _, _ = _run(_truth(8), np.random.default_rng(3), 0.5, 1.0)
    pose, rates = kf.pose_cols, kf.rate_cols
    assert len(pose) == len(rates) == 6 + kf.n
    assert np.abs(kf.kf.P[np.ix_(pose, rates)]).max() > 1e-6  # the filter's run correlated them
    before = kf.kf.P.copy()
    kf.widen(np.diag([9.0] * 3 + [0.01] * 3), 0.02)
    for P in (kf.kf.P, kf.prior.P):
        assert np.all(P[np.ix_(pose, rates)] == 0.0) and np.all(P[np.ix_(rates, pose)] == 0.0)
    assert kf.prior.restarted
    added = np.array([9.0] * 3 + [0.01] * 3 + [0.02] * kf.n)
    assert np.allclose(np.diag(kf.kf.P)[pose], np.diag(before)[pose] + added)


def test_a_part_joining_far_off_is_a_jump_not_a_spin():
    """A part seen again 100 deg from where its instrument's state has it joins (never gated out), as
    a jump of the pose: the rates stay what they were, so the instrument does not start to spin."""
    truth = _truth(3)
    kf = InstrumentKalman(LND, NAMES)
    views = {p: PartFilter(kf, NAMES[p]) for p in LND.part_names}
    for p in ("shaft", "wrist"):
        views[p].init(*truth[0][0][NAMES[p]], 0.0, MEAS)
    views["shaft"].predict(1 / FPS)
    views["shaft"].update(*truth[1][0][NAMES["shaft"]], MEAS)
    omega0 = kf.x[9:12].copy()
    R, t = truth[1][0][NAMES["shaft"]]
    views["shaft"].deactivate()
    views["shaft"] = PartFilter(kf, NAMES["shaft"])
    views["shaft"].init(R @ so3_exp(np.radians([0.0, 0.0, 100.0])), t, 1 / FPS, MEAS)  # rolled 100 deg
    assert views["shaft"].initialized
    assert np.linalg.norm(kf.x[9:12] - omega0) < 0.5, kf.x[9:12]
    assert rotation_angle_deg(views["shaft"].pose[0], R @ so3_exp(np.radians([0.0, 0.0, 100.0]))) < 30.0


def test_a_restart_keeps_the_other_parts_updates_of_the_frame():
    """Widening for one part's restart acts on the current state: the shaft's keyframe fused earlier in
    the same frame stays (going back to the frame's prediction would erase it)."""
    truth = _truth(3)
    kf = InstrumentKalman(LND, NAMES)
    views = {p: PartFilter(kf, NAMES[p]) for p in LND.part_names}
    kf.init(truth[0][0], 0.0, MEAS)
    kf.predict(1 / FPS)
    predicted = kf.part_pose(NAMES["shaft"])[1]
    R, t = truth[1][0][NAMES["shaft"]]
    views["shaft"].update(R, t + np.array([3.0, 0.0, 0.0]), MEAS)  # the keyframe moves the shaft 3 mm
    moved = kf.part_pose(NAMES["shaft"])[1]
    assert np.linalg.norm(moved - predicted) > 1.0
    R_j, t_j = views["jaw_left"].pose
    views["jaw_left"].restart(R_j @ so3_exp(np.radians([0.0, 20.0, 0.0])), t_j, MEAS, np.eye(6))
    assert np.linalg.norm(kf.part_pose(NAMES["shaft"])[1] - moved) < 0.5


def test_a_joint_predicted_into_its_limit_stops_there():
    """A rate carrying a joint past its limit is stopped at the limit in the prediction, so the state, its
    views and its rates (the tool tip's velocity) agree."""
    kf, _, _ = _run(_truth(4), np.random.default_rng(4), 0.5, 1.0)
    j = kf.n - 1  # the opening
    x = kf.kf.x.reshape(kf.dim).copy()
    x[12 + j], x[12 + kf.n + j] = kf.hi[j] - 0.01, 2.0  # 2 rad/s towards the upper limit
    kf.kf.x = x.reshape(-1, 1)
    kf.predict(kf.time + 0.1)
    x = kf.kf.x.reshape(kf.dim)
    assert x[12 + j] == pytest.approx(kf.hi[j]) and x[12 + kf.n + j] == 0.0
    assert kf.prior.x[12 + j] == pytest.approx(kf.hi[j])

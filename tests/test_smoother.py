"""The error-state RTS smoother against filterpy's linear RTS and a brute-force batch solution, on
rotations, and as a fixed-lag stream; the smoother's own motion prior against a filter run under it."""

import dataclasses

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from surftrack.geometry import rotation_angle_deg, so3_exp
from surftrack.track.kalman import KalmanConfig, PoseKalman, refilter, white_noise_q
from surftrack.track.smoother import LagSmoother, SmootherPrior, refilter_under, rts_smooth

DT = 1 / 30
CFG = KalmanConfig(accel_std_mm_s2=50.0, ang_accel_std_rad_s2=2.0)
MEAS_COV = np.diag([4.0, 4.0, 9.0, 1e-4, 1e-4, 1e-4])


def _translation_run(n=25, seed=0):
    rng = np.random.default_rng(seed)
    truth = np.array([[10 + 30 * k * DT, -5 + 0.5 * np.sin(k / 4), 80 - 10 * k * DT] for k in range(n)])
    meas = truth + rng.normal(0, [2.0, 2.0, 3.0], (n, 3))
    return truth, meas, _filtered(meas)


def _filtered(meas, cov=MEAS_COV):
    """The filter's steps over position measurements ``meas`` (n, 3) mm, one per frame, all fused."""
    kf = PoseKalman(CFG)
    steps = []
    for k in range(len(meas)):
        if k == 0:
            kf.init(np.eye(3), meas[0], 0.0, cov)
        else:
            kf.predict(k * DT)
            kf.update(np.eye(3), meas[k], cov, gate=False)
        steps.append(kf.snapshot())
    return steps


def _linear_model():
    F = np.eye(6)
    F[0:3, 3:6] = np.eye(3) * DT
    Q = white_noise_q(DT, CFG.accel_std_mm_s2**2)
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    P0 = np.diag([4.0, 4.0, 9.0] + [CFG.init_vel_std_mm_s**2] * 3)
    return F, Q, H, P0


def test_matches_filterpy_linear_rts():
    _, meas, steps = _translation_run()
    F, Q, H, P0 = _linear_model()
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.F, kf.Q, kf.H, kf.R = F, Q, H, MEAS_COV[:3, :3]
    kf.x, kf.P = np.r_[meas[0], np.zeros(3)].reshape(6, 1), P0
    xs, ps = [kf.x.ravel().copy()], [kf.P.copy()]
    for z in meas[1:]:
        kf.predict()
        kf.update(z.reshape(3, 1))
        xs.append(kf.x.ravel().copy())
        ps.append(kf.P.copy())
    xs_s, ps_s, _, _ = kf.rts_smoother(np.array(xs)[:, :, None], np.array(ps))
    ours = rts_smooth(steps)
    np.testing.assert_allclose([s.x[0:6] for s in ours], xs_s[:, :, 0], atol=1e-6)
    np.testing.assert_allclose([s.P[0:6, 0:6] for s in ours], ps_s, rtol=1e-6, atol=1e-8)


def test_matches_brute_force_batch_solution():
    """The smoothed means are the minimiser of the whole trajectory's least-squares problem (prior on the
    first state, process model between frames, measurements), solved here in one dense system."""
    _, meas, steps = _translation_run(n=15, seed=1)
    F, Q, H, P0 = _linear_model()
    n, m = len(meas), 6
    A = np.zeros((n * m, n * m))
    b = np.zeros(n * m)
    W0, Wq, Wr = np.linalg.inv(P0), np.linalg.inv(Q), np.linalg.inv(MEAS_COV[:3, :3])
    A[:m, :m] += W0
    b[:m] += W0 @ np.r_[meas[0], np.zeros(3)]
    for k in range(1, n):
        i, j = slice((k - 1) * m, k * m), slice(k * m, (k + 1) * m)
        # (x_k - F x_{k-1})^T Wq (x_k - F x_{k-1})
        A[j, j] += Wq
        A[i, i] += F.T @ Wq @ F
        A[i, j] -= F.T @ Wq
        A[j, i] -= Wq @ F
        A[j, j] += H.T @ Wr @ H
        b[j] += H.T @ Wr @ meas[k]
    batch = np.linalg.solve(A, b).reshape(n, m)
    np.testing.assert_allclose([s.x[0:6] for s in rts_smooth(steps)], batch, atol=1e-6)


def test_rotation_smoothing_beats_filtering():
    rng = np.random.default_rng(3)
    omega = np.array([0.4, -0.8, 0.3])  # rad/s, body frame
    R0 = so3_exp(np.array([2.5, 0.5, -1.0]))  # near pi: the charts must not wrap
    kf = PoseKalman(CFG)
    steps, truth = [], []
    cov = np.diag([1.0] * 3 + [np.radians(4.0) ** 2] * 3)
    for k in range(90):
        Rt = R0 @ so3_exp(omega * k * DT)
        truth.append(Rt)
        Rm = Rt @ so3_exp(rng.normal(0, np.radians(4.0), 3))
        if k == 0:
            kf.init(Rm, np.zeros(3), 0.0, cov)
        else:
            kf.predict(k * DT)
            kf.update(Rm, np.zeros(3), cov, gate=False)
        steps.append(kf.snapshot())
    sm = rts_smooth(steps)
    err_f = [rotation_angle_deg(s.pose[0], R) for s, R in zip(steps, truth)]
    err_s = [rotation_angle_deg(s.pose[0], R) for s, R in zip(sm, truth)]
    assert np.mean(err_s[5:-5]) < 0.6 * np.mean(err_f[5:-5]), (np.mean(err_s), np.mean(err_f))
    assert np.linalg.norm(sm[45].x[9:12] - omega) < 0.3
    assert all(np.trace(s.P[6:9, 6:9]) <= np.trace(f.P[6:9, 6:9]) + 1e-12 for s, f in zip(sm, steps))


def test_segments_are_not_linked():
    _, meas, steps = _translation_run(n=20)
    kf = PoseKalman(CFG)
    kf.init(np.eye(3), meas[10] + 50.0, steps[10].time, MEAS_COV)  # a re-initialisation at frame 10
    cut = steps[:10] + [kf.snapshot()] + steps[11:]
    sm = rts_smooth(cut[:10] + [None] + cut[11:])
    assert np.allclose(sm[9].x, cut[9].x) and sm[10] is None
    sm = rts_smooth(cut)
    assert np.allclose(sm[9].x, cut[9].x), "no smoothing across a segment start"
    assert not np.allclose(sm[5].x, cut[5].x)


def test_restart_keeps_the_link_and_the_velocity():
    _, meas, steps = _translation_run(n=20)
    kf = PoseKalman(CFG)
    kf.init(np.eye(3), meas[0], 0.0, MEAS_COV)
    for k in range(1, 12):
        kf.predict(k * DT)
        kf.update(np.eye(3), meas[k], MEAS_COV, gate=False)
    v = kf.velocity[0]
    kf.predict(12 * DT)
    far = meas[12] + np.array([40.0, 0, 0])
    assert kf.gate(np.eye(3), far, MEAS_COV) > kf.config.gate_chi2
    kf.restart(np.eye(3), far, MEAS_COV, np.diag([900.0] * 3 + [0.5] * 3))
    assert np.linalg.norm(kf.pose[1] - far) < 3.0 and kf.snapshot().prior is not None
    assert np.linalg.norm(kf.velocity[0] - v) < 0.5 * np.linalg.norm(v)


def test_lag_smoother_stream():
    _, _, steps = _translation_run(n=60)
    full = rts_smooth(steps)
    sm = LagSmoother(lag=20, chunk=5)
    got = []
    for k, s in enumerate(steps):
        out = sm.push(k, {"p": s, "absent": None})
        assert len(sm) <= 25
        got += out
    assert len(got) == 40 and [i for i, _ in got] == list(range(40))
    got += sm.flush()
    assert [i for i, _ in got] == list(range(60)) and all(st["absent"] is None for _, st in got)
    # a second of future is nearly all a constant-velocity smoother uses
    err = max(np.linalg.norm(st["p"].x[0:3] - f.x[0:3]) for (_, st), f in zip(got, full))
    assert err < 0.05, err
    assert all(np.allclose(st["p"].x, f.x) for (_, st), f in zip(got[40:], full[40:]))
    causal = LagSmoother(lag=0)
    assert [st["p"] is s for s in steps[:3] for _, st in causal.push(0, {"p": s})] == [True] * 3


def test_a_revision_replaces_the_buffered_steps_and_starts_where_the_buffer_does():
    """A step that ``revises`` earlier frames (a restart in hindsight) has the smoother take the revised
    steps for the frames still buffered; released frames keep theirs, and the first revised frame still
    buffered starts a segment (the revised run does not continue what was written)."""
    truth, meas, steps = _translation_run(n=20)
    shifted = [(s.time, (np.eye(3), m + np.array([30.0, 0, 0]), MEAS_COV)) for s, m in zip(steps[8:16], meas[8:16])]
    kf, revised = refilter(CFG, shifted, last_ungated=True)
    sm, got = LagSmoother(lag=4, chunk=1), []
    for k in range(15):
        got += sm.push(k, {"p": steps[k]})
    released = {i for i, _ in got}
    assert released == set(range(11))  # frames 8-10 are written already
    got += sm.push(15, {"p": dataclasses.replace(kf.snapshot(), revises=tuple(revised[:-1]))})
    got += sm.flush()
    by = {i: st["p"] for i, st in got}
    assert all(np.linalg.norm(by[k].x[0:3] - truth[k]) < 8.0 for k in range(11))
    assert all(np.linalg.norm(by[k].x[0:3] - truth[k] - [30.0, 0, 0]) < 8.0 for k in range(11, 16))
    assert by[11].prior is None and all(by[k].prior is not None for k in range(12, 16))


def test_a_revision_without_a_step_to_carry_it():
    """A track that ended revises its last frames with no step of its own on the frame it ends
    (``revisions``): the buffered frames take the revised steps, the ending frame has none."""
    truth, meas, steps = _translation_run(n=12)
    shifted = [(s.time, (np.eye(3), m + np.array([30.0, 0, 0]), MEAS_COV)) for s, m in zip(steps[6:10], meas[6:10])]
    _, revised = refilter(CFG, shifted, last_ungated=True)
    for lag, first in ((6, 6), (2, 8)):  # with a lag of 2, frames 6 and 7 are written before the revision
        sm, got = LagSmoother(lag=lag, chunk=1), []
        for k in range(10):
            got += sm.push(k, {"p": steps[k]})
        got += sm.push(10, {"p": None}, {"p": tuple(revised)})
        got += sm.flush()
        by = {i: st["p"] for i, st in got}
        assert sorted(by) == list(range(11)) and by[10] is None
        assert all(np.linalg.norm(by[k].x[0:3] - truth[k]) < 8.0 for k in range(first))
        assert all(np.linalg.norm(by[k].x[0:3] - truth[k] - [30.0, 0, 0]) < 8.0 for k in range(first, 10))
        assert by[first].prior is None  # the revised run starts a segment where the buffer does
    causal = LagSmoother(lag=0)  # a causal run writes what the filter had
    assert causal.push(10, {"p": None}, {"p": tuple(revised)}) == [(10, {"p": None})]


# the smoother's own prior: stiffer along the line of sight (the runs above look along +z from near the axis)
PRIOR = SmootherPrior(CFG.accel_std_mm_s2, 80.0, 10.0)


def test_refiltering_under_the_filters_own_prior_changes_nothing():
    _, _, steps = _translation_run(n=30)
    a, w = CFG.accel_std_mm_s2, CFG.ang_accel_std_rad_s2
    same = refilter_under(steps, SmootherPrior(a, a, a, w, w))
    np.testing.assert_allclose([s.x for s in same], [s.x for s in steps], atol=1e-7)
    np.testing.assert_allclose([s.P for s in same], [s.P for s in steps], rtol=1e-6, atol=1e-8)


def test_refiltering_matches_a_filter_run_under_the_other_prior():
    """The measurement information recovered from the filter's prediction and posterior, fused under the
    smoother's prior, is a linear Kalman filter run under that prior (per-step process noise turned to
    the line of sight through the filter's predicted position), and smoothing it is that filter's RTS."""
    _, meas, steps = _translation_run(n=25, seed=2)
    ours = refilter_under(steps, PRIOR)
    F, Q, H, P0 = _linear_model()
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.F, kf.H, kf.R = F, H, MEAS_COV[:3, :3]
    kf.x, kf.P = np.r_[meas[0], np.zeros(3)].reshape(6, 1), P0
    xs, ps, qs = [kf.x.ravel().copy()], [kf.P.copy()], [Q]
    for step, z in zip(steps[1:], meas[1:]):
        Qk = Q + PRIOR.position_q_change(step.prior.x[0:3], DT)
        kf.predict(Q=Qk)
        kf.update(z.reshape(3, 1))
        xs.append(kf.x.ravel().copy())
        ps.append(kf.P.copy())
        qs.append(Qk)
    np.testing.assert_allclose([s.x[0:6] for s in ours], xs, atol=1e-6)
    np.testing.assert_allclose([s.P[0:6, 0:6] for s in ours], ps, rtol=1e-6, atol=1e-8)
    xs_s, ps_s, _, _ = kf.rts_smoother(np.array(xs)[:, :, None], np.array(ps), Qs=np.array(qs))  # Qs[k]: into frame k
    np.testing.assert_allclose([s.x[0:6] for s in rts_smooth(ours)], xs_s[:, :, 0], atol=1e-6)


def test_refiltering_through_a_restart_and_a_coast_matches_the_filter_under_that_prior():
    """With the same prior in every direction the smoother's prior is a filter's own: re-filtering a run
    with a restart (widened, pose cut loose from the rates) and unmeasured frames (coasting velocities)
    gives what a filter run under it gives."""
    _, meas, _ = _translation_run(n=25, seed=6)
    widen = np.diag([400.0] * 3 + [0.1] * 3)

    def run(cfg):
        kf, steps = PoseKalman(cfg), []
        for k in range(25):
            if k == 0:
                kf.init(np.eye(3), meas[0], 0.0, MEAS_COV)
            else:
                kf.predict(k * DT, coast=k in (17, 18, 19))
                if k == 12:
                    kf.restart(np.eye(3), meas[k] + [20.0, 0, 0], MEAS_COV, widen)
                elif k not in (16, 17, 18):
                    kf.update(np.eye(3), meas[k] + (k > 12) * np.array([20.0, 0, 0]), MEAS_COV, gate=False)
            steps.append(kf.snapshot())
        return steps

    # the rotation's prior stiffer too (the runs measure the same rotation on every frame: the filter's
    # angular velocity stays 0, and so its transition is the same under either prior)
    looser = dataclasses.replace(CFG, accel_std_mm_s2=80.0, ang_accel_std_rad_s2=0.5)
    ours = refilter_under(run(CFG), SmootherPrior(CFG.accel_std_mm_s2, 80.0, 80.0, CFG.ang_accel_std_rad_s2, 0.5))
    want = run(looser)
    np.testing.assert_allclose([s.x for s in ours], [s.x for s in want], atol=1e-6)
    np.testing.assert_allclose([s.P for s in ours], [s.P for s in want], rtol=1e-6, atol=1e-6)


def test_a_stiffer_depth_prior_keeps_the_depth_noise_out_of_the_path():
    """Depth measured ten times worse than the image position (as the estimator does): under the
    smoother's prior the smoothed depth wanders less while the lateral motion is kept."""
    rng = np.random.default_rng(4)
    n = 90
    truth = np.array([[-15 + 20 * k * DT, 3 * np.sin(k / 10), 80.0] for k in range(n)])
    meas = truth + rng.normal(0, [0.3, 0.3, 3.0], (n, 3))
    steps = _filtered(meas, np.diag([0.09, 0.09, 9.0, 1e-4, 1e-4, 1e-4]))

    def paths(sm):
        d = np.diff([s.x[0:3] for s in sm], axis=0)
        return np.abs(d[:, 2]).sum(), np.linalg.norm(d[:, 0:2], axis=1).sum()

    depth_own, lateral_own = paths(rts_smooth(steps))
    depth_prior, lateral_prior = paths(rts_smooth(refilter_under(steps, PRIOR)))
    lateral_true = np.linalg.norm(np.diff(truth[:, 0:2], axis=0), axis=1).sum()
    assert depth_prior < 0.5 * depth_own, (depth_prior, depth_own)
    assert abs(lateral_prior / lateral_true - 1) < 0.05 and abs(lateral_own / lateral_true - 1) < 0.05


def test_a_stiffer_rotation_prior_keeps_the_rotation_noise_out_of_a_tip():
    """A part turning slowly, its rotation measured with 4 deg of noise: under a stiffer rotation prior
    the smoothed rotation is closer to the truth and a point 10 mm out on the part (a jaw's tip) no
    longer moves for nothing (the filter's own prior: 40 % too far); the turn itself (its rate) is kept."""
    rng = np.random.default_rng(8)
    omega = np.array([0.0, 0.0, 0.15])  # rad/s
    tip = np.array([0.0, 10.0, 0.0])  # mm, in the part's frame
    cov = np.diag([1.0] * 3 + [np.radians(4.0) ** 2] * 3)
    truth = [so3_exp(omega * k * DT) for k in range(90)]
    meas = [(R @ so3_exp(rng.normal(0, np.radians(4.0), 3)), np.array([0.0, 0.0, 80.0]), cov) for R in truth]
    _, steps = refilter(CFG, [(k * DT, m) for k, m in enumerate(meas)])
    stiff = SmootherPrior(CFG.accel_std_mm_s2, CFG.accel_std_mm_s2, CFG.accel_std_mm_s2, CFG.ang_accel_std_rad_s2, 0.3)

    def scores(sm):
        err = np.mean([rotation_angle_deg(s.pose[0], R) for s, R in zip(sm[5:-5], truth[5:-5])])
        path = sum(np.linalg.norm(a.pose[0] @ tip - b.pose[0] @ tip) for a, b in zip(sm[5:-6], sm[6:-5]))
        return err, path, sm[45].x[9:12]

    err_own, path_own, omega_own = scores(rts_smooth(steps))
    err_stiff, path_stiff, omega_stiff = scores(rts_smooth(refilter_under(steps, stiff)))
    path_true = sum(np.linalg.norm(a @ tip - b @ tip) for a, b in zip(truth[5:-6], truth[6:-5]))
    assert err_stiff < 0.8 * err_own, (err_stiff, err_own)
    assert path_own > 1.25 * path_true and abs(path_stiff / path_true - 1) < 0.1, (path_stiff, path_own, path_true)
    assert np.linalg.norm(omega_stiff - omega) < 0.1


def test_lag_smoother_with_its_own_prior_streams_the_refiltered_run():
    _, _, steps = _translation_run(n=60, seed=5)
    full = rts_smooth(refilter_under(steps, PRIOR))
    sm, got = LagSmoother(lag=20, chunk=5, prior=PRIOR), []
    for k, s in enumerate(steps):
        got += sm.push(k, {"p": s})
    got += sm.flush()
    assert [i for i, _ in got] == list(range(60))
    # a stiffer prior reaches further than the lag: the released frames miss a little of the later data
    assert max(np.linalg.norm(st["p"].x[0:3] - f.x[0:3]) for (_, st), f in zip(got, full)) < 0.6
    # the buffer is re-filtered from the last released frame's re-filtered state: the same run as a whole
    assert all(np.allclose(st["p"].x, f.x) for (_, st), f in zip(got[35:], full[35:]))


def test_a_revision_is_refiltered_under_the_smoothers_prior():
    """The re-filtered steps are kept between passes; a revision has its frames re-filtered again (from
    the first revised frame still buffered, which starts a segment)."""
    truth, meas, steps = _translation_run(n=20)
    shifted = [(s.time, (np.eye(3), m + np.array([30.0, 0, 0]), MEAS_COV)) for s, m in zip(steps[8:16], meas[8:16])]
    kf, revised = refilter(CFG, shifted, last_ungated=True)
    sm, got = LagSmoother(lag=4, chunk=1, prior=PRIOR), []
    for k in range(15):
        got += sm.push(k, {"p": steps[k]})
    got += sm.push(15, {"p": dataclasses.replace(kf.snapshot(), revises=tuple(revised[:-1]))})
    got += sm.flush()
    by = {i: st["p"] for i, st in got}
    seen = [dataclasses.replace(revised[3], prior=None)] + list(revised[4:-1]) + [kf.snapshot()]
    want = rts_smooth(refilter_under(seen, PRIOR))
    for k, w in zip(range(11, 16), want):
        np.testing.assert_allclose(by[k].x, w.x, atol=1e-9)
    assert all(np.linalg.norm(by[k].x[0:3] - truth[k] - [30.0, 0, 0]) < 8.0 for k in range(11, 16))


def test_refiltering_an_instruments_state_matches_its_filter_under_that_prior():
    """An instrument's articulated state (root pose, joints and their rates) re-filtered under another
    prior of its root pose is its filter run under that prior, through a restart's widening made before
    the frame's measurements (the joints cut loose from their rates as well) and unmeasured frames; the
    joints keep the filter's prior. A measurement of the root's position and a joint together correlates
    them, so the cut of the joints is felt."""
    from surftrack.instruments import load_instrument
    from surftrack.track.instrument import InstrumentKalman

    lnd = load_instrument("lnd")
    names = {p: f"lnd.0.{p}" for p in lnd.part_names}
    _, meas, _ = _translation_run(n=25, seed=4)
    R_root = so3_exp(np.array([0.3, -0.2, 0.1]))
    cov = np.diag([4.0] * 3 + [1e-3] * 3)

    def run(cfg):
        kf, steps = InstrumentKalman(lnd, names, cfg, joint_accel_std_rad_s2=2.0), []
        for k in range(25):
            if k == 0:
                kf.init({names["shaft"]: (R_root, meas[0])}, 0.0, cov)  # the joints at rest, unpinned
            else:
                kf.predict(k * DT)
                if k == 12:
                    kf.widen(np.diag([400.0] * 3 + [0.1] * 3), 0.05)
                if k not in (16, 17, 18):
                    # the root seen at one rotation: the rates stay 0 and the transition is the same
                    # under either prior, so the two runs linearise alike
                    kf.update_part(names["shaft"], R_root, meas[k] + (k >= 12) * np.array([20.0, 0, 0]), cov,
                                   gate=False)
                if k % 3 == 0:  # x + 10 mm/rad * (the first joint), linear in the state: the joint at 0
                    model = kf.model()
                    basis = np.zeros((1, 6 + len(model.joints)))
                    basis[0, 0], basis[0, 6] = 1.0, 10.0
                    measured = np.zeros(basis.shape[1])
                    measured[0] = meas[k][0] + 20.0 * (k >= 12) - (kf.x[0] + 10.0 * kf.x[12])
                    kf.update_model(model, measured, basis, np.array([[1.0]]), gate=False)
            steps.append(kf.snapshot())
        return steps

    filtered = run(CFG)
    assert filtered[1].x.shape == (12 + 2 * 3,)  # pitch, yaw, opening (the roll is the root's)
    looser = dataclasses.replace(CFG, accel_std_mm_s2=80.0, ang_accel_std_rad_s2=0.5)
    ours = refilter_under(filtered, SmootherPrior(CFG.accel_std_mm_s2, 80.0, 80.0, CFG.ang_accel_std_rad_s2, 0.5))
    want = run(looser)
    np.testing.assert_allclose([s.x for s in ours], [s.x for s in want], atol=1e-6)
    np.testing.assert_allclose([s.P for s in ours], [s.P for s in want], rtol=1e-6, atol=1e-6)
    assert not np.allclose([s.x for s in ours], [s.x for s in filtered], atol=1e-3)


def test_the_tracking_config_names_the_smoothers_prior():
    from surftrack.track import TrackConfig

    cfg = TrackConfig()
    prior = cfg.smoother_prior()
    assert prior == SmootherPrior(cfg.kalman.accel_std_mm_s2, cfg.smooth_lateral_accel_std_mm_s2,
                                  cfg.smooth_depth_accel_std_mm_s2, cfg.kalman.ang_accel_std_rad_s2,
                                  cfg.smooth_ang_accel_std_rad_s2)
    a, w = cfg.kalman.accel_std_mm_s2, cfg.kalman.ang_accel_std_rad_s2
    assert cfg.replace(smooth_lateral_accel_std_mm_s2=a, smooth_depth_accel_std_mm_s2=a,
                       smooth_ang_accel_std_rad_s2=w).smoother_prior() is None
    # the rotation's prior alone differing from the filter's is still the smoother's own
    only_rot = cfg.replace(smooth_lateral_accel_std_mm_s2=a, smooth_depth_accel_std_mm_s2=a).smoother_prior()
    assert only_rot is not None and only_rot.rotation_q_change(0.1) is not None
    assert SmootherPrior(a, a, a).rotation_q_change(0.1) is None
    with pytest.raises(ValueError, match="come together"):
        SmootherPrior(a, a, a, w)
    with pytest.raises(ValueError, match="smooth_ang_accel_std_rad_s2 must be > 0"):
        TrackConfig(smooth_ang_accel_std_rad_s2=0.0)
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(ValueError, match="smooth_depth_accel_std_mm_s2 must be > 0"):
            TrackConfig(smooth_depth_accel_std_mm_s2=bad)

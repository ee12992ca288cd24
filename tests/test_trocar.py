"""The trocar (surftrack.track.trocar): located from measured shaft axes despite wrong ones, its
constraint's derivative, and the instrument state held through it (the shaft's depth follows its
direction), forgotten and located again when the camera moves."""

import math

import numpy as np

from surftrack.geometry import so3_exp
from surftrack.instruments import JointState, load_instrument
from surftrack.instruments.kinematics import rcm_base_pose
from surftrack.track.instrument import InstrumentKalman
from surftrack.track.kalman import KalmanConfig
from surftrack.track.trocar import Trocar

FPS = 30.0
LND = load_instrument("lnd")
NAMES = {p: f"lnd.0.{p}" for p in LND.part_names}
TROCAR = np.array([-120.0, -30.0, 50.0])  # the shaft enters from the side: depth is across it


def _shaft_poses(n: int, trocar: np.ndarray = TROCAR) -> list[tuple[np.ndarray, np.ndarray]]:
    """The shaft's pose on ``n`` frames of an LND pivoting about ``trocar`` (about +-8 deg), rolling and
    moving in and out."""
    out = []
    for k in range(n):
        s = k / FPS
        pitch_point = np.array([12 * math.sin(1.3 * s), 8 * math.cos(0.9 * s), 90.0 + 8 * math.sin(0.7 * s)])
        F = LND.forward(rcm_base_pose(trocar, trocar + (pitch_point - TROCAR)), JointState(roll=0.6 * math.sin(1.1 * s)))
        out.append((F["shaft"][:3, :3], F["shaft"][:3, 3]))
    return out


def _distance_to_axis(c, o, d) -> float:
    v = c - o
    return float(np.linalg.norm(v - d * (d @ v)))


def test_located_from_pivoting_axes_despite_wrong_ones():
    kf = InstrumentKalman(LND, NAMES)
    rng = np.random.default_rng(0)
    tr = Trocar(after=8, axis_std_mm=1.0, axis_std_deg=1.0)
    for k, (R, t) in enumerate(_shaft_poses(60)):
        if k % 5 == 4:  # one axis in five is an estimator's mistake, 20-40 deg off
            R = R @ so3_exp(rng.normal(0, 1, 3) / math.sqrt(3) * math.radians(30))
        else:
            R, t = R @ so3_exp(rng.normal(0, math.radians(1.0), 3)), t + rng.normal(0, 1.0, 3)
        tr.add_axis(*kf.root_axis(R, t))
    assert tr.point is not None
    d = kf.root_axis(*_shaft_poses(1)[0])[1]
    off = tr.point - TROCAR
    across = off - d * (d @ off)
    assert np.linalg.norm(across) < 3.0, tr.point  # across the shafts, where it constrains them
    # along them a pivot of +-8 deg leaves it looser, as its covariance says
    assert off @ np.linalg.solve(tr.cov, off) < 16.3, (off, np.sqrt(np.linalg.eigvalsh(tr.cov)))
    sd = np.sqrt(np.linalg.eigvalsh(tr.cov))
    assert sd[-1] > 3.0 * sd[0] > 0


def test_too_little_pivot_leaves_it_unknown():
    kf = InstrumentKalman(LND, NAMES)
    tr = Trocar(after=4)
    R, t = _shaft_poses(1)[0]
    for k in range(10):  # the same axis slid along itself: no point is pinned
        o, d = kf.root_axis(R, t)
        tr.add_axis(o + 3.0 * k * d, d)
    assert tr.point is None and tr.residual(o, d, R, kf.axis_point, kf.axis_dir) is None


def test_constraint_derivative_matches_finite_differences():
    kf = InstrumentKalman(LND, NAMES)
    tr = Trocar(after=2)
    for R, t in _shaft_poses(40)[::4]:
        tr.add_axis(*kf.root_axis(R, t))
    R, t = _shaft_poses(40)[7]
    R, t = R @ so3_exp(np.array([0.05, -0.03, 0.02])), t + np.array([3.0, -2.0, 4.0])  # off the point
    y, J, cov = tr.residual(*kf.root_axis(R, t), R, kf.axis_point, kf.axis_dir)
    assert np.linalg.norm(y) > 1.0 and np.all(np.linalg.eigvalsh(cov) >= tr.floor_mm ** 2 - 1e-9)
    U = None
    h = 1e-6
    for i in range(6):
        e = np.zeros(6)
        e[i] = h
        R2, t2 = R @ so3_exp(e[3:6]), t + e[0:3]
        o2, d2 = kf.root_axis(R2, t2)
        # h = U (I - d d^T)(c - o) with U fixed at the nominal axis (what the derivative holds fixed)
        if U is None:
            o, d = kf.root_axis(R, t)
            x = np.cross(d, [1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.cross(d, [0.0, 1.0, 0.0])
            x /= np.linalg.norm(x)
            U = np.stack([x, np.cross(d, x)])
            h0 = U @ ((tr.point - o) - d * (d @ (tr.point - o)))
        v2 = tr.point - o2
        assert np.allclose((U @ (v2 - d2 * (d2 @ v2)) - h0) / h, J[:, i], atol=1e-4), i
    assert np.allclose(-h0, y)


def _run(trocar: Trocar | None, shaft_poses, rng) -> tuple[InstrumentKalman, np.ndarray]:
    """The state fed only the shaft's poses, measured 1 mm across the line of sight and 8 mm along it
    (what one image gives): the shaft's position errors across its axis per frame (along it the trocar
    says nothing: the shaft slides through it)."""
    kf = InstrumentKalman(LND, NAMES, KalmanConfig(accel_std_mm_s2=200.0, ang_accel_std_rad_s2=5.0), trocar=trocar)
    cov = np.diag([1.0, 1.0, 64.0] + [math.radians(1.0) ** 2] * 3)
    errs = []
    for k, (R, t) in enumerate(shaft_poses):
        noisy = (R @ so3_exp(rng.normal(0, math.radians(1.0), 3)), t + rng.normal(0, 1, 3) * [1.0, 1.0, 8.0])
        if k == 0:
            kf.init({NAMES["shaft"]: noisy}, 0.0, cov)
        else:
            kf.predict(k / FPS)
            kf.update_part(NAMES["shaft"], *noisy, cov, gate=False)
        if k % 3 == 0:  # the estimator's keyframes: every third frame
            kf.note_root_pose(*noisy)
        d = kf.root_axis(R, t)[1]
        e = kf.part_pose(NAMES["shaft"])[1] - t
        errs.append(np.linalg.norm(e - d * (d @ e)))
    return kf, np.array(errs)


def test_the_state_held_through_the_trocar_is_nearer_across_its_axis():
    truth = _shaft_poses(150)
    _, free = _run(None, truth, np.random.default_rng(3))
    kf, held = _run(Trocar(after=8, axis_std_mm=8.0, axis_std_deg=1.0, floor_mm=1.0), truth, np.random.default_rng(3))
    assert kf.trocar.point is not None
    later = slice(60, None)
    assert held[later].mean() < 0.85 * free[later].mean(), (held[later].mean(), free[later].mean())
    o, d = kf.root_axis(*kf.part_pose(NAMES["shaft"]))
    assert _distance_to_axis(TROCAR, o, d) < 3.0


def test_forgotten_and_located_again_when_the_camera_moves():
    moved = TROCAR + np.array([40.0, -25.0, 10.0])
    truth = _shaft_poses(120) + _shaft_poses(240, moved)[120:]  # the endoscope shifts at frame 120
    kf, errs = _run(Trocar(after=8, axis_std_mm=8.0, axis_std_deg=1.0, floor_mm=1.0), truth, np.random.default_rng(4))
    assert kf.trocar.point is not None
    assert _distance_to_axis(kf.trocar.point, moved, kf.root_axis(*truth[-1])[1]) < 3.0
    assert errs[-30:].mean() < 3.0

"""The region measurement (colour statistics along silhouette normals) on rendered frames."""

import numpy as np
import pytest

from surftrack.geometry import PinholeCamera, se3
from surftrack.geometry.transforms import so3_exp, so3_log
from surftrack.instruments import JointState, load_instrument
from surftrack.render import Renderer
from surftrack.render.scene import add_instrument
from surftrack.track import region
from surftrack.track.region import ArticulatedModel, PoseModel, RegionTracker

W, H = 320, 256
K = np.array([[260.0, 0, (W - 1) / 2], [0, 260.0, (H - 1) / 2], [0, 0, 1]])


@pytest.fixture(scope="module")
def scene():
    """The LND (shaft tube included) over a tissue-coloured background, with sensor noise: the image,
    the true part poses and the joints."""
    lnd = load_instrument("lnd")
    q = JointState.from_degrees(roll=20, pitch=25, yaw=-15, opening=30)
    z = np.array([0.8, 0.3, 0.5])
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    base = se3(np.stack([x, np.cross(z, x), z], axis=1), np.array([-6.0, -2.0, 55.0]))
    poses = lnd.forward(base, q)
    r = Renderer(W, H)
    ids = add_instrument(r, lnd)
    rgb = r.render(PinholeCamera(K, W, H), ids.poses(poses), modalities=("rgb",),
                   background=(0.55, 0.3, 0.27)).rgb
    r.release()
    noisy = np.clip(rgb.astype(np.float64) + np.random.default_rng(0).normal(0, 4, rgb.shape), 0, 255)
    return lnd, noisy.astype(np.uint8), {n: (T[:3, :3], T[:3, 3]) for n, T in poses.items()}, q


def _tracker(lnd):
    meshes = {n: p.mesh for n, p in lnd.parts.items()}
    atts = {n: [a.mesh for a in lnd.attachments if a.part == n] for n in lnd.parts}
    return RegionTracker(K, (W, H), meshes, {n: "lnd" for n in meshes}, atts)


def _errors(est, truth):
    return {n: (np.degrees(np.linalg.norm(so3_log(truth[n][0].T @ R))), np.linalg.norm(t - truth[n][1]))
            for n, (R, t) in est.items()}


def test_articulated_model_derivatives_match_finite_differences():
    lnd = load_instrument("lnd")
    names = {n: f"lnd.0.{n}" for n in lnd.parts}
    rng = np.random.default_rng(1)
    m = ArticulatedModel(lnd, names, so3_exp(rng.normal(size=3)), np.array([3.0, -2.0, 60.0]),
                         JointState.from_degrees(pitch=10, yaw=-20, opening=25))
    assert m.size == 9  # the shaft pose and pitch, yaw, opening (the roll is the shaft's own rotation)
    x = rng.normal(scale=0.05, size=m.size)
    D, base = m.derivatives(x), m.poses(x)
    for j in range(m.size):
        e = np.zeros(m.size)
        e[j] = 1e-6
        up = m.poses(x + e)
        for n, (R, t) in base.items():
            num = np.r_[(up[n][1] - t) / 1e-6, so3_log(R.T @ up[n][0]) / 1e-6]
            np.testing.assert_allclose(D[n][:, j], num, atol=2e-3 * max(1.0, np.abs(num).max()))


def test_region_fit_converges_from_a_perturbed_pose(scene):
    """The instrument-wide fit pulls every part back from a perturbed base pose and joints, the shaft's
    roll and its position along its axis included (seen through the wrist and jaws)."""
    lnd, image, truth, q = scene
    rt = _tracker(lnd)
    _, masks = rt.contours(truth)
    rt.learn(image, "lnd", masks["lnd"])
    R0, t0 = truth["shaft"]
    Rp, tp = R0 @ so3_exp(np.radians([2.0, -2.0, 4.0])), t0 + np.array([1.2, -0.8, 1.5])
    q_start = JointState(q.roll, q.pitch + np.radians(6), q.yaw - np.radians(6), q.opening + np.radians(5))
    model = ArticulatedModel(lnd, {n: n for n in lnd.parts}, Rp, tp, q_start)
    start = model.poses(np.zeros(model.size))
    contours, _ = rt.contours(start)
    prior = np.diag([4.0] * 3 + [np.radians(5) ** 2] * 3 + [np.radians(10) ** 2] * 3)
    before = _errors(start, truth)
    for _ in range(3):  # three frames' worth of steps on the same image, contours re-rendered each time
        res = rt.measure(image, contours, model, prior)
        model = ArticulatedModel(lnd, {n: n for n in lnd.parts}, res["shaft"].R, res["shaft"].t,
                                 model.joint_state(model.solution))
        contours, _ = rt.contours({n: (r.R, r.t) for n, r in res.items()})
    after = _errors({n: (r.R, r.t) for n, r in res.items()}, truth)
    rt.release()
    for n in lnd.parts:
        assert after[n][1] < 0.5 * before[n][1] and after[n][1] < 1.0, (n, before[n], after[n])
        assert after[n][0] < 0.6 * before[n][0], (n, before[n], after[n])
    assert all(r.agreement > 0.9 for r in res.values()), {n: r.agreement for n, r in res.items()}
    # the covariance is honest about the shaft: its roll is far less certain than its axis direction
    var_rot = np.linalg.eigvalsh(res["shaft"].cov[3:, 3:])
    assert var_rot[-1] > 10 * var_rot[0]


def test_region_fit_of_a_free_part_and_without_colours(scene):
    lnd, image, truth, _ = scene
    rt = _tracker(lnd)
    R, t = truth["wrist"]
    Rp, tp = R @ so3_exp(np.radians([3.0, 0.0, -3.0])), t + np.array([0.8, 0.6, 0.0])
    contours, masks = rt.contours({"wrist": (Rp, tp)})
    model = PoseModel("wrist", Rp, tp)
    prior = np.diag([4.0] * 3 + [np.radians(5) ** 2] * 3)
    assert rt.measure(image, contours, model, prior) == {}  # no colour model yet: nothing claimed
    assert not rt.learn(image, "lnd", np.zeros_like(masks["lnd"]))  # an empty mask teaches nothing
    assert not rt.colors["lnd"].ready and rt.measure(image, contours, model, prior) == {}
    assert rt.learn(image, "lnd", masks["lnd"])
    res = rt.measure(image, contours, model, prior)["wrist"]
    rt.release()
    # what a lone part's silhouette pins: its place across the image (x, y), and its turns
    lateral = lambda tt: np.linalg.norm((tt - truth["wrist"][1])[:2])  # noqa: E731
    assert lateral(res.t) < 0.4 * lateral(tp), (lateral(tp), lateral(res.t))
    rot = lambda R: np.degrees(np.linalg.norm(so3_log(truth["wrist"][0].T @ R)))  # noqa: E731
    assert rot(res.R) < 0.6 * rot(Rp), (rot(Rp), rot(res.R))


def test_contour_points_nearer_than_the_near_limit_are_not_measured(scene, monkeypatch):
    """Lines at points within ``NEAR_MM`` of the lens are left out (their projection's Jacobian, ~1 / z^2,
    swamped the rest and made the normal equations singular): with the limit beyond the scene's depth
    (55 mm) nothing is measured; at its default the same frame is."""
    lnd, image, truth, _ = scene
    rt = _tracker(lnd)
    R, t = truth["wrist"]
    contours, masks = rt.contours({"wrist": (R, t)})
    rt.learn(image, "lnd", masks["lnd"])
    prior = np.diag([4.0] * 3 + [np.radians(5) ** 2] * 3)
    assert "wrist" in rt.measure(image, contours, PoseModel("wrist", R, t), prior)
    monkeypatch.setattr(region, "NEAR_MM", 100.0)
    assert rt.measure(image, contours, PoseModel("wrist", R, t), prior) == {}
    rt.release()

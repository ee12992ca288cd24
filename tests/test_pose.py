"""Pose estimation: the batched P3P, the hypothesis / scoring / refinement solver on correspondence
distributions built from RENDERED object coordinates (noise + 30 % outliers), and a tiny model end to end."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from surftrack.geometry import PinholeCamera, rotation_angle_deg
from surftrack.instruments import load_instrument
from surftrack.model.config import ModelCfg
from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D
from surftrack.pose import PRESETS, PoseEstimator, p3p, p4p, solve_field, solve_quartic
from surftrack.pose import scoring
from surftrack.pose.scoring import score_poses
from surftrack.pose.synthetic import rendered_problem
from surftrack.pose.views import merge_views, view_offsets

K_LND = np.array([[818.05, 0.0, 476.31], [0.0, 816.0, 298.18], [0.0, 0.0, 1.0]])  # SurgRIPE LND, 960x540


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One intra-op thread: on a 2-core machine that is busy with other work, two OpenMP threads make
    the many small tensor ops of the solver several times slower (the threads wait for each other)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def lnd():
    return load_instrument("large_needle_driver")


def _random_problems(n: int, seed: int):
    """Well-conditioned random P3P problems: points in a 20 mm cube, 50-100 mm in front of the camera,
    triangles with sides >= 5 mm and area >= 20 mm^2."""
    rng = np.random.default_rng(seed)
    P = rng.uniform(-10, 10, (4 * n, 4, 3))
    s = [np.linalg.norm(P[:, i] - P[:, j], axis=1) for i, j in ((0, 1), (0, 2), (1, 2))]
    area = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
    P = P[(np.min(s, axis=0) > 5) & (area > 20)][:n]
    R = Rotation.random(n, random_state=seed).as_matrix()
    t = np.c_[rng.uniform(-10, 10, (n, 2)), rng.uniform(50, 100, n)]
    X = np.einsum("hij,hkj->hki", R, P) + t[:, None]
    return torch.from_numpy(R), torch.from_numpy(t), torch.from_numpy(P), torch.from_numpy(X)


def test_quartic_real_roots_match_numpy():
    c = torch.from_numpy(np.random.default_rng(0).normal(size=(500, 5)))
    roots, real = solve_quartic(c, real_tol=0.0)
    for i in range(len(c)):
        ref = np.roots(c[i].numpy())
        ref = np.sort(ref[np.abs(ref.imag) < 1e-9].real)
        got = np.sort(roots[i][real[i]].numpy())
        assert len(got) == len(ref) and np.allclose(got, ref, atol=1e-9), (c[i], ref, got)


def test_p3p_batched_recovers_random_poses():
    R, t, P, X = _random_problems(5000, seed=1)
    Rs, ts, valid = p3p(X[:, :3] * 0.37, P[:, :3])  # bearings need not be unit vectors
    err = torch.linalg.matrix_norm(Rs - R[:, None], dim=(-2, -1)) + torch.linalg.vector_norm(ts - t[:, None], dim=-1)
    best = torch.where(valid, err, torch.full_like(err, np.inf)).amin(-1)
    assert float(best.max()) < 1e-6, f"{int((best >= 1e-6).sum())} of {len(best)} problems not solved"
    dets = torch.linalg.det(Rs[valid])
    assert torch.allclose(dets, torch.ones_like(dets), atol=1e-9)


def test_p4p_picks_the_true_solution():
    R, t, P, X = _random_problems(3000, seed=2)
    K = torch.tensor(K_LND)
    uvw = X @ K.T
    Rb, tb, err, valid = p4p(uvw[..., :2] / uvw[..., 2:], P, K)
    assert bool(valid.all()) and float(err.max()) < 1e-6
    assert float(torch.linalg.matrix_norm(Rb - R, dim=(-2, -1)).max()) < 1e-6
    assert float(torch.linalg.vector_norm(tb - t, dim=-1).max()) < 1e-6


def _rendered(lnd, part_name: str, seed: int, preset):
    """Rendered LND part at a random pose (seeded), 0.1 mm coordinate noise (about half a grid pixel),
    30 % outliers (:mod:`surftrack.pose.synthetic`)."""
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = [rng.uniform(-10, 10), rng.uniform(-5, 5), rng.uniform(45, 80)]
    return rendered_problem(lnd.parts[part_name], T, PinholeCamera(K_LND, 960, 540), preset, noise_mm=0.1,
                            outliers=0.3, sigma_mm=0.4, seed=seed)


@pytest.mark.parametrize("part_name,seed", [("wrist", 2), ("shaft", 1)])
def test_solver_recovers_pose_from_rendered_correspondences(lnd, part_name, seed):
    preset = PRESETS["accurate"]
    pb = _rendered(lnd, part_name, seed, preset)
    field = pb.field
    sol = solve_field(field, pb.bank, pb.K_grid, pb.box_side, preset, torch.Generator().manual_seed(0))
    re, te = float(rotation_angle_deg(sol.R, pb.R)), float(np.linalg.norm(sol.t - pb.t))
    assert sol.ok and re < 1.0 and te < 1.0, f"{part_name}: RE {re:.3f} deg, TE {te:.3f} mm, {sol.counts}"
    assert sol.counts["plausible"] > 0 and not sol.counts["relaxed"]
    assert set(sol.timings) == {"hypotheses", "scoring", "refinement"}
    # about 70 % of the active pixels are inliers (30 % outliers, the rest within the noise)
    assert 0.5 * len(field.active) < sol.n_inliers < 0.8 * len(field.active)


def test_fast_preset_solver(lnd):
    preset = PRESETS["fast"]
    pb = _rendered(lnd, "wrist", 0, preset)
    sol = solve_field(pb.field, pb.bank, pb.K_grid, pb.box_side, preset, torch.Generator().manual_seed(0))
    re, te = float(rotation_angle_deg(sol.R, pb.R)), float(np.linalg.norm(sol.t - pb.t))
    assert re < 1.5 and te < 1.5, f"RE {re:.3f} deg, TE {te:.3f} mm, {sol.counts}"


def test_prior_pose_is_kept_only_when_it_scores_best(lnd):
    """The tracker hands its pose to the estimator as a prior: the true pose beats the hypotheses of a
    field with few draws; a wrong prior (20 deg off) loses to them."""
    preset = PRESETS["fast"]
    pb = _rendered(lnd, "wrist", 0, preset)
    true = solve_field(pb.field, pb.bank, pb.K_grid, pb.box_side, preset, torch.Generator().manual_seed(0),
                       prior=(pb.R, pb.t))
    assert true.prior_won is True
    assert rotation_angle_deg(true.R, pb.R) < 1.0 and np.linalg.norm(true.t - pb.t) < 1.0
    off = Rotation.from_rotvec(np.radians(20) * np.array([0.0, 0.6, 0.8])).as_matrix()
    wrong = solve_field(pb.field, pb.bank, pb.K_grid, pb.box_side, preset, torch.Generator().manual_seed(0),
                        prior=(pb.R @ off, pb.t + 5.0))
    assert wrong.prior_won is False and rotation_angle_deg(wrong.R, pb.R) < 1.5
    alone = solve_field(pb.field, pb.bank, pb.K_grid, pb.box_side, preset, torch.Generator().manual_seed(0))
    assert alone.prior_won is None


def test_a_pose_touching_the_lens_does_not_outscore_the_true_one(lnd, monkeypatch):
    """Moving the part along the ray of one of its visible points until that point is 0.1 mm from the
    lens keeps the point on its pixel with some 10^5 times its projected area; its weight is capped, so
    the pose scores below the true one (uncapped it scored 50x the true pose on a real shaft crop)."""
    preset = PRESETS["fast"]
    pb = _rendered(lnd, "shaft", 1, preset)
    K = pb.K_grid.double()
    X = pb.bank.points.double() @ torch.as_tensor(pb.R).T + torch.as_tensor(pb.t)
    uv = X @ K.T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    facing = (pb.bank.normals.double() @ torch.as_tensor(pb.R).T * X).sum(1) < 0
    centre = (pb.field.g - 1) / 2.0
    i = int(torch.argmin(torch.where(facing, (u - centre) ** 2 + (v - centre) ** 2, torch.inf)))
    t_near = pb.t - X[i].numpy() * (1.0 - 0.1 / float(X[i, 2]))
    scores = score_poses(torch.as_tensor(np.stack([pb.R, pb.R])), torch.as_tensor(np.stack([pb.t, t_near])),
                         pb.field, pb.bank, pb.K_grid, preset)
    assert float(scores[1]) < float(scores[0]), scores
    monkeypatch.setattr(scoring, "SAMPLE_AREA_CAP", math.inf)  # the case the cap is for
    uncapped = score_poses(torch.as_tensor(np.stack([pb.R, pb.R])), torch.as_tensor(np.stack([pb.t, t_near])),
                           pb.field, pb.bank, pb.K_grid, preset)
    assert float(uncapped[1]) > 10 * float(uncapped[0]), uncapped


@pytest.fixture(scope="module")
def tiny_model(lnd):
    parts = [PartInfo.from_part(i + 1, lnd.name, lnd.parts[n]) for i, n in enumerate(lnd.part_names)]
    torch.manual_seed(0)
    return SurfSurg6D(parts, ModelCfg(decoder_widths=(16, 16, 16, 16, 16), siren_hidden=32)).eval()


BOXES = {1: (300.0, 200.0, 200.0, 120.0), 2: (480.0, 250.0, 60.0, 50.0), 3: (530.0, 260.0, 40.0, 30.0)}


@pytest.mark.parametrize("preset", ["fast", "accurate"])
def test_tiny_model_end_to_end(tiny_model, preset):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (540, 960, 3), dtype=np.uint8)
    est = PoseEstimator(tiny_model, preset, device="cpu", crop_size=64)
    out = est.estimate(img, BOXES, K_LND)
    assert [p.obj_id for p in out] == [1, 2, 3]
    assert [p.part for p in out] == ["shaft", "wrist", "jaw_left"]
    for p in out:
        assert p.R.shape == (3, 3) and p.t.shape == (3,) and np.all(np.isfinite(p.pose))
        assert np.allclose(p.R @ p.R.T, np.eye(3), atol=1e-6) and np.isfinite(p.score) and p.n_inliers >= 0
        for stage in ("crop", "forward", "correspondence", "hypotheses", "scoring", "refinement", "total"):
            assert stage in p.timings and p.timings[stage] >= 0
        assert p.crop_K.shape == (3, 3)
    # Two frames in one call, a repeated part in the second; the first frame's results are reproducible.
    frames = est.estimate_batch([img, img[::-1].copy()], [BOXES, [(2, (10.0, 10.0, 50.0, 40.0)), (2, BOXES[2])]],
                                [K_LND, K_LND])
    assert [len(f) for f in frames] == [3, 2] and [p.image_index for p in frames[1]] == [1, 1]
    for a, b in zip(out, frames[0]):
        assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t)
    # ... and do not depend on their place in the batch (the solver's seed comes from the crop itself)
    later = est.estimate_batch([img[::-1].copy(), img], [[(2, (10.0, 10.0, 50.0, 40.0))], BOXES], [K_LND, K_LND])[1]
    for a, b in zip(out, later):
        assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t)
    assert est.estimate(img, {}, K_LND) == []


def test_merge_views_averages_the_modal_rotation():
    rng = np.random.default_rng(3)
    R0, t0 = Rotation.random(random_state=4).as_matrix(), np.array([5.0, -3.0, 60.0])
    near = [Rotation.from_rotvec(np.radians(3) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ R0 for _ in range(4)]
    flipped = Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix() @ R0
    Rs = [near[0], flipped, *near[1:]]
    ts = [t0 + rng.normal(size=3) for _ in range(5)]
    scores = [0.2, 0.9, 0.3, 0.1, 0.4]  # the flipped view scores best, but no other view agrees with it
    R, t, score, ref, members = merge_views(Rs, ts, scores, 15.0)
    assert list(members) == [0, 2, 3, 4] and ref == 4  # all four agree: the best score among them
    assert np.allclose(t, np.mean([ts[i] for i in members], axis=0)) and score == pytest.approx(0.25)
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert rotation_angle_deg(R, R0) < 3.0
    # Two groups of equal support: the higher score decides
    _, t2, _, ref2, members2 = merge_views([R0, R0, flipped, flipped], ts[:4], [0.1, 0.2, 0.5, 0.3], 15.0)
    assert ref2 == 2 and list(members2) == [2, 3] and np.allclose(t2, (ts[2] + ts[3]) / 2)
    assert view_offsets(1, 0.06) == [(0.0, 0.0)] and len(view_offsets(9, 0.1)) == 9
    assert view_offsets(3, 0.05)[1:] == [(0.05, 0.05), (-0.05, -0.05)]
    with pytest.raises(ValueError, match="views"):
        view_offsets(10, 0.06)
    with pytest.raises(ValueError, match="views"):
        PRESETS["fast"].replace(views=0)


def test_estimator_merges_crop_views(tiny_model):
    img = np.random.default_rng(2).integers(0, 256, (540, 960, 3), dtype=np.uint8)
    one = PoseEstimator(tiny_model, "fast", device="cpu", crop_size=64).estimate(img, BOXES, K_LND)
    est = PoseEstimator(tiny_model, PRESETS["fast"].replace(views=3), device="cpu", crop_size=64)
    out = est.estimate(img, BOXES, K_LND)
    assert [p.obj_id for p in out] == [1, 2, 3]
    for a, p in zip(one, out):
        assert p.counts["views"] == 3 and 1 <= p.counts["views_merged"] <= 3
        assert np.allclose(p.R @ p.R.T, np.eye(3), atol=1e-6) and np.all(np.isfinite(p.t)) and p.ok
        assert p.crop_box == a.crop_box  # the unshifted view's crop
        assert p.timings["forward"] > 0.0 and p.timings["total"] > 0.0  # summed over the views: see below
    # the same poses whatever else is in the batch
    later = est.estimate_batch([img[::-1].copy(), img], [[(2, (10.0, 10.0, 50.0, 40.0))], BOXES], [K_LND, K_LND])
    assert [len(f) for f in later] == [1, 3]
    for a, b in zip(out, later[1]):
        assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t) and a.counts == b.counts


def test_named_parts_get_their_own_crop_views(tiny_model):
    """``part_views`` gives the named part (the instrument fit's anchor, obj 2 the wrist) its own number of
    crop views; the other parts keep the preset's, and each part's pose is what an estimator with that
    number of views for every part gives it."""
    img = np.random.default_rng(3).integers(0, 256, (540, 960, 3), dtype=np.uint8)
    assert tiny_model.parts[1].name == "wrist"
    preset = PRESETS["fast"].replace(part_views=(("wrist", 3),))
    assert preset.views_of("wrist") == 3 and preset.views_of("shaft") == 1
    out = PoseEstimator(tiny_model, preset, device="cpu", crop_size=64).estimate(img, BOXES, K_LND)
    one = PoseEstimator(tiny_model, "fast", device="cpu", crop_size=64).estimate(img, BOXES, K_LND)
    three = PoseEstimator(tiny_model, PRESETS["fast"].replace(views=3), device="cpu", crop_size=64).estimate(
        img, BOXES, K_LND)
    assert [p.obj_id for p in out] == [1, 2, 3]
    assert out[1].counts["views"] == 3 and "views" not in out[0].counts and "views" not in out[2].counts
    for got, want in zip(out, (one[0], three[1], one[2])):
        assert np.allclose(got.R, want.R) and np.allclose(got.t, want.t) and got.score == pytest.approx(want.score)
    # a box's stage times add up its views' (one network forward: each crop has the same share of it)
    assert out[1].timings["forward"] == pytest.approx(3 * out[0].timings["forward"])
    assert PRESETS["fast"].replace(part_views=[["wrist", 3]]).part_views == (("wrist", 3),)  # hashable
    for bad in ((("wrist", 10),), (("wrist", True),), (("wrist", "3"),), {"wrist": 3}, (("wrist",),)):
        with pytest.raises(ValueError, match="part_views must be"):
            PRESETS["fast"].replace(part_views=bad)
    with pytest.raises(ValueError, match="crop views asked for wirst, not a part of the model"):
        PoseEstimator(tiny_model, PRESETS["fast"].replace(part_views=(("wirst", 3),)), device="cpu", crop_size=64)


def test_twin_jaws_trade_boxes_by_score(tiny_model):
    """The LND's jaws are each other's roll twin's: with instrument groups each jaw is also estimated on
    the other jaw's box, and the assignment with the larger summed score is kept, the results keeping their
    boxes' order and labels. So the jaws' poses do not depend on which of the two boxes carries which label;
    other parts, and jaws of different instruments, are estimated as without groups."""
    img = np.random.default_rng(5).integers(0, 256, (540, 960, 3), dtype=np.uint8)
    est = PoseEstimator(tiny_model, "fast", device="cpu", crop_size=64)
    assert est.twin_partner == {3: 4, 4: 3}
    a, b = (530.0, 260.0, 40.0, 30.0), (560.0, 250.0, 50.0, 40.0)
    boxes = [(1, BOXES[1]), (2, BOXES[2]), (3, a), (4, b)]
    plain = est.estimate(img, boxes, K_LND)
    crossed = est.estimate(img, [(3, b), (4, a)], K_LND)
    paired = est.estimate(img, boxes, K_LND, groups=[0, 0, 0, 0])
    relabelled = est.estimate(img, [(1, BOXES[1]), (2, BOXES[2]), (3, b), (4, a)], K_LND, groups=[0, 0, 0, 0])
    swap = crossed[0].score + crossed[1].score > plain[2].score + plain[3].score
    expect = crossed if swap else plain[2:]
    assert [p.obj_id for p in paired] == [p.obj_id for p in relabelled] == [1, 2, 3, 4]
    for got, again, want in zip(paired[2:], relabelled[2:], expect):
        assert np.allclose(got.R, want.R) and np.allclose(got.t, want.t) and got.crop_box == want.crop_box
        assert np.allclose(again.R, want.R) and np.allclose(again.t, want.t)
    for got, want in zip(paired[:2], plain[:2]):
        assert np.allclose(got.R, want.R) and np.allclose(got.t, want.t)
    apart = est.estimate(img, boxes, K_LND, groups=[0, 0, 0, 1])  # jaws of two instruments: no trade
    for got, want in zip(apart, plain):
        assert np.allclose(got.R, want.R) and np.allclose(got.t, want.t)


def test_estimator_from_checkpoint(tiny_model, tmp_path):
    from surftrack.model import save_checkpoint
    from surftrack.model.config import TrainConfig

    cfg = TrainConfig.from_dict({"model": {"decoder_widths": [16, 16, 16, 16, 16], "siren_hidden": 32},
                                 "data": {"crop": 48, "scale": 1.3}})
    path = save_checkpoint(tmp_path / "tiny.pt", tiny_model, cfg, step=0)
    est = PoseEstimator(path, "fast", device="cpu")
    assert (est.crop_size, est.box_scale, est.obj_ids) == (48, 1.3, [1, 2, 3, 4])
    img = np.random.default_rng(1).integers(0, 256, (540, 960, 3), dtype=np.uint8)
    (p,) = est.estimate(img, [(4, (500.0, 260.0, 40.0, 30.0))], K_LND)
    assert p.part == "jaw_right" and np.all(np.isfinite(p.pose))
    x0, y0, x1, y1 = p.crop_box  # square, centred on the box, 1.3 x its longer side
    assert np.allclose([x1 - x0, y1 - y0, (x0 + x1) / 2, (y0 + y1) / 2], [52.0, 52.0, 520.0, 275.0])


def test_bad_inputs_raise_clear_errors(tiny_model):
    est = PoseEstimator(tiny_model, "fast", device="cpu", crop_size=64)
    img = np.zeros((540, 960, 3), np.uint8)
    with pytest.raises(ValueError, match="unknown obj_id 9"):
        est.estimate(img, {9: (0, 0, 10, 10)}, K_LND)
    with pytest.raises(ValueError, match="degenerate box"):
        est.estimate(img, {1: (10, 10, 0, 20)}, K_LND)
    with pytest.raises(ValueError, match="degenerate box"):
        est.estimate(img, {1: (10, 10, 5, -1)}, K_LND)
    with pytest.raises(ValueError, match="outside"):
        est.estimate(img, {1: (2000, 10, 50, 50)}, K_LND)
    with pytest.raises(ValueError, match="4 finite numbers"):
        est.estimate(img, {1: (10, 10, np.nan, 5)}, K_LND)
    with pytest.raises(ValueError, match="uint8"):
        est.estimate(img.astype(np.float32), {1: (10, 10, 50, 50)}, K_LND)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        est.estimate(img[..., 0], {1: (10, 10, 50, 50)}, K_LND)
    with pytest.raises(ValueError, match="3x3"):
        est.estimate(img, {1: (10, 10, 50, 50)}, np.eye(2))
    with pytest.raises(ValueError, match="fx, fy > 0"):
        est.estimate(img, {1: (10, 10, 50, 50)}, np.diag([0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="as many"):
        est.estimate_batch([img, img], [{1: (10, 10, 50, 50)}], [K_LND])
    with pytest.raises(ValueError, match="unknown preset"):
        PoseEstimator(tiny_model, "slow")
    with pytest.raises(ValueError, match="SurfSurg6D model or a checkpoint"):
        PoseEstimator(42)


def test_the_network_masks_come_with_the_poses_when_asked(tiny_model):
    """``masks=True``: each pose carries its crop's foreground probability (the network's sigmoid), the
    poses themselves unchanged; ``image_mask`` puts it into the frame over the crop's pixels only."""
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (540, 960, 3), dtype=np.uint8)
    est = PoseEstimator(tiny_model, "fast", device="cpu", crop_size=64)
    plain = est.estimate(img, BOXES, K_LND)
    with_masks = est.estimate(img, BOXES, K_LND, masks=True)
    assert all(p.mask is None for p in plain)
    for a, b in zip(plain, with_masks):
        assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t)
        assert b.mask.shape == (64, 64) and b.mask.dtype == np.float32
        assert 0.0 <= b.mask.min() and b.mask.max() <= 1.0
        prob, covered = b.image_mask((960, 540))
        x0, y0, x1, y1 = b.crop_box
        inside, near = np.zeros((540, 960), bool), np.zeros((540, 960), bool)
        inside[max(int(np.ceil(y0)), 0):int(y1), max(int(np.ceil(x0)), 0):int(x1)] = True
        r = int(np.ceil((x1 - x0) / 64)) + 1  # a crop pixel's reach in the frame (bilinear)
        near[max(int(y0) - r, 0):int(y1) + r, max(int(x0) - r, 0):int(x1) + r] = True
        assert covered.sum() > 0 and (covered <= inside).all() and (prob[~near] == 0).all()
    with pytest.raises(ValueError, match="without its mask"):
        plain[0].image_mask((960, 540))
    # with several crop views per box, the mask is the unshifted view's (the crop of crop_box)
    views = PoseEstimator(tiny_model, PRESETS["fast"].replace(views=3), device="cpu", crop_size=64)
    for a, b in zip(with_masks, views.estimate(img, BOXES, K_LND, masks=True)):
        assert b.crop_box == a.crop_box and np.allclose(b.mask, a.mask, atol=1e-6)

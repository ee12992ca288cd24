import json
from pathlib import Path

import numpy as np
import pytest

from surftrack.eval import (
    add,
    add_threshold_rate,
    adds,
    auc,
    diameter_bbox_diagonal,
    diameter_max_pairwise,
    dice,
    keypoint_oks,
    mspd,
    mssd,
    oks_ap_per_threshold,
    oks_map,
    proj,
    re,
    te,
)

GOLDEN = Path(__file__).resolve().parents[1].parent / "shared" / "golden" / "metrics_golden.json"
RTOL, ATOL = 1e-6, 1e-9
K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
rng = np.random.default_rng(3)
PTS = rng.uniform(-10, 10, size=(200, 3))


def rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------- golden reference
@pytest.fixture(scope="module")
def golden():
    if not GOLDEN.is_file():
        pytest.skip(f"golden metric values not found at {GOLDEN} (shared/golden is outside the repository)")
    return json.loads(GOLDEN.read_text())


def close(a, b):
    return abs(a - b) <= max(ATOL, RTOL * abs(b))


def case_errors(golden, case):
    pts = np.array(golden["objects"][case["object"]]["points"])
    Kg = np.array(golden["K"])
    R_e, t_e, R_g, t_g = (np.array(case[k]) for k in ("R_est", "t_est", "R_gt", "t_gt"))
    return {
        "add": add(R_e, t_e, R_g, t_g, pts),
        "adi": adds(R_e, t_e, R_g, t_g, pts),
        "re_deg": re(R_e, R_g),
        "te": te(t_e, t_g),
        "mssd": mssd(R_e, t_e, R_g, t_g, pts),
        "mspd": mspd(R_e, t_e, R_g, t_g, Kg, pts),
        "proj": proj(R_e, t_e, R_g, t_g, Kg, pts),
    }


def test_golden_pose_errors(golden):
    bad = []
    for i, case in enumerate(golden["cases"]):
        for name, value in case_errors(golden, case).items():
            if not close(value, case[name]):
                bad.append((i, name, value, case[name]))
    assert not bad, bad


def test_golden_diameters(golden):
    for obj in golden["objects"].values():
        pts = np.array(obj["points"])
        assert close(diameter_max_pairwise(pts), obj["diameter_max_pairwise"])
        assert close(diameter_bbox_diagonal(pts), obj["diameter_bbox_diagonal"])


def test_golden_summary(golden):
    for name, summary in golden["summary"].items():
        errs = [case_errors(golden, c)["add"] for c in golden["cases"] if c["object"] == name]
        assert len(errs) == 40
        pts = np.array(golden["objects"][name]["points"])
        got = {
            "add10_rate_max_pairwise": add_threshold_rate(errs, diameter_max_pairwise(pts)),
            "add10_rate_bbox_diagonal": add_threshold_rate(errs, diameter_bbox_diagonal(pts)),
            "auc_add_0_5mm": auc(errs, 5.0),
            "auc_add_0_10mm": auc(errs, 10.0),
        }
        for key, value in got.items():
            assert close(value, summary[key]), (name, key, value, summary[key])
        # the golden ADDs and diameters give the same
        g_errs = [c["add"] for c in golden["cases"] if c["object"] == name]
        obj = golden["objects"][name]
        assert add_threshold_rate(g_errs, obj["diameter_max_pairwise"]) == summary["add10_rate_max_pairwise"]
        assert add_threshold_rate(g_errs, obj["diameter_bbox_diagonal"]) == summary["add10_rate_bbox_diagonal"]
        assert close(auc(g_errs, 5.0), summary["auc_add_0_5mm"])
        assert close(auc(g_errs, 10.0), summary["auc_add_0_10mm"])


def test_golden_oks_map(golden):
    o = golden["oks"]
    res = oks_map(o["ground_truth"], o["detections"], sigmas=o["sigmas"])
    assert close(res.mAP, o["mAP"]) and close(res.AP50, o["AP50"]) and close(res.AP75, o["AP75"]), res
    # area taken from the box when absent (the golden areas are the GT box areas)
    gts = [{k: v for k, v in g.items() if k != "area"} for g in o["ground_truth"]]
    assert close(oks_map(gts, o["detections"], sigmas=o["sigmas"]).mAP, o["mAP"])


# ------------------------------------------------------------------------------- hand-computed cases
def test_identity_pose_gives_zero_errors():
    R, t = np.eye(3), np.array([1.0, -2.0, 100.0])
    assert add(R, t, R, t, PTS) == 0.0
    assert adds(R, t, R, t, PTS) == 0.0
    assert re(R, R) == 0.0
    assert te(t, t) == 0.0
    assert mssd(R, t, R, t, PTS) == 0.0
    assert mspd(R, t, R, t, K, PTS) == 0.0
    assert proj(R, t, R, t, K, PTS) == 0.0


def test_pure_translation():
    R, t_g = rot_z(30.0), np.array([0.0, 0.0, 100.0])
    dt = np.array([3.0, -4.0, 12.0])
    t_e = (t_g + dt).reshape(3, 1)  # (3, 1) accepted as well as (3,)
    assert add(R, t_e, R, t_g, PTS) == pytest.approx(13.0, abs=1e-12)
    assert te(t_e, t_g) == pytest.approx(13.0, abs=1e-12)
    assert mssd(R, t_e, R, t_g, PTS) == pytest.approx(13.0, abs=1e-12)
    assert re(R, R) == pytest.approx(0.0, abs=1e-6)
    # image-plane shift of a point at depth z is f * dx / z: a lateral shift at constant depth
    t_e2 = t_g + np.array([2.0, 0.0, 0.0])
    flat = np.column_stack([PTS[:, :2], np.zeros(len(PTS))])
    assert proj(np.eye(3), t_e2, np.eye(3), t_g, K, flat) == pytest.approx(800 * 2 / 100, rel=1e-12)
    assert mspd(np.eye(3), t_e2, np.eye(3), t_g, K, flat) == pytest.approx(16.0, rel=1e-12)


def test_rotation_error_degrees():
    assert re(rot_z(90.0), np.eye(3)) == pytest.approx(90.0, abs=1e-9)
    assert re(rot_z(180.0), np.eye(3)) == pytest.approx(180.0, abs=1e-6)
    assert re(rot_z(25.0) @ rot_z(10.0), rot_z(10.0)) == pytest.approx(25.0, abs=1e-9)


def test_symmetric_object():
    # points on a ring about z: a rotation about z leaves the point set (nearly) unchanged
    ang = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    ring = np.column_stack([10 * np.cos(ang), 10 * np.sin(ang), np.zeros_like(ang)])
    t = np.array([0.0, 0.0, 150.0])
    R_e = rot_z(20.0)
    a, s = add(R_e, t, np.eye(3), t, ring), adds(R_e, t, np.eye(3), t, ring)
    assert s < 1e-9 < a
    assert a == pytest.approx(2 * 10 * np.sin(np.radians(10.0)), rel=1e-9)
    # MSSD with the matching symmetry removes the error; without it, it is the max distance
    assert mssd(R_e, t, np.eye(3), t, ring) == pytest.approx(a, rel=1e-9)
    sym = [{"R": np.eye(3), "t": np.zeros(3)}, {"R": rot_z(20.0), "t": np.zeros((3, 1))}]
    assert mssd(R_e, t, np.eye(3), t, ring, syms=sym) == pytest.approx(0.0, abs=1e-9)
    T = np.eye(4)
    T[:3, :3] = rot_z(20.0)
    assert mspd(R_e, t, np.eye(3), t, K, ring, syms=[np.eye(4), T]) == pytest.approx(0.0, abs=1e-9)


def test_diameters_and_add10():
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 2) for z in (0, 2)], dtype=float)
    assert diameter_max_pairwise(cube) == pytest.approx(3.0)
    assert diameter_bbox_diagonal(cube) == pytest.approx(3.0)
    tri = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [2.0, 1.0, 0.0]])
    assert diameter_max_pairwise(tri) == pytest.approx(4.0)
    assert diameter_bbox_diagonal(tri) == pytest.approx(np.hypot(4.0, 1.0))
    big = rng.normal(size=(1000, 3))  # hull shortcut equals brute force
    brute = np.max(np.linalg.norm(big[:, None] - big[None], axis=-1))
    assert diameter_max_pairwise(big) == pytest.approx(brute, rel=1e-12)
    # strict "<": an error equal to 10% of the diameter is a failure
    assert add_threshold_rate([0.5, 1.0, 2.0, np.inf], diameter=10.0) == 0.25
    assert add_threshold_rate([0.5, 1.0], diameter=10.0, frac=0.2) == 1.0


def test_auc_vocap():
    # all perfect -> 1, all beyond the range -> 0
    assert auc([0.0, 0.0], 5.0) == pytest.approx(1.0)
    assert auc([7.0, np.inf], 5.0) == 0.0
    # VOCap = exact mean of accuracy(ADD < d) + e_(m) / (n max): errors 1 and 3 on [0, 5]
    exact = ((5 - 1) + (5 - 3)) / 2 / 5
    assert auc([3.0, 1.0], 5.0) == pytest.approx(exact + 3.0 / (2 * 5.0), rel=1e-12)
    assert auc([1.0, 3.0, 9.0], 10.0) == pytest.approx((9 + 7 + 1) / 3 / 10 + 9 / 30, rel=1e-12)


def test_dice():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    assert dice(a, b) == 1.0
    a[:2, :2] = True  # 4 px
    assert dice(a, b) == 0.0
    b[:2, :] = True  # 8 px, overlap 4
    assert dice(a, b) == pytest.approx(2 * 4 / 12)
    assert dice(a, a) == 1.0
    with pytest.raises(ValueError, match="same shape"):
        dice(a, np.zeros((3, 4), bool))


# ----------------------------------------------------------------------------------------------- OKS
def kp_gt(i):
    return [100.0 + i, 50.0, 2, 140.0 + i, 60.0, 2, 120.0 + i, 90.0, 2]


def test_perfect_keypoint_detections_give_map_one():
    gts = [{"image_id": i, "keypoints": kp_gt(i), "bbox": [90.0, 40.0, 60.0, 60.0]} for i in range(5)]
    dts = [{"image_id": i, "keypoints": kp_gt(i), "score": 0.5 + 0.1 * i} for i in range(5)]
    res = oks_map(gts, dts)
    assert res == (1.0, 1.0, 1.0)
    assert keypoint_oks(kp_gt(0), 3600.0, kp_gt(0)) == 1.0


def test_oks_value_and_partial_map():
    # one keypoint off by d: OKS = (2 + exp(-d^2 / (2 s^2 k^2))) / 3 with k = 2 sigma
    area, sigma, d = 2500.0, 0.1, 6.0
    det = kp_gt(0)
    det[0] += d
    expected = (2 + np.exp(-(d**2) / (2 * area * (2 * sigma) ** 2))) / 3
    assert keypoint_oks(kp_gt(0), area, det, [sigma] * 3) == pytest.approx(expected, rel=1e-12)
    # an unlabelled keypoint (v = 0) does not count
    gt = kp_gt(0)
    gt[2] = 0
    assert keypoint_oks(gt, area, det, [sigma] * 3) == pytest.approx(1.0)
    # two images, one perfect, one missed: recall reaches 0.5 at precision 1 -> AP = 51 / 101
    gts = [{"image_id": i, "keypoints": kp_gt(0), "area": area} for i in (0, 1)]
    dts = [{"image_id": 0, "keypoints": kp_gt(0), "score": 0.9}]
    res = oks_map(gts, dts)
    assert res.mAP == pytest.approx(51 / 101) and res.AP50 == pytest.approx(51 / 101)
    # a false positive scored higher than the true positive halves precision
    dts.append({"image_id": 1, "keypoints": [0, 0, 1, 1, 1, 1, 2, 0, 1], "score": 0.95})
    assert oks_map(gts, dts).AP50 == pytest.approx(51 / 101 * 0.5)
    aps = oks_ap_per_threshold(gts, dts)
    assert aps.shape == (10,)


def test_gt_without_labelled_keypoints_is_ignored():
    # COCO: a GT with num_keypoints == 0 is ignored; its OKS uses the distance to its box enlarged by its
    # size on each side, and a detection matched to it is neither a TP nor an FP
    unlabelled = [100.0, 50.0, 0, 140.0, 60.0, 0, 120.0, 90.0, 0]
    box = [90.0, 40.0, 60.0, 60.0]
    inside = [80.0, 30.0, 1, 200.0, 150.0, 1, 120.0, 90.0, 1]  # in [30, 210] x [-20, 160]
    assert keypoint_oks(unlabelled, 3600.0, inside, gt_bbox=box) == 1.0
    outside = [20.0, 30.0, 1] + inside[3:]  # 10 px left of the enlarged box
    e = 10.0**2 / (2 * 0.1) ** 2 / (3600.0 + np.spacing(1)) / 2
    assert keypoint_oks(unlabelled, 3600.0, outside, gt_bbox=box) == pytest.approx((2 + np.exp(-e)) / 3)
    gts = [
        {"image_id": 0, "keypoints": kp_gt(0), "bbox": box},
        {"image_id": 1, "keypoints": unlabelled, "bbox": box},
    ]
    dts = [
        {"image_id": 1, "keypoints": inside, "score": 0.99},
        {"image_id": 0, "keypoints": kp_gt(0), "score": 0.5},
    ]
    assert oks_map(gts, dts) == pytest.approx((1.0, 1.0, 1.0), abs=1e-15)  # 1 / (1 + eps), as COCO
    # no regular GT at all -> undefined (COCO prints -1)
    assert np.isnan(oks_map(gts[1:], dts[:1]).mAP)


def test_input_checks():
    with pytest.raises(ValueError, match="3x3"):
        re(np.eye(4), np.eye(3))
    with pytest.raises(ValueError, match=r"\(3,\)"):
        te(np.zeros(4), np.zeros(3))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        add(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="sigmas"):
        oks_map([{"image_id": 0, "keypoints": kp_gt(0), "area": 1.0}], [], sigmas=[0.1, 0.1])
    with pytest.raises(ValueError, match="area"):
        oks_map([{"image_id": 0, "keypoints": kp_gt(0)}], [])
    with pytest.raises(ValueError, match="non-negative"):
        auc([-1.0])

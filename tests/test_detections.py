"""det.json: schema and semantic validation, file I/O errors, and the simulated noisy detector."""

import copy
import json

import numpy as np
import pytest

from surftrack.synth.detections import (
    SCHEMA_PATH,
    DetectionNoise,
    clip_box,
    detections_document,
    load_detections,
    load_schema,
    simulate_detections,
    validate_detections,
    write_detections,
)

W, H = 320, 256
PARTS = {
    1: {"instrument": "large_needle_driver", "instance": 0, "part": "shaft"},
    2: {"instrument": "large_needle_driver", "instance": 0, "part": "wrist"},
    3: {"instrument": "large_needle_driver", "instance": 0, "part": "jaw_left"},
}
GT = {1: (10.5, 20.25, 80.0, 30.0), 2: (100.0, 90.0, 40.5, 35.0), 3: (150.0, 120.0, 20.0, 16.0)}
VISIBLE = {1: 2000, 2: 1200, 3: 250}


def generated_doc(n=12, seed=0):
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        dets = simulate_detections(GT, VISIBLE, (W, H), DetectionNoise(false_prob=0.3), rng)
        frames.append({"index": i, "time": i / 30.0, "detections": dets})
    frames.append({"index": n + 3, "time": (n + 3) / 30.0, "detections": []})  # skipped frames, no boxes
    return detections_document((W, H), PARTS, frames, meta={"detector": "simulated", "seed": seed})


def test_schema_file_is_a_valid_schema():
    assert SCHEMA_PATH.is_file()
    schema = load_schema()
    assert schema["$schema"].endswith("2020-12/schema")


def test_generated_document_validates_and_roundtrips(tmp_path):
    doc = generated_doc()
    validate_detections(doc)
    path = tmp_path / "out" / "det.json"
    write_detections(path, doc)
    back = load_detections(path)
    assert back == json.loads(json.dumps(doc))
    assert list(back["parts"]) == ["1", "2", "3"]
    assert any(f["detections"] for f in back["frames"])
    assert not list(tmp_path.glob("out/*.tmp"))


def test_numpy_values_and_tuples_are_accepted(tmp_path):
    doc = detections_document((W, H), PARTS, [
        {"index": np.int64(0), "time": np.float32(0.0),
         "detections": [{"part_id": np.int32(2), "bbox": (1.0, 2.0, np.float32(3.0), 4), "score": np.float64(0.5)}]}])
    write_detections(tmp_path / "det.json", doc)
    assert load_detections(tmp_path / "det.json")["frames"][0]["detections"][0]["bbox"] == [1.0, 2.0, 3.0, 4]


def broken(mutate):
    doc = json.loads(json.dumps(generated_doc()))
    doc["frames"][0]["detections"] = [{"part_id": 1, "bbox": [1.0, 2.0, 30.0, 40.0], "score": 0.9}]
    mutate(doc)
    return doc


CASES = {
    "missing key": (lambda d: d.pop("image_size"), "image_size"),
    "missing detection key": (lambda d: d["frames"][0]["detections"][0].pop("score"), "score"),
    "negative w": (lambda d: d["frames"][0]["detections"][0]["bbox"].__setitem__(2, -1.0), r"bbox\[2\]"),
    "score > 1": (lambda d: d["frames"][0]["detections"][0].__setitem__("score", 1.2), "score"),
    "unknown part_id": (lambda d: d["frames"][0]["detections"][0].__setitem__("part_id", 9), "part_id"),
    "non-increasing index": (lambda d: d["frames"][1].__setitem__("index", 0), r"frames\[1\].index"),
    "decreasing time": (lambda d: d["frames"][2].__setitem__("time", 0.0), r"frames\[2\].time"),
    "wrong format": (lambda d: d.__setitem__("format", "bop-detections"), "format"),
    "wrong version": (lambda d: d.__setitem__("version", 2), "version"),
    "extra key": (lambda d: d["frames"][0].__setitem__("boxes", []), "boxes"),
    "bad part key": (lambda d: d["parts"].__setitem__("wrist", dict(PARTS[2])), "wrist"),
    "box outside image": (lambda d: d["frames"][0]["detections"][0].__setitem__("bbox", [300.0, 2.0, 30.0, 4.0]),
                          "outside"),
    "bool as number": (lambda d: d["frames"][0].__setitem__("index", True), "index"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_invalid_documents_are_rejected(tmp_path, case):
    mutate, pattern = CASES[case]
    doc = broken(mutate)
    with pytest.raises(ValueError, match=pattern) as e:
        validate_detections(doc, source="clip7/det.json")
    msg = str(e.value)
    assert msg.startswith("clip7/det.json: ") and "\n" not in msg and len(msg) < 400
    # The same through a file: the message names the file.
    path = tmp_path / "bad_det.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=pattern) as e:
        load_detections(path)
    assert str(path) in str(e.value)
    with pytest.raises(ValueError, match="bad_det.json"):
        write_detections(tmp_path / "bad_det.json", doc)


def test_valid_base_of_broken_cases():
    validate_detections(broken(lambda d: None))


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(ValueError, match="nothing_here.json") as e:
        load_detections(tmp_path / "nothing_here.json")
    assert "\n" not in str(e.value)
    bad = tmp_path / "truncated.json"
    bad.write_text('{"format": "surftrack-detections", "frames": [')
    with pytest.raises(ValueError, match=r"truncated.json: invalid JSON.*line 1") as e:
        load_detections(bad)
    nan = tmp_path / "nan.json"
    nan.write_text(json.dumps(generated_doc()).replace('"time": 0.0', '"time": NaN', 1))
    with pytest.raises(ValueError, match="nan.json: invalid JSON: NaN"):
        load_detections(nan)
    arr = tmp_path / "array.json"
    arr.write_text("[]")
    with pytest.raises(ValueError, match="array.json"):
        load_detections(arr)


def test_zero_noise_returns_the_ground_truth():
    rng = np.random.default_rng(1)
    gt = {**GT, 4: None}
    for _ in range(20):
        dets = simulate_detections(gt, VISIBLE, (W, H), DetectionNoise.none(), rng)
        assert {d["part_id"]: tuple(d["bbox"]) for d in dets} == {k: v for k, v in GT.items()}
        assert all(d["score"] == 1.0 for d in dets)
    # min_visible_px hides barely visible parts.
    noise = DetectionNoise(center_std=0, scale_std=0, miss_prob=0, false_prob=0, min_visible_px=300)
    dets = simulate_detections(GT, VISIBLE, (W, H), noise, rng)
    assert sorted(d["part_id"] for d in dets) == [1, 2]


def test_deterministic_for_a_seed():
    a = simulate_detections(GT, VISIBLE, (W, H), DetectionNoise(false_prob=0.5), np.random.default_rng(5))
    b = simulate_detections(GT, VISIBLE, (W, H), DetectionNoise(false_prob=0.5), np.random.default_rng(5))
    assert a == b


def test_jitter_statistics():
    noise = DetectionNoise(center_std=0.03, scale_std=0.05, miss_prob=0.0, false_prob=0.0)
    gt = {1: (100.0, 80.0, 100.0, 80.0)}
    rng = np.random.default_rng(2)
    errs, logs = [], []
    for _ in range(3000):
        (d,) = simulate_detections(gt, {1: 5000}, (W, H), noise, rng)
        x, y, w, h = d["bbox"]
        errs.append([(x + w / 2 - 150.0) / 100.0, (y + h / 2 - 120.0) / 80.0])
        logs.append([np.log(w / 100.0), np.log(h / 80.0)])
        assert 0.6 <= d["score"] <= 1.0
    errs, logs = np.asarray(errs), np.asarray(logs)
    assert np.all(np.abs(errs.mean(axis=0)) < 0.003)
    assert np.all((errs.std(axis=0) > 0.027) & (errs.std(axis=0) < 0.033))
    assert np.all((logs.std(axis=0) > 0.045) & (logs.std(axis=0) < 0.055))


def run_frames(noise, gt, visible, n, seed):
    rng = np.random.default_rng(seed)
    return [simulate_detections(gt, visible, (W, H), noise, rng) for _ in range(n)]


def test_miss_and_false_rates():
    gt = {1: (10.0, 20.0, 60.0, 40.0), 2: (200.0, 100.0, 50.0, 40.0), 3: None}
    visible = {1: 1000, 2: 1000}
    n = 4000
    frames = run_frames(DetectionNoise(miss_prob=0.1, false_prob=0.0), gt, visible, n, seed=3)
    miss_rate = 1 - sum(len(d) for d in frames) / (2 * n)
    assert 0.08 < miss_rate < 0.12, miss_rate
    # With no misses, every box beyond the two real ones is a false one.
    frames = run_frames(DetectionNoise(miss_prob=0.0, false_prob=0.05), gt, visible, n, seed=4)
    extra = [len(d) - 2 for d in frames]
    assert set(extra) <= {0, 1}
    assert 0.035 * n < sum(extra) < 0.065 * n, sum(extra)
    scores_true, scores_false, sizes = [], [], []
    for dets in frames:
        for d in dets:
            real = d["part_id"] in (1, 2) and np.allclose(d["bbox"][:2], gt[d["part_id"]][:2], atol=15)
            (scores_true if real else scores_false).append(d["score"])
            if not real:
                sizes.append(d["bbox"][2:])
    assert np.mean(scores_false) < np.mean(scores_true) - 0.1
    # False boxes are sized like the real parts (55 x 40 on average).
    assert 35 < np.median(np.asarray(sizes)[:, 0]) < 80 and 25 < np.median(np.asarray(sizes)[:, 1]) < 60


def test_boxes_always_inside_image():
    noise = DetectionNoise(miss_prob=0.1, false_prob=0.3, center_std=0.3, scale_std=0.3)
    # Boxes touching every border, so jitter pushes them outside and clipping must act.
    gt = {1: (0.0, 0.0, 60.0, 40.0), 2: (W - 50.0, H - 40.0, 50.0, 40.0), 3: (0.0, H - 30.0, W, 30.0)}
    frames = run_frames(noise, gt, {1: 1000, 2: 1000, 3: 1000}, 2000, seed=5)
    clipped = 0
    for dets in frames:
        for d in dets:
            x, y, w, h = d["bbox"]
            assert 0 <= x and 0 <= y and w > 0 and h > 0 and x + w <= W and y + h <= H
            assert d["part_id"] in gt and 0 <= d["score"] <= 1
            clipped += x == 0 or y == 0 or x + w == W or y + h == H
    assert clipped > 1000


def test_clip_box():
    assert clip_box((-5.0, 2.0, 10.0, 4.0), (W, H)) == (0.0, 2.0, 5.0, 4.0)
    assert clip_box((W - 3.0, H - 2.0, 10.0, 10.0), (W, H)) == (W - 3.0, H - 2.0, 3.0, 2.0)
    assert clip_box((W + 1.0, 0.0, 10.0, 10.0), (W, H)) is None
    box = (0.1, 0.2, 0.3, 0.7)
    assert clip_box(box, (W, H)) == box


def test_noise_from_dict():
    noise = DetectionNoise.from_dict({"miss_prob": 0.2, "score_range": [0.5, 0.9]})
    assert noise.miss_prob == 0.2 and noise.score_range == (0.5, 0.9) and noise.center_std == 0.03
    with pytest.raises(ValueError, match="miss_rate"):
        DetectionNoise.from_dict({"miss_rate": 0.2})
    with pytest.raises(ValueError, match="score_range"):
        DetectionNoise(score_range=(0.5, 1.5))


def test_document_helper_does_not_alias():
    frames = [{"index": 0, "time": 0.0, "detections": []}]
    doc = detections_document((W, H), {"2": PARTS[2]}, frames)
    snapshot = copy.deepcopy(doc)
    validate_detections(doc)
    assert doc == snapshot

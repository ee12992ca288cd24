"""MCAP tracking log: topics, schemas, encodings, times, units, metadata, statistics, interrupted runs."""

import base64
import json

import numpy as np
import pytest
from mcap.reader import make_reader
from scipy.spatial.transform import Rotation

from surftrack.io import TrackWriter

PARTS = ("shaft", "jaw")
K = np.array([[500.0, 0, 32], [0, 500.0, 24], [0, 0, 1]])
JPEG = b"\xff\xd8\xff\xe0fake-jpeg\xff\xd9"
TIMES = (0.0, 0.0333333333, 1.5, 2.000000001)


def part_pose(i, j):
    R = Rotation.from_rotvec([0.3 * i + j, -0.2, 0.1 * j + 0.05]).as_matrix()
    t = np.array([10.0 * i - 5, 3.0 * j + 1, 80.0 + i])
    return R, t


def write_frames(w, times):
    verts = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]], float)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    for i, ts in enumerate(times):
        poses = {p: part_pose(i, j) for j, p in enumerate(PARTS)}
        if i == 0:
            w.camera_calibration(ts, K, 64, 48, dist=[0.1, -0.01, 0, 0, 0])
            w.scene_meshes(ts, {p: (verts, faces, (0.8, 0.8, 0.9)) for p in PARTS})
        w.image_jpeg(ts, JPEG)
        w.poses(ts, poses)
        for j, p in enumerate(PARTS):
            w.status(ts, p, "tracking", 0.9 - 0.1 * j, {"iters": i, "err_px": np.float32(1.5)})
        w.annotations(ts, points=[
            {"points": [[32, 24], [40, 24], [32, 24], [32, 16]], "type": "line_list",
             "colors": [(1, 0, 0), (1, 0, 0), (0, 1, 0), (0, 1, 0)]},
            {"points": [[10, 10], [20, 10], [20, 20], [10, 20]], "type": "line_loop", "color": (1, 1, 0, 1)}],
            circles=[{"center": (32, 24), "diameter": 4}], texts=[{"position": (5, 5), "text": f"f{i}"}])
    return len(times) * (1 + 1 + 2 * 2 + 1) + 2  # image, tf, pose+status per part, annotations; calib, meshes


EXPECTED = {
    "/parts/shaft/pose": "foxglove.PoseInFrame", "/parts/jaw/pose": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransforms", "/parts/shaft/status": "surftrack.PartStatus",
    "/parts/jaw/status": "surftrack.PartStatus", "/camera/calibration": "foxglove.CameraCalibration",
    "/camera/image": "foxglove.CompressedImage", "/camera/annotations": "foxglove.ImageAnnotations",
    "/parts/meshes": "foxglove.SceneUpdate",
}


def stamp_ns(ts):
    return ts["sec"] * 1_000_000_000 + ts["nsec"]


def message_stamps(topic, msg):
    """Every timestamp inside a message."""
    if topic == "/tf":
        return [stamp_ns(t["timestamp"]) for t in msg["transforms"]]
    if topic == "/camera/annotations":
        return [stamp_ns(a["timestamp"]) for k in ("points", "circles", "texts") for a in msg[k]]
    if topic == "/parts/meshes":
        return [stamp_ns(e["timestamp"]) for e in msg["entities"]]
    return [stamp_ns(msg["timestamp"])]


def read_all(path):
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        msgs = [(s, c, m, json.loads(m.data)) for s, c, m in reader.iter_messages(log_time_order=True)]
    return msgs


def check_quat(qd, R):
    q = np.array([qd["x"], qd["y"], qd["z"], qd["w"]])
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-9)
    assert np.allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-9)


def test_full_run(tmp_path):
    path = tmp_path / "run.mcap"
    meta = {"video": "clip.mp4", "model": "ckpt.pt", "fps": 30}
    with TrackWriter(path, meta) as w:
        n = write_frames(w, TIMES)
    assert w.closed

    msgs = read_all(path)
    assert len(msgs) == n
    assert {c.topic for _, c, _, _ in msgs} == set(EXPECTED)
    frame_ns = {int(round(t * 1e9)) for t in TIMES}
    for schema, channel, m, d in msgs:
        assert schema.name == EXPECTED[channel.topic]
        assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
        js = json.loads(schema.data)
        assert js["type"] == "object" and set(js["properties"]) >= set(d)
        assert m.log_time == m.publish_time
        assert m.log_time in frame_ns
        stamps = message_stamps(channel.topic, d)
        assert stamps and all(s == m.log_time for s in stamps)

    by_time = {}
    for _, c, m, d in msgs:
        by_time.setdefault(m.log_time, {}).setdefault(c.topic, []).append(d)
    for i, ts in enumerate(TIMES):
        frame = by_time[int(round(ts * 1e9))]
        assert len(frame["/tf"]) == 1  # one batched FrameTransforms per frame
        tfs = {t["child_frame_id"]: t for t in frame["/tf"][0]["transforms"]}
        assert set(tfs) == set(PARTS)
        for j, p in enumerate(PARTS):
            R, t_mm = part_pose(i, j)
            pose = frame[f"/parts/{p}/pose"][0]
            assert pose["frame_id"] == "camera"
            pos = pose["pose"]["position"]
            assert np.allclose([pos["x"], pos["y"], pos["z"]], t_mm / 1000.0, atol=1e-12)
            check_quat(pose["pose"]["orientation"], R)
            tf = tfs[p]
            assert tf["parent_frame_id"] == "camera"
            tr = tf["translation"]
            assert np.allclose([tr["x"], tr["y"], tr["z"]], t_mm / 1000.0, atol=1e-12)
            check_quat(tf["rotation"], R)
            st = frame[f"/parts/{p}/status"][0]
            assert st["part"] == p and st["status"] == "tracking"
            assert st["extra"] == {"iters": i, "err_px": 1.5}
        img = frame["/camera/image"][0]
        assert img["format"] == "jpeg" and base64.b64decode(img["data"]) == JPEG
        ann = frame["/camera/annotations"][0]
        assert [a["type"] for a in ann["points"]] == [4, 2]
        assert ann["texts"][0]["text"] == f"f{i}"

    first = by_time[0]
    cal = first["/camera/calibration"][0]
    assert cal["K"] == K.reshape(-1).tolist() and len(cal["P"]) == 12 and len(cal["R"]) == 9
    assert (cal["width"], cal["height"], cal["distortion_model"]) == (64, 48, "plumb_bob")
    ents = {e["id"]: e for e in first["/parts/meshes"][0]["entities"]}
    assert set(ents) == set(PARTS)
    for p, e in ents.items():
        assert e["frame_id"] == p and e["frame_locked"] is True
        tri = e["triangles"][0]
        assert max(pt["x"] for pt in tri["points"]) == pytest.approx(0.010)  # 10 mm -> 0.01 m
        assert len(tri["indices"]) == 12

    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        metas = list(reader.iter_metadata())
        summary = reader.get_summary()
    assert [m.name for m in metas] == ["surftrack"]
    assert metas[0].metadata == {"video": "clip.mp4", "model": "ckpt.pt", "fps": "30"}
    stats = summary.statistics
    assert stats.message_count == n
    assert stats.channel_count == len(EXPECTED) and stats.schema_count == len(set(EXPECTED.values()))
    assert stats.metadata_count == 1
    per_channel = {summary.channels[cid].topic: cnt for cid, cnt in stats.channel_message_counts.items()}
    assert per_channel["/tf"] == len(TIMES) and per_channel["/parts/meshes"] == 1
    assert per_channel["/parts/jaw/pose"] == len(TIMES)
    assert stats.message_start_time == 0 and stats.message_end_time == int(round(TIMES[-1] * 1e9))


def test_interrupted_run_leaves_readable_file(tmp_path):
    path = tmp_path / "crash.mcap"
    with pytest.raises(RuntimeError, match="boom"):
        with TrackWriter(path, {"run": "crash"}) as w:
            n = write_frames(w, TIMES[:2])
            raise RuntimeError("boom")
    assert w.closed
    msgs = read_all(path)
    assert len(msgs) == n
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary().statistics.message_count == n
        assert [m.name for m in reader.iter_metadata()] == ["surftrack"]
    with pytest.raises(ValueError, match="closed"):
        w.image_jpeg(5.0, JPEG)
    w.close()  # idempotent


def test_unwritable_path_names_the_path(tmp_path):
    bad = tmp_path / "no_such_dir" / "out.mcap"
    with pytest.raises(OSError, match="no_such_dir"):
        TrackWriter(bad, {})
    with pytest.raises(OSError, match=str(tmp_path.name)):
        TrackWriter(tmp_path, {})  # a directory


def test_bad_inputs(tmp_path):
    with TrackWriter(tmp_path / "x.mcap", {}) as w:
        with pytest.raises(ValueError):
            w.pose("a/b", 0.0, np.eye(3), [0, 0, 0])
        with pytest.raises(ValueError):
            w.pose("a", -1.0, np.eye(3), [0, 0, 0])
        with pytest.raises(ValueError):
            w.pose("a", 0.0, np.eye(3), [0, 0])


def test_status_json_is_strict(tmp_path):
    """JSON has no NaN or infinity (strict readers such as Foxglove's reject them): non-finite extras are
    written as null, a non-finite confidence is refused."""
    path = tmp_path / "s.mcap"
    with TrackWriter(path, {}) as w:
        w.status(0.0, "jaw", "tracking", 0.5, {"rms_px": float("inf"), "d": [1.0, float("nan")], "n": 3})
        with pytest.raises(ValueError, match="confidence"):
            w.status(0.1, "jaw", "tracking", float("nan"))
    with open(path, "rb") as f:
        (_, _, msg), = list(make_reader(f).iter_messages(topics=["/parts/jaw/status"]))
    doc = json.loads(msg.data, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert doc["extra"] == {"rms_px": None, "d": [1.0, None], "n": 3} and doc["confidence"] == 0.5

"""Synthetic clips (``surftrack.synth.clip``).

Every check recomputes what it tests from the written files (``camera.json``, the ``gt.json`` poses and
joints, the instrument models) and the decoded video, never from the generator's internals. Where a
check needs to know which pixels show an instrument it renders the ground-truth poses again in a fresh
renderer holding only the instruments (no tissue; the renderer itself is checked against ray casting
in test_render.py).
"""

import json

import cv2
import numpy as np
import pytest

from surftrack.geometry import PinholeCamera
from surftrack.instruments import JointState, load_instrument, rcm_base_pose
from surftrack.io.video import read_video_frames
from surftrack.render import Renderer, add_instrument
from surftrack.synth.clip import ClipConfig, make_clip
from surftrack.synth.detections import load_detections

W, H, FPS = 320, 256, 15.0
NOISELESS = {"center_std": 0.0, "scale_std": 0.0, "miss_prob": 0.0, "false_prob": 0.0,
             "score_range": [1.0, 1.0], "min_visible_px": 1}
CFG = ClipConfig(seconds=1.5, fps=FPS, width=W, height=H, detection_noise=NOISELESS)
SEED = 3
MARGIN_PX = 20


def _pose(rec):
    T = np.eye(4)
    T[:3, :3] = np.asarray(rec["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
    T[:3, 3] = rec["cam_t_m2c"]
    return T


def _rerender(gt, camera):
    """Instrument-only renders of the gt.json poses: per frame the instance image, the in-image amodal
    masks and padded amodal pixel counts per (instrument_index, part), and the renderer ids per tool."""
    names = {}
    for rec in gt["frames"]["0"]["gt"]:
        names[rec["instrument_index"]] = rec["instrument"]
    r = Renderer(camera.width, camera.height)
    handles = {}
    for k in sorted(names):
        inst = load_instrument(names[k])
        like = next((h for j, h in handles.items() if names[j] == names[k]), None)
        handles[k] = add_instrument(r, inst, like=like)
    pad = max(camera.width, camera.height) // 2
    out = []
    try:
        for i in range(len(gt["frames"])):
            part_poses = {k: {} for k in handles}
            for rec in gt["frames"][str(i)]["gt"]:
                part_poses[rec["instrument_index"]][rec["part"]] = _pose(rec)
            poses = {}
            for k, h in handles.items():
                poses.update(h.poses(part_poses[k]))
            res = r.render(camera, poses, modalities={"instance", "amodal"}, amodal_pad=pad)
            amodal = {(k, p): res.amodal_in_image(iid) for k, h in handles.items() for p, iid in h.parts.items()}
            count_all = {(k, p): int(res.amodal[iid].sum()) for k, h in handles.items() for p, iid in h.parts.items()}
            out.append({"instance": res.instance, "amodal": amodal, "count_all": count_all})
    finally:
        r.release()
    ids = {k: np.array(sorted(set(h.parts.values()) | {i for _, i in h.attachments})) for k, h in handles.items()}
    roots = {k: h.instrument.part_names[0] for k, h in handles.items()}
    return out, ids, roots


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    out = tmp_path_factory.mktemp("clip")
    summary = make_clip(out, "lnd", CFG, seed=SEED)
    gt = json.loads((out / "gt.json").read_text())
    cam_doc = json.loads((out / "camera.json").read_text())
    camera = PinholeCamera.from_dict(cam_doc)
    frames = list(read_video_frames(out / "video.mp4"))
    renders, ids, roots = _rerender(gt, camera)
    return dict(out=out, summary=summary, gt=gt, cam_doc=cam_doc, camera=camera, frames=frames,
                renders=renders, ids=ids, roots=roots)


def test_files_and_camera(clip):
    out, doc = clip["out"], clip["cam_doc"]
    for name in ("video.mp4", "camera.json", "gt.json", "det.json"):
        assert (out / name).is_file(), name
    assert set(doc) == {"K", "width", "height", "dist"} and doc["dist"] == []
    assert (doc["width"], doc["height"]) == (W, H)
    fx = 0.5 * W / np.tan(np.radians(CFG.hfov_deg) / 2)
    np.testing.assert_allclose(np.asarray(doc["K"]), [[fx, 0, (W - 1) / 2], [0, fx, (H - 1) / 2], [0, 0, 1]])
    assert clip["summary"]["frames"] == CFG.n_frames


def test_video_frames_and_timestamps(clip):
    frames, gt = clip["frames"], clip["gt"]
    n = CFG.n_frames
    assert len(frames) == n == len(gt["frames"])
    times = np.array([t for t, _ in frames])
    np.testing.assert_allclose(times, np.arange(n) / FPS, atol=1e-4)
    assert all(f.shape == (H, W, 3) and f.dtype == np.uint8 for _, f in frames)
    np.testing.assert_allclose([gt["frames"][str(i)]["time"] for i in range(n)], np.arange(n) / FPS, atol=1e-9)
    assert gt["fps"] == FPS


def test_gt_poses_match_video_pixels(clip):
    """The camera, the tissue and the lights are fixed in a clip, so wherever no instrument is, a pixel
    shows the same tissue in every frame (up to sensor noise and compression). Estimate that static
    background per pixel as the median over the frames whose re-rendered instrument silhouettes (gt.json
    poses, dilated) leave the pixel free. Then, in every frame: a ring of pixels just outside the
    re-rendered silhouette must match the background (no instrument pixels the gt misses, so the poses
    are not shifted or from another frame), and pixels well inside it must differ from the background
    (the instrument really is there)."""
    frames = np.stack([f for _, f in clip["frames"]]).astype(np.float32)
    masks = np.stack([r["instance"] > 0 for r in clip["renders"]])
    disk = lambda r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))  # noqa: E731
    near = np.stack([cv2.dilate(m.astype(np.uint8), disk(3)) > 0 for m in masks])
    free = np.where(near[..., None], np.nan, frames)
    valid = (~near).sum(0) >= 3
    background = np.nanmedian(np.where(valid[None, ..., None], free, 0.0), axis=0)
    diff = np.abs(frames - background[None]).mean(-1)
    ring_bad, ring_n, inner_diff, inner_n = 0, 0, 0, 0
    for i, m in enumerate(masks):
        ring = (cv2.dilate(m.astype(np.uint8), disk(10)) > 0) & ~near[i] & valid
        inner = (cv2.erode(m.astype(np.uint8), disk(2)) > 0) & valid
        ring_bad += int((diff[i][ring] > 15).sum())
        ring_n += int(ring.sum())
        inner_diff += int((diff[i][inner] > 15).sum())
        inner_n += int(inner.sum())
        if ring.sum() > 50:
            assert (diff[i][ring] > 15).mean() < 0.05, f"frame {i}: instrument pixels outside the gt silhouette"
    assert ring_n > 1000 and inner_n > 1000, "the check must see a fair number of pixels"
    assert ring_bad / ring_n < 0.01
    assert inner_diff / inner_n > 0.8, "pixels inside the gt silhouettes look like the static background"


def test_shaft_passes_through_trocar_and_kinematics(clip):
    """Shaft axis (origin + z of the root part) within 0.1 mm of the trocar on every frame; the trocar is
    fixed per tool; and all part poses follow from the trocar, the shaft origin and joints_deg."""
    gt = clip["gt"]
    trocars = {}
    for i in range(len(gt["frames"])):
        recs = gt["frames"][str(i)]["gt"]
        by_tool = {}
        for rec in recs:
            by_tool.setdefault(rec["instrument_index"], []).append(rec)
        for k, tool in by_tool.items():
            inst = load_instrument(tool[0]["instrument"])
            root = next(r for r in tool if r["part"] == inst.part_names[0])
            T = _pose(root)
            trocar = np.asarray(root["trocar_mm"])
            trocars.setdefault(k, trocar)
            np.testing.assert_allclose(trocar, trocars[k], atol=1e-9)
            o, z = T[:3, 3], T[:3, 2]
            dist = np.linalg.norm(np.cross(trocar - o, z))
            assert dist < 0.1, f"frame {i} tool {k}: shaft misses the trocar by {dist:.3f} mm"
            assert (o - trocar) @ z > 0, "the shaft points from the trocar towards the tip"
            assert len({json.dumps(r["joints_deg"], sort_keys=True) for r in tool}) == 1
            q = JointState.from_degrees(**tool[0]["joints_deg"])
            poses = inst.forward(rcm_base_pose(trocar, o), q)
            for r in tool:
                np.testing.assert_allclose(_pose(r), poses[r["part"]], atol=1e-6)


def test_joints_within_limits(clip):
    gt = clip["gt"]
    seen = set()
    for i in range(len(gt["frames"])):
        for rec in gt["frames"][str(i)]["gt"]:
            inst = load_instrument(rec["instrument"])
            q = JointState.from_degrees(**rec["joints_deg"])
            assert inst.limits.contains(q, tol=1e-6), (i, rec["instrument"], rec["joints_deg"])
            assert -1e-6 <= rec["joints_deg"]["opening"] <= 60 + 1e-6
            seen.add(rec["instrument_index"])
    assert seen == {0, 1}


def test_gt_records_complete_and_consistent(clip):
    """Every part of every tool on every frame; obj ids and part ids agree with the tables; pixel counts
    agree with the instrument-only re-render (tissue can only hide pixels, never add any)."""
    gt, renders = clip["gt"], clip["renders"]
    expected = {(k, p) for k, name in ((0, "large_needle_driver"), (1, "cadiere_forceps"))
                for p in load_instrument(name).part_names}
    for i, r in enumerate(renders):
        recs = gt["frames"][str(i)]["gt"]
        assert {(rec["instrument_index"], rec["part"]) for rec in recs} == expected
        for rec in recs:
            key = (rec["instrument_index"], rec["part"])
            assert gt["models"][str(rec["obj_id"])] == {"instrument": rec["instrument"], "part": rec["part"]}
            assert gt["parts"][str(rec["part_id"])]["part"] == rec["part"]
            assert gt["parts"][str(rec["part_id"])]["instrument"] == rec["instrument"]
            assert abs(rec["px_count_all"] - r["count_all"][key]) <= 2 + 0.005 * r["count_all"][key]
            iid_pixels = r["amodal"][key]
            assert rec["px_count_visib"] <= iid_pixels.sum() + 2
            if rec["px_count_visib"] == 0:
                assert rec["bbox_visib"] == [-1, -1, -1, -1]
            else:
                x, y, w, h = rec["bbox_visib"]
                assert w >= 0 and h >= 0 and x >= 0 and y >= 0 and x + w < W and y + h < H
                # The visible pixels lie where the part's silhouette is.
                assert iid_pixels[y:y + h + 1, x:x + w + 1].any()


def test_det_json_valid_and_boxes_in_edge_convention(clip):
    """det.json validates; with a noiseless detector its boxes are the gt visible boxes converted from
    BOP pixel-index boxes (w = xmax - xmin) to pixel-edge boxes: (x, y, w + 1, h + 1)."""
    det = load_detections(clip["out"] / "det.json")
    gt = clip["gt"]
    assert det["image_size"] == [W, H]
    assert det["parts"] == gt["parts"]
    assert [f["index"] for f in det["frames"]] == list(range(CFG.n_frames))
    np.testing.assert_allclose([f["time"] for f in det["frames"]], np.arange(CFG.n_frames) / FPS, atol=1e-9)
    for f in det["frames"]:
        boxes = {d["part_id"]: d["bbox"] for d in f["detections"]}
        assert len(boxes) == len(f["detections"])
        want = {rec["part_id"]: rec["bbox_visib"] for rec in gt["frames"][str(f["index"])]["gt"]
                if rec["px_count_visib"] > 0}
        assert set(boxes) == set(want)
        for pid, (x, y, w, h) in want.items():
            assert boxes[pid] == [x, y, w + 1, h + 1]


def test_main_tool_leaves_and_reenters(clip):
    renders, roots = clip["renders"], clip["roots"]
    in_view = np.array([any(r["amodal"][(0, p)].any() for (k, p) in r["amodal"] if k == 0 and p != roots[0])
                        for r in renders])
    out = np.flatnonzero(~in_view)
    assert len(out) >= 2, "the main tool's wrist and jaws never leave the image"
    assert in_view[: out[0]].any() and in_view[out[-1]:].any(), "the main tool must be seen before and after"
    assert in_view.sum() >= len(renders) // 2


def test_second_tool_occludes_main_tool(clip):
    renders, ids, roots, gt = clip["renders"], clip["ids"], clip["roots"], clip["gt"]
    hits = 0
    for i, r in enumerate(renders):
        by_second = np.isin(r["instance"], ids[1])
        main_in_view = any(r["amodal"][(0, p)].any() for (k, p) in r["amodal"] if k == 0 and p != roots[0])
        for rec in gt["frames"][str(i)]["gt"]:
            if rec["instrument_index"] != 0:
                continue
            hidden = int((r["amodal"][(0, rec["part"])] & by_second).sum())
            if main_in_view and hidden >= MARGIN_PX:
                hits += 1
                assert rec["px_count_visib"] <= rec["px_count_all"] - MARGIN_PX
    assert hits >= 1, "the second tool never hides part of the main tool"


def test_deterministic(clip, tmp_path):
    """Same seed -> identical gt.json and video frames (the detection noise has its own generator, so it
    does not change the ground truth); the default noisy detector's det.json validates."""
    cfg = ClipConfig(seconds=CFG.seconds, fps=FPS, width=W, height=H)
    make_clip(tmp_path, "large_needle_driver", cfg, seed=SEED)
    a = json.loads((clip["out"] / "gt.json").read_text())
    b = json.loads((tmp_path / "gt.json").read_text())
    a.pop("config"), b.pop("config")
    assert a == b
    assert (clip["out"] / "camera.json").read_text() == (tmp_path / "camera.json").read_text()
    frames = [f for _, f in read_video_frames(tmp_path / "video.mp4")]
    assert all(np.array_equal(f, g) for f, (_, g) in zip(frames, clip["frames"]))
    det = load_detections(tmp_path / "det.json")
    assert sum(len(f["detections"]) for f in det["frames"]) > 0


def test_single_tool_clip(tmp_path):
    cfg = ClipConfig(seconds=0.6, fps=10, width=W, height=H, second_instrument=None, leave_view=False)
    s = make_clip(tmp_path, "scissors", cfg, seed=1)
    gt = json.loads((tmp_path / "gt.json").read_text())
    assert s["frames"] == 6 and len(gt["frames"]) == 6
    assert {rec["instrument_index"] for f in gt["frames"].values() for rec in f["gt"]} == {0}
    assert all(v > 0 for v in s["visible_frames"].values())
    load_detections(tmp_path / "det.json")


def test_a_clip_stopped_part_way_leaves_no_earlier_truth_beside_its_video(tmp_path, monkeypatch):
    import surftrack.synth.clip as clip_module

    cfg = ClipConfig(seconds=0.4, fps=10, width=W, height=H, second_instrument=None, leave_view=False)
    make_clip(tmp_path, "scissors", cfg, seed=1)
    assert (tmp_path / "gt.json").is_file()

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):  # the run killed while it renders the second clip
        raise Stop

    monkeypatch.setattr(clip_module, "apply_effects", stop)
    with pytest.raises(Stop):
        make_clip(tmp_path, "scissors", cfg, seed=2)
    assert not any((tmp_path / f).exists() for f in ("camera.json", "gt.json", "det.json"))


def test_the_roll_starts_where_asked_and_wanders_as_far_as_asked(tmp_path):
    """A tool rolled away from the camera (the jaws opening away from it) for a whole clip: what the
    estimator's roll twin needs to be measured on (surftrack.instruments.twin)."""
    cfg = ClipConfig(seconds=0.5, fps=10, width=W, height=H, second_instrument=None, leave_view=False,
                     roll_deg=(150, 170), roll_swing_deg=(0, 0))
    make_clip(tmp_path, "lnd", cfg, seed=2)
    gt = json.loads((tmp_path / "gt.json").read_text())
    rolls = {round(rec["joints_deg"]["roll"], 6) for f in gt["frames"].values() for rec in f["gt"]}
    assert len(rolls) == 1 and 150 <= rolls.pop() <= 170
    assert ClipConfig.from_dict(gt["config"]) == cfg


def test_config_validation():
    for bad in ({"roll_deg": (10, -10)}, {"roll_deg": (0, 400)}, {"roll_swing_deg": (-5, 5)}, {"roll_deg": 30}):
        with pytest.raises(ValueError, match="roll"):
            ClipConfig.from_dict(bad)
    assert ClipConfig.from_dict({"seconds": 2, "second_instrument": None}).second_instrument is None
    assert ClipConfig.from_dict(ClipConfig().to_dict()) == ClipConfig()
    with pytest.raises(ValueError, match="unknown clip config"):
        ClipConfig.from_dict({"secs": 2})
    with pytest.raises(ValueError, match="even"):
        ClipConfig(width=321)
    with pytest.raises(ValueError, match="unknown camera effect"):
        ClipConfig(effects={"blurr": 1})
    with pytest.raises(ValueError, match="unknown detection noise"):
        ClipConfig(detection_noise={"miss": 0.1})
    with pytest.raises(ValueError, match="fps"):
        ClipConfig(fps=0)

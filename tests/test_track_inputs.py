"""Every bad input of the main command: one line on stderr naming the file and the problem, exit code 2,
no traceback, and no output left half-written."""

import json
import shutil

import pytest
from mcap.reader import make_reader

from surftrack.cli import EXIT_BATCH_INCOMPLETE, main


def _run(capsys, args):
    rc = main(args)
    err = capsys.readouterr().err
    return rc, err


def _base(clip, tiny_ckpt, tmp_path, **over):
    a = {"video": str(clip / "video.mp4"), "--boxes": str(clip / "det.json"), "--camera": str(clip / "camera.json"),
         "--model": str(tiny_ckpt), "-o": str(tmp_path / "out.mcap")}
    a.update(over)
    args = [a.pop("video")]
    for k, v in a.items():
        args += [k, v]
    return args + ["--quiet"]


def _check(capsys, args, *needles):
    rc, err = _run(capsys, args)
    assert rc == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("surftrack: error: "), err
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def _det(clip):
    return json.loads((clip / "det.json").read_text())


def test_missing_corrupt_and_truncated_video(clip, tiny_ckpt, tmp_path, capsys):
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, video=str(tmp_path / "nope.mp4")), "nope.mp4", "no such video")
    bad = tmp_path / "corrupt.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40)
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, video=str(bad)), "corrupt.mp4")
    data = (clip / "video.mp4").read_bytes()
    cut = tmp_path / "truncated.mp4"
    cut.write_bytes(data[: len(data) // 2])
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, video=str(cut)), "truncated.mp4")


def test_malformed_and_mismatched_detections(clip, tiny_ckpt, tmp_path, capsys):
    p = tmp_path / "det.json"
    p.write_text("{not json")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "invalid JSON")
    p.write_text(json.dumps({"hello": 1}))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "not a detection file")
    d = _det(clip)
    d["image_size"] = [640, 480]
    p.write_text(json.dumps(d))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "640x480", "320x256")
    d = _det(clip)
    for f in d["frames"]:  # boxes made for a video at half the frame rate
        f["time"] = 2 * f["time"]
    p.write_text(json.dumps(d))
    out = tmp_path / "partial.mcap"
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p), "-o": str(out)}), "det.json", "frame 1")
    from mcap.reader import make_reader

    with open(out, "rb") as f:  # what was written before the error is a complete, readable file
        assert make_reader(f).get_summary() is not None


def test_bad_boxes(clip, tiny_ckpt, tmp_path, capsys):
    p = tmp_path / "det.json"
    d = _det(clip)
    frame = next(f for f in d["frames"] if f["detections"])
    frame["detections"][0]["bbox"] = [300.0, 10.0, 50.0, 20.0]  # extends past x = 320
    p.write_text(json.dumps(d))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "outside")
    d = _det(clip)
    frame = next(f for f in d["frames"] if f["detections"])
    frame["detections"][0]["part_id"] = 99
    p.write_text(json.dumps(d))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "99")
    d = _det(clip)
    lnd_pid = next(k for k, v in d["parts"].items() if v["instrument"] == "large_needle_driver")
    d["parts"][lnd_pid]["part"] = "jawz"
    p.write_text(json.dumps(d))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "jawz")
    d = _det(clip)
    lnd = [k for k, v in d["parts"].items() if v["instrument"] == "large_needle_driver"]
    d["parts"][lnd[1]] = dict(d["parts"][lnd[0]])  # two ids for the same part
    p.write_text(json.dumps(d))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "same part")
    d = _det(clip)
    for v in d["parts"].values():
        v["instrument"] = "harmonic_scalpel"
    p.write_text(json.dumps(d))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "none of its parts")
    d = _det(clip)
    for f in d["frames"]:
        f["detections"] = []
    p.write_text(json.dumps(d))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "det.json", "no boxes")


def test_wrong_intrinsics(clip, tiny_ckpt, tmp_path, capsys):
    cam = json.loads((clip / "camera.json").read_text())
    p = tmp_path / "camera.json"
    p.write_text(json.dumps(dict(cam, width=640, height=512)))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--camera": str(p)}), "camera.json", "640x512")
    K = [row[:] for row in cam["K"]]
    K[0][2] = 900.0
    p.write_text(json.dumps(dict(cam, K=K)))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--camera": str(p)}), "camera.json", "principal point")
    K = [row[:] for row in cam["K"]]
    K[0][0] = -5.0
    p.write_text(json.dumps(dict(cam, K=K)))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--camera": str(p)}), "camera.json", "fx")
    K = [row[:] for row in cam["K"]]
    K[0][1] = 0.5
    p.write_text(json.dumps(dict(cam, K=K)))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--camera": str(p)}), "camera.json", "skew")
    p.write_text(json.dumps(dict(cam, K=[[1, 2], [3, 4]])))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--camera": str(p)}), "camera.json", "3x3")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--camera": str(tmp_path / "none.json")}), "none.json")


def test_unwritable_output_and_bad_options(clip, tiny_ckpt, tmp_path, capsys):
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"-o": str(tmp_path / "missing_dir" / "x.mcap")}), "x.mcap")
    d = tmp_path / "a_dir.mcap"
    d.mkdir()
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"-o": str(d)}), "a_dir.mcap")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--model": str(tmp_path / "m.pt")}), "m.pt")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--start", "2", "--end", "1"], "--end")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--start", "-1"], "--start -1")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"-o": str(tmp_path / "out.txt")}), "out.txt", ".mcap")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--joints-csv", str(tmp_path / "nodir" / "j.csv")],
           "j.csv", "no folder")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--joints-csv", str(tmp_path / "j.txt")], "j.txt", ".csv")
    (tmp_path / "tum_file").write_text("")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--export-tum", str(tmp_path / "tum_file")], "tum_file")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--export-tum", str(tmp_path / "out.mcap")],
           "--export-tum would overwrite the MCAP")
    assert not (tmp_path / "out.mcap").exists()  # every output checked before the MCAP is opened
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--config", "no_such_config"], "no_such_config",
           "every_frame")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--keyframe-every", "0"], "--keyframe-every")
    cfg = tmp_path / "t.yaml"
    cfg.write_text("keyframe_evry: 3\n")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--config", str(cfg)], "t.yaml", "keyframe_evry")


def test_outputs_never_overwrite_inputs_or_the_last_run(clip, tiny_ckpt, tmp_path, capsys):
    """An output named like an input is refused before anything is opened (the input stays whole), and so
    is an overlay the writer would refuse, before the previous run's MCAP is touched; a malformed YAML
    config is one line too."""
    video = tmp_path / "clip.mp4"
    shutil.copy(clip / "video.mp4", video)
    size = video.stat().st_size
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, video=str(video)) + ["--overlay", str(video)],
           "clip.mp4", "--overlay would overwrite the input video")
    assert video.stat().st_size == size
    boxes = tmp_path / "det.json"
    shutil.copy(clip / "det.json", boxes)
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(boxes)}) + ["--joints-csv", str(boxes)],
           "--joints-csv would overwrite the boxes")
    assert json.loads(boxes.read_text()) == _det(clip)
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"-o": str(tmp_path / "t.mcap")})
           + ["--overlay", str(tmp_path / "t.mcap")], "t.mcap", "--overlay would overwrite the MCAP")
    last = tmp_path / "out.mcap"
    last.write_bytes(b"the last run")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--overlay", str(tmp_path / "o.avi")], "o.avi", ".mp4")
    assert last.read_bytes() == b"the last run"
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--views", "12"], "--views must be between 1 and 9")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--anchor-views", "0"], "--anchor-views must be between 1 and 9")
    no_fit = tmp_path / "no_fit.yaml"
    no_fit.write_text("kinematic: false\n")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--anchor-views", "3", "--config", str(no_fit)],
           "turns the fit off")
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("preset: [fast\nkeyframe_every: 2\n")
    _check(capsys, _base(clip, tiny_ckpt, tmp_path) + ["--config", str(cfg)], "bad.yaml", "line 2, column 15")


def test_boxes_past_the_last_frame_get_a_note(clip, tiny_ckpt, tmp_path, capsys):
    d = _det(clip)
    n = len(d["frames"])
    dt = d["frames"][1]["time"] - d["frames"][0]["time"]
    for f in d["frames"]:  # numbered from 1, as an ffmpeg frame dump would be (the times follow)
        f["index"] += 1
        f["time"] = f["index"] * dt
    p = tmp_path / "det1.json"
    p.write_text(json.dumps(d))
    rc = main(_base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}))
    out = capsys.readouterr().out
    assert rc == 0
    assert f"boxes for 1 frame(s) after the video's last frame ({n - 1}), from {n}" in out, out


@pytest.mark.xdist_group("ray")  # a folder of videos is a batch on a local Ray (see tests/test_batch.py)
def test_camera_found_beside_the_video_and_folder_of_videos(clip, tiny_ckpt, tmp_path, capsys):
    vids, boxes = tmp_path / "videos", tmp_path / "boxes"
    vids.mkdir()
    boxes.mkdir()
    for name in ("a", "b"):
        shutil.copy(clip / "video.mp4", vids / f"{name}.mp4")
        shutil.copy(clip / "det.json", boxes / f"{name}.json")
    shutil.copy(clip / "camera.json", vids / "camera.json")
    out = tmp_path / "tracks"
    rc = main([str(vids), "--boxes", str(boxes), "--model", str(tiny_ckpt), "-o", str(out), "--quiet",
               "--end", "0.25"])
    assert rc == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["a.mcap", "b.mcap", "manifest.jsonl"]
    with open(out / "a.mcap", "rb") as f:  # --end reaches every video of the folder
        assert make_reader(f).get_summary().statistics.message_end_time == 200_000_000
    (boxes / "b.json").unlink()  # one video's problem no longer stops the folder: it is reported and skipped
    rc = main([str(vids), "--boxes", str(boxes), "--model", str(tiny_ckpt), "-o", str(out), "--quiet"])
    assert rc == EXIT_BATCH_INCOMPLETE and "b.json" in capsys.readouterr().out
    shutil.copy(clip / "video.mp4", vids / "a.mov")
    _check(capsys, [str(vids), "--boxes", str(boxes), "--model", str(tiny_ckpt), "-o", str(out), "--quiet"],
           "a.mov", "a.mcap")


def test_coco_detections_are_accepted(clip, tiny_ckpt, tmp_path, capsys):
    """The same boxes as a COCO file (categories named by instrument and part, frame numbers in the
    image file names) track like det.json."""
    d = _det(clip)
    coco = {"images": [], "annotations": [], "categories": []}
    for pid, p in d["parts"].items():
        coco["categories"].append({"id": int(pid), "name": p["part"], "supercategory": p["instrument"]})
    for f in d["frames"]:
        coco["images"].append({"id": 1000 + f["index"], "file_name": f"frames/frame_{f['index']:06d}.png"})
        for det in f["detections"]:
            coco["annotations"].append({"id": len(coco["annotations"]), "image_id": 1000 + f["index"],
                                        "category_id": det["part_id"], "bbox": det["bbox"], "score": det["score"]})
    p = tmp_path / "coco.json"
    p.write_text(json.dumps(coco))
    out = tmp_path / "coco.mcap"
    rc = main(_base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p), "-o": str(out)}) + ["--end", "0.35"])
    assert rc == 0, capsys.readouterr().err
    from mcap.reader import make_reader

    with open(out, "rb") as f:
        stats = make_reader(f).get_summary().statistics
    assert stats.message_count > 0 and stats.message_end_time == 300_000_000  # frames 0..3 at 10 fps
    del coco["annotations"][0]["bbox"]
    p.write_text(json.dumps(coco))
    _check(capsys, _base(clip, tiny_ckpt, tmp_path, **{"--boxes": str(p)}), "coco.json", "annotations[0]")


def test_interrupted_run_leaves_complete_outputs(clip, tiny_ckpt, tmp_path):
    """Ctrl-C in the middle of a causal run: the MCAP, overlay and TUM files written so far are complete
    (tests/test_stop.py covers a smoothed run, which also writes the frames waiting for their lag)."""
    from mcap.reader import make_reader

    from surftrack.annotate import AnnotateOptions, annotate_video
    from surftrack.track import TrackConfig
    from surftrack.io.tum import read_tum
    from surftrack.io.video import read_video_frames

    def stop(index, time_s, states):
        if index == 4:
            raise KeyboardInterrupt

    opts = AnnotateOptions(model=tiny_ckpt, camera=clip / "camera.json", out=tmp_path / "x.mcap",
                           overlay=tmp_path / "x.mp4", export_tum=tmp_path / "tum", progress=False,
                           config=TrackConfig(smooth_lag_s=0.0))
    with pytest.raises(KeyboardInterrupt):
        annotate_video(clip / "video.mp4", clip / "det.json", opts, on_frame=stop)
    with open(tmp_path / "x.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary.statistics.message_end_time == 400_000_000
    assert len(list(read_video_frames(tmp_path / "x.mp4"))) == 5
    for p in (tmp_path / "tum").glob("*.tum"):
        assert len(read_tum(p)[0]) <= 5


def test_analyze_bad_file(tmp_path, capsys):
    bad = tmp_path / "junk.mcap"
    bad.write_bytes(b"not an mcap file at all")
    _check(capsys, ["analyze", str(bad)], "junk.mcap")
    _check(capsys, ["analyze", str(tmp_path / "missing.mcap")], "missing.mcap")
    _check(capsys, ["analyze", str(bad), "--png", str(bad)], "--png", ".png")
    _check(capsys, ["analyze", str(bad), "--png", str(tmp_path / "junk.png.mcap")], ".png")
    _check(capsys, ["analyze", str(bad), "--png", str(tmp_path / "nodir" / "a.png")], "no folder")


def test_an_error_during_a_smoothed_run_still_writes_every_tracked_frame(clip, tiny_ckpt, tmp_path):
    """An exception in the middle of writing (here from the on_frame hook, as frame 3 is written): the
    frames already let go by the smoother and those still waiting are all written, in order, and the
    MCAP is finished; the error propagates."""
    from surftrack.annotate import AnnotateOptions, annotate_video
    from surftrack.track import Status, TrackConfig

    def fail(index, time_s, states):
        if index == 3:
            raise RuntimeError("boom")

    opts = AnnotateOptions(model=tiny_ckpt, camera=clip / "camera.json", out=tmp_path / "x.mcap", progress=False,
                           config=TrackConfig(smooth_lag_s=0.5), joints=False)
    with pytest.raises(RuntimeError, match="boom"):
        annotate_video(clip / "video.mp4", clip / "det.json", opts, on_frame=fail)
    with open(tmp_path / "x.mcap", "rb") as f:
        reader = make_reader(f)
        times = [m.log_time for _, ch, m in reader.iter_messages() if ch.topic == "/parts/large_needle_driver.0.wrist/status"]
    # frame 3 is written once frame 8 is tracked (a 5-frame lag): frames 0-8 were tracked, all are written
    assert times == [k * 100_000_000 for k in range(9)]
    assert str(Status.LOST) == "lost" and f"{Status.KEYFRAME}" == "keyframe"

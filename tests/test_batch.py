"""``surftrack batch`` (and the main command on a folder) on a real local Ray with 2 CPUs: a bad video is
reported and skipped, the others finish with valid MCAPs, the manifest has a row per video, and a rerun
of the batch processes nothing."""

from __future__ import annotations

import json
import shutil

import pytest
from mcap.reader import make_reader

from surftrack.cli import EXIT_BATCH_INCOMPLETE, main

# each test starts a local Ray of 2 CPUs: two at once on a 2-core machine time out starting up, so they
# share one xdist worker (`make test` runs with --dist loadgroup)
pytestmark = pytest.mark.xdist_group("ray")

def test_batch_skips_a_bad_video_and_reruns_nothing(clip, tiny_ckpt, tmp_path, capsys):
    videos, boxes = tmp_path / "videos", tmp_path / "boxes"
    videos.mkdir()
    boxes.mkdir()
    (videos / "a_bad.mp4").write_text("this is a text file, not a video")
    for stem in ("a_bad", "b_good", "c_good"):
        shutil.copy(clip / "det.json", boxes / f"{stem}.json")
    for stem in ("b_good", "c_good"):
        shutil.copy(clip / "video.mp4", videos / f"{stem}.mp4")
    out = tmp_path / "out"
    args = ["batch", str(videos), "-o", str(out), "--boxes", str(boxes), "--camera", str(clip / "camera.json"),
            "--model", str(tiny_ckpt), "--workers", "2", "--quiet"]
    assert main(args) == EXIT_BATCH_INCOMPLETE
    printed = capsys.readouterr().out
    assert "surftrack batch: 2 of 3 videos finished" in printed
    rows = {json.loads(line)["video"]: json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()}
    assert rows[str(videos / "a_bad.mp4")]["status"] == "failed"
    assert "a_bad.mp4" in rows[str(videos / "a_bad.mp4")]["error"] and rows[str(videos / "a_bad.mp4")]["mcap"] is None
    for stem in ("b_good", "c_good"):
        r = rows[str(videos / f"{stem}.mp4")]
        assert r["status"] == "done" and r["frames"] == 15 and r["fps"] > 0
        with open(out / f"{stem}.mcap", "rb") as f:
            assert make_reader(f).get_summary().statistics.message_end_time == 1_400_000_000
    assert not (out / "a_bad.mcap").exists() and not (out / ".progress").exists()
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("*.mcap")}

    assert main(args) == EXIT_BATCH_INCOMPLETE  # the bad video is still bad; the good ones are not redone
    lines = (out / "manifest.jsonl").read_text().splitlines()[3:]
    assert sorted(json.loads(line)["status"] for line in lines) == ["failed", "skipped", "skipped"]
    for line in lines:  # a skipped video keeps the figures of the run that finished it
        r = json.loads(line)
        if r["status"] == "skipped":
            assert r["frames"] == 15 and r["mcap"] == rows[r["video"]]["mcap"]
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.mcap")} == stamps

    # the main command on a folder is the same batch (every video redone, like the main command on one)
    folder_out = tmp_path / "main_out"
    assert main([str(videos), "-o", str(folder_out), "--boxes", str(boxes), "--camera", str(clip / "camera.json"),
                 "--model", str(tiny_ckpt), "--quiet"]) == EXIT_BATCH_INCOMPLETE
    assert "surftrack batch: 2 of 3 videos finished" in capsys.readouterr().out
    assert sorted(p.name for p in folder_out.glob("*.mcap")) == ["b_good.mcap", "c_good.mcap"]


def test_sigterm_stops_a_batch_with_finished_files(clip, tiny_ckpt, tmp_path):
    """SIGTERM while the first video is tracked: exit 143, every MCAP written is finished, the manifest has
    a row for every video and the videos not started are marked stopped."""
    import signal
    import subprocess
    import sys
    import time

    videos, boxes, out = tmp_path / "videos", tmp_path / "boxes", tmp_path / "out"
    videos.mkdir()
    boxes.mkdir()
    for stem in "abcd":
        shutil.copy(clip / "video.mp4", videos / f"{stem}.mp4")
        shutil.copy(clip / "det.json", boxes / f"{stem}.json")
    proc = subprocess.Popen([sys.executable, "-m", "surftrack.cli", "batch", str(videos), "-o", str(out), "--boxes",
                             str(boxes), "--camera", str(clip / "camera.json"), "--model", str(tiny_ckpt),
                             "--workers", "1", "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list(out.glob("*.mcap")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=180)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "surftrack: stopped by SIGTERM"
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert sorted(r["video"] for r in rows) == sorted(str(videos / f"{s}.mp4") for s in "abcd")
    assert {r["status"] for r in rows} <= {"done", "stopped"} and any(r["status"] == "stopped" for r in rows)
    for p in out.glob("*.mcap"):
        with open(p, "rb") as f:
            assert make_reader(f).get_summary() is not None, p
    assert not (out / ".stop").exists()


def test_progress_counts_the_frames_of_running_videos(tmp_path):
    from surftrack.batch import BatchJob, _frames_running, _progress_file

    stop = tmp_path / ".stop"
    jobs = [BatchJob(tmp_path / f"{s}.mp4", None, None, tmp_path / f"{s}.mcap") for s in "abc"]
    (tmp_path / ".progress").mkdir()
    _progress_file(stop, jobs[0]).write_text("30")
    _progress_file(stop, jobs[1]).write_text("")  # being written
    assert _frames_running(stop, jobs) == 30  # c has not reported yet


@pytest.mark.slow
def test_batch_joins_a_running_cluster(clip, tiny_ckpt, tmp_path):
    """The README's cluster recipe on one machine: `ray start --head`, then `surftrack batch --address auto`.
    Slow and kept out of `make test`: `ray stop` ends every Ray process of the user, which would cut the
    local Ray of a test running beside it."""
    import subprocess
    import sys
    from pathlib import Path

    ray_cli = Path(sys.executable).with_name("ray")
    videos, boxes, out = tmp_path / "videos", tmp_path / "boxes", tmp_path / "out"
    videos.mkdir()
    boxes.mkdir()
    shutil.copy(clip / "video.mp4", videos / "a.mp4")
    shutil.copy(clip / "det.json", boxes / "a.json")
    subprocess.run([str(ray_cli), "start", "--head", "--num-cpus", "2", "--disable-usage-stats",
                    "--include-dashboard=false"], check=True, capture_output=True, timeout=180)
    try:
        r = subprocess.run([sys.executable, "-m", "surftrack.cli", "batch", str(videos), "--boxes", str(boxes),
                            "--camera", str(clip / "camera.json"), "--model", str(tiny_ckpt), "-o", str(out),
                            "--address", "auto", "--quiet"], capture_output=True, text=True, timeout=300)
    finally:
        subprocess.run([str(ray_cli), "stop"], capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "1 of 1 videos finished" in r.stdout
    with open(out / "a.mcap", "rb") as f:
        assert make_reader(f).get_summary().statistics.message_end_time == 1_400_000_000

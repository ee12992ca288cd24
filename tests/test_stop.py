"""Every way a run ends: SIGTERM and SIGHUP finalise the outputs as Ctrl-C does, with exit codes 143 and
129; inputs that would leave nothing useful are refused before any output is opened."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from surftrack.cli import main

# Runs the real command in a child process that sends itself ``signum`` after frame 4 has been written.
DRIVER = """
import os, sys
import surftrack.annotate as annotate

real = annotate.annotate_video

def signalling(video, boxes, opts=None, on_frame=None):
    def at(index, time_s, states):
        if index == 4:
            os.kill(os.getpid(), {signum})
    return real(video, boxes, opts, on_frame=at)

annotate.annotate_video = signalling
from surftrack.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("signum,causal", [(signal.SIGTERM, True), (signal.SIGHUP, True), (signal.SIGTERM, False)])
def test_stop_signal_finalises_every_output(clip, tiny_ckpt, tmp_path, signum, causal):
    """The signal arrives as frame 4 is written. Causal: frames 0-4 were tracked and are written.
    Smoothed: frame 4 waited for the clip's last frame (1 s of future), so all 15 tracked frames are
    written, the last ones smoothed with what there was."""
    from mcap.reader import make_reader

    from surftrack.io.joints_csv import JOINT_CSV_COLUMNS
    from surftrack.io.tum import read_tum
    from surftrack.io.video import read_video_frames

    out = tmp_path / "x.mcap"
    cmd = [sys.executable, "-c", DRIVER.format(signum=int(signum)), "track", str(clip / "video.mp4"),
           "--boxes", str(clip / "det.json"), "--camera", str(clip / "camera.json"), "--model", str(tiny_ckpt),
           "-o", str(out), "--overlay", str(tmp_path / "x.mp4"), "--export-tum", str(tmp_path / "tum"),
           "--joints-csv", str(tmp_path / "j.csv"), "--quiet"] + (["--causal"] if causal else [])
    n = 5 if causal else 15
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 128 + signum, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"surftrack: stopped by {signal.Signals(signum).name} after {n} frames; finalised ")
    assert str(out) in last and "Traceback" not in r.stderr
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()  # needs the footer: a finished file
    assert summary.statistics.message_end_time == (n - 1) * 100_000_000  # frames 0..n-1 at 10 fps
    assert len(list(read_video_frames(tmp_path / "x.mp4"))) == n
    assert (tmp_path / "tum").is_dir()  # a part's file appears with its first pose (the untrained model has few)
    assert all(len(read_tum(p)[0]) <= n for p in (tmp_path / "tum").glob("*.tum"))
    with open(tmp_path / "j.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == JOINT_CSV_COLUMNS and all(float(r[0]) <= (n - 1) / 10 + 1e-9 for r in rows[1:])


def test_start_past_the_end_leaves_no_output(clip, tiny_ckpt, tmp_path, capsys):
    out = tmp_path / "x.mcap"
    assert main(["track", str(clip / "video.mp4"), "--boxes", str(clip / "det.json"), "--model", str(tiny_ckpt),
                 "-o", str(out), "--start", "60", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "video.mp4: --start 60 s is past the end of the video (1.50 s)" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_a_file_that_is_no_checkpoint_gets_no_advice_to_load_code(clip, tmp_path, capsys):
    import torch

    bad = tmp_path / "model.pt"
    torch.save({"fn": json.dumps}, bad)  # a pickle that references code
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint" * 8)
    for model in (bad, junk):
        assert main(["track", str(clip / "video.mp4"), "--boxes", str(clip / "det.json"), "--model", str(model),
                     "-o", str(tmp_path / "x.mcap"), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"surftrack: error: {model}: not a") and len(err.splitlines()) == 1
        assert "weights_only" not in err and "issue" not in err


def test_progress_counts_frames_up_to_end():
    from surftrack.annotate import _frames_to_read
    from surftrack.track.inputs import VideoInfo

    info = VideoInfo(Path("v.mp4"), 320, 256, 30.0, 3000)
    assert _frames_to_read(info, None) == 3000
    assert _frames_to_read(info, 50.0) == 1501  # frames at 0, 1/30, ..., 50 s
    assert _frames_to_read(info, 500.0) == 3000
    assert _frames_to_read(VideoInfo(Path("v.mp4"), 320, 256, 30.0, 0), None) is None


def _cut_mdat(src: Path, dst: Path, keep: float) -> None:
    """Copy an mp4 (moov after mdat, as PyAV writes it) keeping the first ``keep`` of its sample data: the
    index still lists every frame, so decoding fails part of the way through, as in a damaged recording."""
    import struct

    data = src.read_bytes()
    mdat, moov = data.find(b"mdat") - 4, data.find(b"moov") - 4
    assert 0 <= mdat < moov, "expected mdat before moov"
    cut = mdat + int((moov - mdat) * keep)
    out = bytearray(data[:cut] + data[moov:])
    out[mdat:mdat + 4] = struct.pack(">I", cut - mdat)
    dst.write_bytes(bytes(out))


def test_partially_decodable_video_is_tracked_as_far_as_it_decodes(clip, tiny_ckpt, tmp_path, capsys):
    from mcap.reader import make_reader

    from surftrack.cli import EXIT_PARTIAL
    from surftrack.io.video import read_video_frames

    video = tmp_path / "damaged.mp4"
    _cut_mdat(clip / "video.mp4", video, 0.5)
    with pytest.raises(ValueError, match="decoding failed"):
        list(read_video_frames(video))
    out = tmp_path / "x.mcap"
    assert main(["track", str(video), "--boxes", str(clip / "det.json"), "--camera", str(clip / "camera.json"),
                 "--model", str(tiny_ckpt), "-o", str(out), "--overlay", str(tmp_path / "x.mp4"), "--quiet"]) \
        == EXIT_PARTIAL
    cap = capsys.readouterr()
    tracked = int(cap.out.split(f"{video}: ")[1].split(" frames")[0])
    assert 0 < tracked < 15
    assert cap.err.strip().startswith(f"surftrack: partial: {video}: {tracked} of 15 frames, decoding stopped "
                                       f"at t = {(tracked - 1) / 10:.3f} s (")
    with open(out, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_end_time == (tracked - 1) * 100_000_000
    assert len(list(read_video_frames(tmp_path / "x.mp4"))) == tracked

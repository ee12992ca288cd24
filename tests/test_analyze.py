"""Tracking-log summaries (``surftrack.io.analyze``) of MCAP files written by TrackWriter."""

import math

import numpy as np
import pytest
from PIL import Image

from surftrack.io import TrackWriter, analyze_mcap, format_analysis, plot_analysis

FPS = 10.0
N = 21                                        # 2 s
SHAFT_V = np.array([3.0, 4.0, 0.0]) * 4.0     # 20 mm/s
JAW_V = np.array([0.0, -30.0, 40.0])          # 50 mm/s
LOST = {8, 9}                                 # jaw frames reported lost


def write_log(path):
    """Shaft in a straight line at 20 mm/s; jaw at 50 mm/s, lost on frames 8-9 (frame 8 without a pose,
    frame 9 with a pose but status "lost"), jumping 100 mm between frames 9 and 10; jaw opening 20 + 10 sin."""
    R = np.eye(3)
    with TrackWriter(path) as w:
        for i in range(N):
            t = i / FPS
            w.pose("shaft", t, R, np.array([10.0, -5.0, 80.0]) + SHAFT_V * t)
            w.status(t, "shaft", "keyframe" if i % 2 == 0 else "tracking", 0.9,  # both are measured poses
                     {"position_std_mm": [1.0, 2.0, 2.0], "speed_std_mm_s": 1.0 + (i % 2)})
            w.pose("tip", t, R, np.array([10.0 * t**3, 0.0, 70.0]))  # jerk 60 mm/s^3
            jaw = np.array([0.0, 0.0, 60.0]) + JAW_V * t + (100.0 if i >= 10 else 0.0)
            if i != 8:
                w.pose("jaw", t, R, jaw)
            w.status(t, "jaw", "lost" if i in LOST else "tracking", 0.1 if i in LOST else 0.8)
            w.joint_states(t, "large_needle_driver", ["roll", "opening"],
                           [0.0, math.radians(20.0 + 10.0 * math.sin(2 * math.pi * 0.5 * t))])
            w.joint_states(t, "large_needle_driver", ["roll", "opening"], [math.radians(2.0), math.radians(3.0)],
                           kind="joints_std")


def test_straight_line_speed_and_path(tmp_path):
    path = tmp_path / "tracks.mcap"
    write_log(path)
    s = analyze_mcap(path)

    shaft = s["parts"]["shaft"]
    assert shaft["pose_frames"] == N and shaft["tracked_frames"] == N
    assert shaft["t_start_s"] == 0.0 and shaft["t_end_s"] == pytest.approx(2.0)
    assert shaft["path_length_mm"] == pytest.approx(20.0 * 2.0, rel=1e-9)
    assert shaft["mean_speed_mm_s"] == pytest.approx(20.0, rel=1e-9)
    assert shaft["max_speed_mm_s"] == pytest.approx(20.0, rel=1e-9)
    assert shaft["series"]["x_mm"][-1] == pytest.approx(10.0 + 12.0 * 2.0)  # metres in the file, mm here
    assert shaft["rms_jerk_mm_s3"] == pytest.approx(0.0, abs=1e-6) and shaft["position_std_mm"] == pytest.approx(3.0)
    assert s["parts"]["tip"]["rms_jerk_mm_s3"] == pytest.approx(60.0, rel=1e-6)
    assert s["parts"]["tip"]["position_std_mm"] is None
    # the path's uncertainty: the speed's standard deviation (1 and 2 mm/s on alternate frames, 1.5 per step)
    # integrated over the 2 s, as if fully correlated; none where the file has no speed uncertainty
    assert shaft["path_length_sd_bound_mm"] == pytest.approx(1.5 * 2.0)
    assert shaft["mean_speed_sd_bound_mm_s"] == pytest.approx(1.5)
    assert s["parts"]["tip"]["path_length_sd_bound_mm"] is None
    assert s["instruments"]["large_needle_driver"]["opening_deg"]["mean_sd"] == pytest.approx(3.0)
    text = format_analysis(s)
    assert "path_sd<=" in text and "sd_deg" in text

    # jaw: steps touching frames 8 and 9 are not counted (no pose / "lost"), nor is the 100 mm jump
    jaw = s["parts"]["jaw"]
    assert jaw["pose_frames"] == N - 1 and jaw["tracked_frames"] == N - len(LOST)
    counted_steps = (N - 1) - 3  # steps 7-8, 8-9, 9-10 dropped
    assert jaw["path_length_mm"] == pytest.approx(50.0 * counted_steps / FPS, rel=1e-9)
    assert jaw["mean_speed_mm_s"] == pytest.approx(50.0, rel=1e-9)
    assert jaw["max_speed_mm_s"] == pytest.approx(50.0, rel=1e-9)
    assert len(jaw["series"]["speed_mm_s"]) == counted_steps
    assert jaw["series"]["tracked"][8] is False  # index 8 of the poses is frame 9 (frame 8 had none)

    inst = s["instruments"]["large_needle_driver"]
    assert inst["frames"] == N and inst["joint_names"] == ["roll", "opening"]
    assert inst["opening_deg"]["min"] == pytest.approx(10.0, abs=0.1)
    assert inst["opening_deg"]["max"] == pytest.approx(30.0, abs=0.1)
    assert inst["series"]["opening_deg"][5] == pytest.approx(30.0)  # t = 0.5 s

    text = format_analysis(s)
    assert "shaft" in text and "jaw" in text and "large_needle_driver" in text
    assert "40.0" in text and "20.0" in text and "10.0 / " in text
    png = plot_analysis(s, tmp_path / "tracks.png")
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size[0] > 300 and im.size[1] > 500


def test_any_status_can_count_as_tracked(tmp_path):
    path = tmp_path / "tracks.mcap"
    write_log(path)
    s = analyze_mcap(path, tracked_statuses=("tracking", "lost"))
    assert s["parts"]["jaw"]["tracked_frames"] == N - 1  # frame 8 still has no pose
    assert s["parts"]["jaw"]["max_speed_mm_s"] > 500.0    # now the 100 mm jump (frames 9-10) is counted


def test_bad_files_raise_one_line_value_error(tmp_path):
    missing = tmp_path / "nope.mcap"
    with pytest.raises(ValueError, match="nope.mcap"):
        analyze_mcap(missing)
    text = tmp_path / "notes.mcap"
    text.write_text("not an mcap file\n")
    with pytest.raises(ValueError, match="notes.mcap") as e:
        analyze_mcap(text)
    assert "\n" not in str(e.value)
    good = tmp_path / "tracks.mcap"
    write_log(good)
    cut = tmp_path / "cut.mcap"
    data = good.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="cut.mcap") as e:
        analyze_mcap(cut)
    assert "\n" not in str(e.value)


def test_empty_log(tmp_path):
    path = tmp_path / "empty.mcap"
    TrackWriter(path).close()
    s = analyze_mcap(path)
    assert s["parts"] == {} and s["instruments"] == {}
    assert "no part poses" in format_analysis(s)
    assert plot_analysis(s, tmp_path / "empty.png").is_file()


def test_tool_tip_motion_skips_frames_without_a_fit(tmp_path):
    """The tool tip is logged only on frames with a fit: a step across missing frames is not a path."""
    path = tmp_path / "tip.mcap"
    v = np.array([0.0, 30.0, 40.0])  # 50 mm/s
    with TrackWriter(path) as w:
        for i in range(N):
            if i in (8, 9):
                continue  # no fit: no joints, no tip
            t = i / FPS
            w.joint_states(t, "lnd.0", ["roll"], [0.0])
            w.tool_tip(t, "lnd.0", np.eye(3), np.array([0.0, 0.0, 60.0]) + v * t + (100.0 if i >= 10 else 0.0))
    tip = analyze_mcap(path)["instruments"]["lnd.0"]["tool_tip"]
    assert tip["frames"] == N - 2
    assert tip["path_length_mm"] == pytest.approx(50.0 * (N - 1 - 3) / FPS)  # 20 steps less the 3 across the gap
    assert tip["max_speed_mm_s"] == pytest.approx(50.0)
    assert "tip_path_mm" in format_analysis(analyze_mcap(path))
    assert tip["path_length_sd_bound_mm"] is None and tip["position_std_mm"] is None


def test_tool_tip_uncertainty_bounds_its_path(tmp_path):
    """The tip's logged speed sd, integrated over the counted steps, bounds its path's sd."""
    path = tmp_path / "tip_std.mcap"
    with TrackWriter(path) as w:
        for i in range(N):
            t = i / FPS
            w.joint_states(t, "lnd.0", ["roll"], [0.0])
            w.tool_tip(t, "lnd.0", np.eye(3), np.array([0.0, 0.0, 60.0 + 10.0 * t]))
            w.tool_tip_std(t, "lnd.0", np.diag([1.0, 4.0, 4.0]), [0.0, 0.0, 10.0], 2.0)
    tip = analyze_mcap(path)["instruments"]["lnd.0"]["tool_tip"]
    assert tip["path_length_mm"] == pytest.approx(10.0 * (N - 1) / FPS)
    assert tip["path_length_sd_bound_mm"] == pytest.approx(2.0 * (N - 1) / FPS)
    assert tip["position_std_mm"] == pytest.approx(3.0)
    assert "tip_path_sd<=" in format_analysis(analyze_mcap(path))


def test_min_confidence_leaves_doubted_frames_out(tmp_path, capsys):
    """A part moving at 50 mm/s whose track is 40 mm off on frames 10-12 (confidence 0.2 there): over
    every frame the excursion adds about 70 mm of path; with ``min_confidence`` 0.5 the steps touching those
    frames are not counted, for the part and for its instrument's tool tip."""
    from surftrack.cli import main

    path = tmp_path / "doubt.mcap"
    v = np.array([0.0, 30.0, 40.0])
    doubted = {10, 11, 12}
    with TrackWriter(path) as w:
        for i in range(N):
            t = i / FPS
            off = np.array([40.0, 0.0, 0.0]) if i in doubted else 0.0
            p = np.array([0.0, 0.0, 60.0]) + v * t + off
            w.pose("lnd.0.jaw", t, np.eye(3), p)
            w.status(t, "lnd.0.jaw", "tracking", 0.2 if i in doubted else 0.9)
            w.pose("lnd.0.shaft", t, np.eye(3), p - off - 20.0)
            w.status(t, "lnd.0.shaft", "tracking", 0.95)
            w.joint_states(t, "lnd.0", ["roll"], [0.0])
            w.tool_tip(t, "lnd.0", np.eye(3), p + 5.0)
    every = analyze_mcap(path)
    excursion = 2 * math.hypot(40.0, 5.0)  # off at frame 10, back at 13 (5 mm of motion per step)
    assert every["parts"]["lnd.0.jaw"]["path_length_mm"] == pytest.approx(5.0 * (N - 3) + excursion, rel=1e-6)
    sure = analyze_mcap(path, min_confidence=0.5)
    jaw, tip = sure["parts"]["lnd.0.jaw"], sure["instruments"]["lnd.0"]["tool_tip"]
    assert jaw["tracked_frames"] == N - len(doubted)
    assert jaw["path_length_mm"] == pytest.approx(5.0 * (N - 1 - 4), rel=1e-6)  # 4 steps touch 10-12
    assert tip["frames"] == N - len(doubted) and tip["path_length_mm"] == pytest.approx(5.0 * (N - 1 - 4), rel=1e-6)
    assert sure["parts"]["lnd.0.shaft"]["path_length_mm"] == pytest.approx(5.0 * (N - 1), rel=1e-6)
    assert "confidence >= 0.5" in format_analysis(sure) and "confidence" not in format_analysis(every).split("\n")[1]
    with pytest.raises(ValueError, match="min_confidence"):
        analyze_mcap(path, min_confidence=1.5)

    # doubted on every other frame: no step has two trusted ends, for the part nor for the tip
    alternate = tmp_path / "alternate.mcap"
    with TrackWriter(alternate) as w:
        for i in range(N):
            t = i / FPS
            w.pose("lnd.0.jaw", t, np.eye(3), v * t)
            w.status(t, "lnd.0.jaw", "tracking", 0.2 if i % 2 else 0.9)
            w.joint_states(t, "lnd.0", ["roll"], [0.0])
            w.tool_tip(t, "lnd.0", np.eye(3), v * t)
    sure = analyze_mcap(alternate, min_confidence=0.5)
    assert sure["parts"]["lnd.0.jaw"]["path_length_mm"] == 0.0
    assert sure["instruments"]["lnd.0"]["tool_tip"]["path_length_mm"] == 0.0
    assert analyze_mcap(alternate)["instruments"]["lnd.0"]["tool_tip"]["path_length_mm"] == pytest.approx(5.0 * (N - 1))
    assert main(["analyze", str(path), "--min-confidence", "0.5", "--png", str(tmp_path / "a.png")]) == 0
    assert "confidence >= 0.5" in capsys.readouterr().out


def test_a_restart_or_fresh_start_is_no_motion(tmp_path):
    """A track 30 mm off that the estimator restarts at frame 8 (status keyframe, ``restarted``), and one
    dropped and started again from an estimate at frame 15 (``estimator: reappearance``) without a lost frame
    logged between: neither jump is counted, for the part nor for its instrument's tool tip; the same jumps
    on a plain keyframe are."""
    path = tmp_path / "restart.mcap"
    v = np.array([0.0, 30.0, 40.0])  # 50 mm/s: 5 mm a step
    extra = {8: {"estimator": "box disagreement", "restarted": True}, 15: {"estimator": "reappearance"}}
    with TrackWriter(path) as w:
        for i in range(N):
            t = i / FPS
            p = np.array([0.0, 0.0, 60.0]) + v * t + (np.array([30.0, 0.0, 0.0]) if i < 8 else 0.0) \
                + (np.array([0.0, 0.0, 20.0]) if i >= 15 else 0.0)
            w.pose("lnd.0.jaw", t, np.eye(3), p)
            w.status(t, "lnd.0.jaw", "keyframe" if i in extra else "tracking", 0.9,
                     extra.get(i, {"estimator": "cadence"}))
            w.joint_states(t, "lnd.0", ["roll"], [0.0])
            w.tool_tip(t, "lnd.0", np.eye(3), p + 5.0)
    s = analyze_mcap(path)
    jaw, tip = s["parts"]["lnd.0.jaw"], s["instruments"]["lnd.0"]["tool_tip"]
    assert jaw["path_length_mm"] == pytest.approx(5.0 * (N - 1 - 2), rel=1e-9)
    assert jaw["max_speed_mm_s"] == pytest.approx(50.0, rel=1e-9)
    assert tip["path_length_mm"] == pytest.approx(5.0 * (N - 1 - 2), rel=1e-9)
    assert jaw["rms_jerk_mm_s3"] == pytest.approx(0.0, abs=1e-6)  # no jerk window spans a jump
    assert jaw["track_starts"] == 2 and "starts" in format_analysis(s)  # the two corrections are reported

    plain = tmp_path / "plain.mcap"
    with TrackWriter(plain) as w:
        for i in range(N):
            t = i / FPS
            p = np.array([0.0, 0.0, 60.0]) + v * t + (np.array([30.0, 0.0, 0.0]) if i < 8 else 0.0)
            w.pose("lnd.0.jaw", t, np.eye(3), p)
            w.status(t, "lnd.0.jaw", "keyframe", 0.9, {"estimator": "cadence"})
    assert analyze_mcap(plain)["parts"]["lnd.0.jaw"]["path_length_mm"] > 5.0 * (N - 2) + 25.0

"""Summaries of a tracking log: per-part motion (path length, speed) and jaw opening over time.

:func:`analyze_mcap` reads an MCAP written by :class:`~surftrack.io.TrackWriter`:

* ``/parts/<name>/pose`` (``foxglove.PoseInFrame``, metres; converted back to millimetres here),
* ``/parts/<name>/status`` (``surftrack.PartStatus``): a frame counts as tracked when the part has a
  pose at that time and its status there, if one was logged, is in ``tracked_statuses`` (by default
  every status with a pose: "keyframe" and "tracking" are measured, "predicted" ones are carried by the
  filter, interpolated from both sides in a smoothed run; pass :data:`~surftrack.track.MEASURED` for the
  measured ones only),
* ``/instruments/<name>/joints`` (``foxglove.JointStates``, radians; reported in degrees),
* ``/instruments/<name>/tool_tip`` (``foxglove.PoseInFrame``): the fitted tool tip, whose motion is
  reported as a part's is (a step longer than 1.5x the median breaks the chain: no fit in between), with
  its uncertainty from ``/instruments/<name>/tool_tip_std`` (``surftrack.PointUncertainty``) where the
  tip was read off an instrument's tracked state.

``min_confidence``: a frame counts as tracked only when its logged confidence (the probability that
the part is within ADD-10, :func:`~surftrack.track.state.confidence`) is at least this (a pose
without a status, or a status without a confidence, then does not count); a tool-tip frame only when
every part of its instrument logged at that time is (a hidden jaw, logged lost at confidence 0, holds
the tip out too). Motion through frames the tracker doubts (a tool entering close to the lens, a
track the estimator keeps contradicting) is then left out rather than summed: on clip 12 of the
tracking benchmark the default run's paths came out 1.0-1.9x the truth over the steps with confidence
>= 0.5 (36-57 % of them) against 1.7-3.3x over all steps; what remains is mostly jitter
(docs/results/2026-12-03-fit-speed.md).

Motion is measured only between CONSECUTIVE tracked frames of a part (frames are the union of its pose
and status times, so a logged "lost" frame, or a pose with a non-tracking status, breaks the chain and
no distance is counted across it), and none into a frame where its track restarted or started afresh
(:func:`~surftrack.track.status.starts_anew`, from the status's diagnostics; for the tool tip, any of its
instrument's parts): that jump is the track's correction, not motion (on the tracking benchmark's
held-out clips such jumps made 80 % of the paths' excess over the truth,
docs/results/2026-12-04-path-jumps.md). Path length = sum of the step lengths, mean speed = path length
/ the summed duration of those steps, max speed = the largest step length / step duration, RMS jerk = the
root mean square of the central third difference over 5 consecutive tracked frames (mm/s^3; a smoothness
figure of skill assessment). ``position_std_mm``: the mean over tracked frames of the pose's 3D position
standard deviation, from the filter's covariance the tracker writes in the status (None in files
without it). ``path_length_sd_bound_mm``: the sum over the counted steps of the speed's standard
deviation (status ``speed_std_mm_s``) times the step's duration: the path's standard deviation were the
speed errors of all frames fully correlated, an upper bound on it (the file holds no cross-frame
covariance; smoothed errors are strongly correlated over a second or so). It does not include the bias
that noise adds to a path length (jitter only lengthens it); ``mean_speed_sd_bound_mm_s`` is the bound
over the steps' duration. The jaw opening's ``mean_sd`` is the mean over the frames that have one of
its standard deviation (``/instruments/<name>/joints_std``): the filter's uncertainty on a frame, not
the opening's spread over time.

:func:`format_analysis` renders the summary as a text table, :func:`plot_analysis` as a PNG.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Iterable

import numpy as np
from mcap.reader import make_reader
from mcap.writer import MCAP0_MAGIC as MCAP_MAGIC

from surftrack.track.status import POSED, starts_anew

__all__ = ["analyze_mcap", "format_analysis", "plot_analysis"]

_POSE = re.compile(r"^/parts/([^/]+)/pose$")
_STATUS = re.compile(r"^/parts/([^/]+)/status$")
_JOINTS = re.compile(r"^/instruments/([^/]+)/joints$")
_JOINTS_STD = re.compile(r"^/instruments/([^/]+)/joints_std$")
_TIP = re.compile(r"^/instruments/([^/]+)/tool_tip$")
_TIP_STD = re.compile(r"^/instruments/([^/]+)/tool_tip_std$")


def _read(path: Path) -> list[tuple[str, str, int, dict]]:
    """(topic, schema name, log time ns, decoded JSON) of every message; any read or decode problem
    becomes a one-line ``ValueError`` naming the file."""
    if not path.is_file():
        raise ValueError(f"{path}: no such MCAP file")
    out = []
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                if channel.message_encoding != "json":
                    continue
                out.append((channel.topic, schema.name if schema else "", message.log_time,
                            json.loads(message.data)))
    except Exception as e:  # mcap raises many types (bad magic, truncated records, CRC, zstd, JSON)
        why = " ".join(f"{type(e).__name__}: {e}".split())
        with open(path, "rb") as f:
            unfinished = f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
        hint = (f"; if its run was cut off, `surftrack recover {path} -o FIXED.mcap` keeps every readable "
                f"message" if unfinished else "")
        raise ValueError(f"{path}: not a readable MCAP tracking log ({why}){hint}") from None
    return out


def _motion(times_ns: list[int], xyz_mm: dict[int, np.ndarray], tracked: dict[int, bool],
            speed_std: dict[int, float] | None = None, fresh: set[int] | None = None) -> dict:
    """Path length, speeds and jerk over consecutive tracked frames, and their uncertainty bounds where
    ``speed_std`` (frame -> mm/s) is known (see the module docstring); no step leads into a frame of
    ``fresh`` (a restarted or newly started track)."""
    fresh = fresh or set()
    steps_t, steps_v, steps_sd, length, duration = [], [], [], 0.0, 0.0
    for a, b in zip(times_ns[:-1], times_ns[1:]):
        if not (tracked[a] and tracked[b]) or b <= a or b in fresh:
            continue
        d = float(np.linalg.norm(xyz_mm[b] - xyz_mm[a]))
        dt = (b - a) * 1e-9
        length += d
        duration += dt
        steps_t.append(0.5 * (a + b) * 1e-9)
        steps_v.append(d / dt)
        if speed_std is not None and a in speed_std and b in speed_std:
            steps_sd.append((0.5 * (speed_std[a] + speed_std[b]), dt))
    # jerk: central third difference over 5 consecutive tracked frames (exact for a cubic path)
    jerks = []
    for k in range(2, len(times_ns) - 2):
        win = times_ns[k - 2:k + 3]
        steps = np.diff(win)
        if (not all(tracked[n] for n in win) or any(n in fresh for n in win[1:])
                or steps.min() <= 0 or steps.max() > 1.1 * steps.min()):
            continue  # the difference needs evenly spaced frames (none missing)
        dt = (win[-1] - win[0]) * 1e-9 / 4.0
        x = [xyz_mm[n] for n in win]
        jerks.append(float(np.linalg.norm(x[4] - 2.0 * x[3] + 2.0 * x[1] - x[0]) / (2.0 * dt**3)))
    known = speed_std is not None and steps_v and len(steps_sd) == len(steps_v)
    path_sd = sum(sd * dt for sd, dt in steps_sd) if known else None
    return {
        "path_length_mm": length,
        "path_length_sd_bound_mm": path_sd,
        "mean_speed_sd_bound_mm_s": path_sd / duration if known and duration > 0 else None,
        "mean_speed_mm_s": length / duration if duration > 0 else None,
        "max_speed_mm_s": max(steps_v) if steps_v else None,
        "rms_jerk_mm_s3": float(np.sqrt(np.mean(np.square(jerks)))) if jerks else None,
        "speed_time_s": steps_t,
        "speed_mm_s": steps_v,
    }


def _is_part_of(part: str, instrument: str) -> bool:
    """Whether the part topic name ``part`` is one of ``instrument``'s: "<instrument>.<part>", the part's
    own name without dots."""
    return part.startswith(instrument + ".") and "." not in part[len(instrument) + 1:]


def _with_gaps(xyz_mm: dict[int, np.ndarray]) -> tuple[list[int], dict[int, np.ndarray], dict[int, bool]]:
    """(frames, positions, tracked) of a series logged only where it exists (the tool tip: frames with a
    fit): an untracked frame is inserted in every step longer than 1.5 x the median step, so that no
    distance is counted across a gap."""
    times = sorted(xyz_mm)
    tracked = {ns: True for ns in times}
    if len(times) > 2:
        step = float(np.median(np.diff(times)))
        for a, b in zip(times[:-1], times[1:]):
            if b - a > 1.5 * step:
                tracked[(a + b) // 2] = False
    return sorted(tracked), xyz_mm, tracked


def analyze_mcap(path: str | os.PathLike, tracked_statuses: Iterable[str] = POSED,
                 min_confidence: float = 0.0) -> dict:
    """Summary of a TrackWriter MCAP file (frames counted as the module docstring says)::

        {"file": str, "min_confidence": float,
         "parts": {name: {"pose_frames", "tracked_frames", "track_starts", "t_start_s", "t_end_s", "span_s",
                          "path_length_mm", "mean_speed_mm_s", "max_speed_mm_s", "rms_jerk_mm_s3",
                          "position_std_mm", "path_length_sd_bound_mm", "mean_speed_sd_bound_mm_s",
                          "series": {"time_s", "x_mm", "y_mm", "z_mm", "tracked",
                                     "speed_time_s", "speed_mm_s"}}},
         "instruments": {name: {"frames", "t_start_s", "t_end_s", "joint_names",
                                "opening_deg": {"min", "mean", "max", "mean_sd"} or None,
                                "tool_tip": {"frames", "path_length_mm", "path_length_sd_bound_mm",
                                             "mean_speed_mm_s", "max_speed_mm_s", "rms_jerk_mm_s3",
                                             "position_std_mm"} or None,
                                "series": {"time_s", "<joint>_deg": [...]}}}}

    ``track_starts``: frames where the part's track started, restarted or started again
    (:func:`~surftrack.track.status.starts_anew`; 1 for one unbroken track, more for each correction whose
    jump the path leaves out). Times are the messages' log times in seconds; speeds are None when a part
    has no two consecutive tracked frames; series are plain lists (NaN where a joint has no position). A
    missing, corrupt or non-MCAP file raises ``ValueError`` with a one-line message naming it.
    """
    path = Path(path)
    min_confidence = float(min_confidence)
    if not 0.0 <= min_confidence <= 1.0:
        raise ValueError(f"min_confidence must lie in [0, 1], got {min_confidence!r}")
    tracked_ok = set(tracked_statuses)
    poses: dict[str, dict[int, np.ndarray]] = {}
    status: dict[str, dict[int, str]] = {}
    confidence: dict[str, dict[int, float]] = {}
    pos_std: dict[str, dict[int, float]] = {}
    speed_std: dict[str, dict[int, float]] = {}
    joints: dict[str, list[tuple[int, dict[str, float]]]] = {}
    joints_std: dict[str, list[dict[str, float]]] = {}
    tips: dict[str, dict[int, np.ndarray]] = {}
    tip_std: dict[str, dict[int, tuple[float, float]]] = {}  # (position sd mm, speed sd mm/s) by frame
    fresh: dict[str, set[int]] = {}  # frames whose pose does not continue the frame before's (starts_anew)
    messages = _read(path)
    try:
        for topic, schema, ns, msg in messages:
            if (m := _POSE.match(topic)) and schema == "foxglove.PoseInFrame":
                p = msg["pose"]["position"]
                poses.setdefault(m.group(1), {})[ns] = 1000.0 * np.array([p["x"], p["y"], p["z"]], dtype=float)
            elif (m := _STATUS.match(topic)) and schema == "surftrack.PartStatus":
                status.setdefault(m.group(1), {})[ns] = str(msg["status"])
                if starts_anew(msg["status"], msg.get("extra") or {}):
                    fresh.setdefault(m.group(1), set()).add(ns)
                if msg.get("confidence") is not None:
                    confidence.setdefault(m.group(1), {})[ns] = float(msg["confidence"])
                sd = (msg.get("extra") or {}).get("position_std_mm")
                if sd is not None:
                    pos_std.setdefault(m.group(1), {})[ns] = float(np.linalg.norm(sd))
                vsd = (msg.get("extra") or {}).get("speed_std_mm_s")
                if vsd is not None:
                    speed_std.setdefault(m.group(1), {})[ns] = float(vsd)
            elif (m := _TIP.match(topic)) and schema == "foxglove.PoseInFrame":
                p = msg["pose"]["position"]
                tips.setdefault(m.group(1), {})[ns] = 1000.0 * np.array([p["x"], p["y"], p["z"]], dtype=float)
            elif (m := _TIP_STD.match(topic)) and schema == "surftrack.PointUncertainty":
                tip_std.setdefault(m.group(1), {})[ns] = (float(np.linalg.norm(msg["position_std_mm"])),
                                                          float(msg["speed_std_mm_s"]))
            elif (m := _JOINTS.match(topic)) and schema == "foxglove.JointStates":
                vals = {j["name"]: float(j["position"]) for j in msg["joints"] if "position" in j}
                joints.setdefault(m.group(1), []).append((ns, vals))
            elif (m := _JOINTS_STD.match(topic)) and schema == "foxglove.JointStates":
                joints_std.setdefault(m.group(1), []).append(
                    {j["name"]: float(j["position"]) for j in msg["joints"] if "position" in j})
    except (AttributeError, KeyError, TypeError, ValueError) as e:  # AttributeError: a field of the wrong type
        raise ValueError(f"{path}: malformed tracking message ({type(e).__name__}: {e})") from None

    parts = {}
    for name in sorted(set(poses) | set(status)):
        xyz = poses.get(name, {})
        st = status.get(name, {})
        frames = sorted(set(xyz) | set(st))
        conf = confidence.get(name, {})
        tracked = {ns: ns in xyz and (ns not in st or st[ns] in tracked_ok)
                   and (min_confidence <= 0.0 or conf.get(ns, -1.0) >= min_confidence) for ns in frames}
        pose_ns = sorted(xyz)
        motion = _motion(frames, xyz, tracked, speed_std.get(name) if name in speed_std else None, fresh.get(name))
        arr = np.array([xyz[ns] for ns in pose_ns]).reshape(-1, 3)
        parts[name] = {
            "pose_frames": len(pose_ns),
            "tracked_frames": sum(tracked.values()),
            "track_starts": len(fresh.get(name, ())),
            "t_start_s": pose_ns[0] * 1e-9 if pose_ns else None,
            "t_end_s": pose_ns[-1] * 1e-9 if pose_ns else None,
            "span_s": (pose_ns[-1] - pose_ns[0]) * 1e-9 if pose_ns else 0.0,
            "path_length_mm": motion["path_length_mm"],
            "mean_speed_mm_s": motion["mean_speed_mm_s"],
            "max_speed_mm_s": motion["max_speed_mm_s"],
            "path_length_sd_bound_mm": motion["path_length_sd_bound_mm"],
            "mean_speed_sd_bound_mm_s": motion["mean_speed_sd_bound_mm_s"],
            "rms_jerk_mm_s3": motion["rms_jerk_mm_s3"],
            "position_std_mm": (float(np.mean(sds)) if (sds := [v for ns, v in pos_std.get(name, {}).items()
                                                                 if tracked.get(ns)]) else None),
            "series": {
                "time_s": [ns * 1e-9 for ns in pose_ns],
                "x_mm": arr[:, 0].tolist(), "y_mm": arr[:, 1].tolist(), "z_mm": arr[:, 2].tolist(),
                "tracked": [tracked[ns] for ns in pose_ns],
                "speed_time_s": motion["speed_time_s"], "speed_mm_s": motion["speed_mm_s"],
            },
        }

    instruments = {}
    for name, msgs in sorted(joints.items()):
        names = list(dict.fromkeys(j for _, vals in msgs for j in vals))
        series = {"time_s": [ns * 1e-9 for ns, _ in msgs]}
        for j in names:
            series[f"{j}_deg"] = [math.degrees(vals[j]) if j in vals else math.nan for _, vals in msgs]
        opening = [v for v in series.get("opening_deg", []) if math.isfinite(v)]
        opening_sd = [math.degrees(sd["opening"]) for sd in joints_std.get(name, []) if "opening" in sd]
        tip, tsd = tips.get(name, {}), tip_std.get(name, {})
        tip_motion = None
        if tip:
            tip_frames, tip_xyz, tip_ok = _with_gaps(tip)  # gaps from the logged frames, before any is left out
            if min_confidence > 0.0:
                members = [c for part, c in confidence.items() if _is_part_of(part, name)]
                tip_ok = {ns: ok and any(ns in c for c in members)
                          and all(c[ns] >= min_confidence for c in members if ns in c) for ns, ok in tip_ok.items()}
            # a restart or fresh start of any of its parts moves the tip without motion
            tip_fresh = set().union(*(f for part, f in fresh.items() if _is_part_of(part, name)))
            tip_motion = _motion(tip_frames, tip_xyz, tip_ok, {ns: v[1] for ns, v in tsd.items()} if tsd else None,
                                 tip_fresh)
            tip_counted = [ns for ns in tip if tip_ok[ns]]
        instruments[name] = {
            "tool_tip": None if tip_motion is None else {
                "frames": len(tip_counted), **{k: tip_motion[k] for k in ("path_length_mm", "path_length_sd_bound_mm",
                                                                          "mean_speed_mm_s", "max_speed_mm_s",
                                                                          "rms_jerk_mm_s3")},
                "position_std_mm": (float(np.mean(sds)) if (sds := [tsd[ns][0] for ns in tip_counted if ns in tsd])
                                    else None)},
            "frames": len(msgs),
            "t_start_s": msgs[0][0] * 1e-9,
            "t_end_s": msgs[-1][0] * 1e-9,
            "joint_names": names,
            "opening_deg": ({"min": min(opening), "mean": float(np.mean(opening)), "max": max(opening),
                             "mean_sd": float(np.mean(opening_sd)) if opening_sd else None}
                            if opening else None),
            "series": series,
        }
    return {"file": str(path), "min_confidence": min_confidence, "parts": parts, "instruments": instruments}


def _num(v: float | None, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def format_analysis(summary: dict) -> str:
    """A readable text table of :func:`analyze_mcap`'s summary (one line per part, then per instrument)."""
    lines = [f"{summary['file']}"]
    if summary.get("min_confidence", 0.0) > 0.0:
        lines.append(f"motion over frames with confidence >= {summary['min_confidence']:g}")
    parts = summary["parts"]
    if not parts:
        lines.append("no part poses")
    else:
        w = max(4, *(len(n) for n in parts))
        lines.append(f"{'part':<{w}}  {'frames':>6}  {'tracked':>7}  {'starts':>6}  {'start_s':>8}  {'end_s':>8}  "
                     f"{'path_mm':>9}  {'path_sd<=':>9}  {'mean_mm/s':>9}  {'max_mm/s':>9}  {'jerk_mm/s3':>10}  "
                     f"{'pos_std_mm':>10}")
        for n, p in parts.items():
            lines.append(f"{n:<{w}}  {p['pose_frames']:>6}  {p['tracked_frames']:>7}  {p.get('track_starts', 0):>6}  "
                         f"{_num(p['t_start_s'], '8.3f'):>8}  {_num(p['t_end_s'], '8.3f'):>8}  "
                         f"{p['path_length_mm']:>9.1f}  {_num(p.get('path_length_sd_bound_mm'), '9.1f'):>9}  "
                         f"{_num(p['mean_speed_mm_s'], '9.1f'):>9}  "
                         f"{_num(p['max_speed_mm_s'], '9.1f'):>9}  {_num(p['rms_jerk_mm_s3'], '10.0f'):>10}  "
                         f"{_num(p['position_std_mm'], '10.2f'):>10}")
    insts = summary["instruments"]
    if insts:
        w = max(10, *(len(n) for n in insts))
        lines.append("")
        lines.append(f"{'instrument':<{w}}  {'frames':>6}  {'start_s':>8}  {'end_s':>8}  "
                     f"{'opening_deg min / mean / max':>28}  {'sd_deg':>8}  {'tip_path_mm':>11}  {'tip_path_sd<=':>13}  "
                     f"{'tip_mean_mm/s':>13}  {'tip_max_mm/s':>12}  {'tip_jerk_mm/s3':>14}")
        for n, i in insts.items():
            o, tip = i["opening_deg"], i.get("tool_tip") or {}
            ostr = "-" if o is None else f"{o['min']:.1f} / {o['mean']:.1f} / {o['max']:.1f}"
            osd = _num(None if o is None else o.get("mean_sd"), "8.1f")
            lines.append(f"{n:<{w}}  {i['frames']:>6}  {i['t_start_s']:>8.3f}  {i['t_end_s']:>8.3f}  {ostr:>28}  {osd:>8}  "
                         f"{_num(tip.get('path_length_mm'), '11.1f'):>11}  {_num(tip.get('path_length_sd_bound_mm'), '13.1f'):>13}  "
                         f"{_num(tip.get('mean_speed_mm_s'), '13.1f'):>13}  "
                         f"{_num(tip.get('max_speed_mm_s'), '12.1f'):>12}  {_num(tip.get('rms_jerk_mm_s3'), '14.0f'):>14}")
    return "\n".join(lines)


def plot_analysis(summary: dict, png_path: str | os.PathLike) -> Path:
    """PNG of :func:`analyze_mcap`'s summary: x, y, z (mm) against time per part (untracked frames left
    as gaps), speed per part (one dot per counted step, at its mid-time), and jaw opening per instrument
    when joints were logged. Returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_opening = any("opening_deg" in i["series"] for i in summary["instruments"].values())
    rows = ["x_mm", "y_mm", "z_mm", "speed"] + (["opening"] if has_opening else [])
    fig, axes = plt.subplots(len(rows), 1, figsize=(9, 2.0 * len(rows)), sharex=True, squeeze=False)
    axes = axes[:, 0]
    for name, p in summary["parts"].items():
        s = p["series"]
        t = np.asarray(s["time_s"])
        keep = np.asarray(s["tracked"], dtype=bool)
        for ax, key in zip(axes[:3], ("x_mm", "y_mm", "z_mm")):
            ax.plot(t, np.where(keep, np.asarray(s[key]), np.nan), label=name, lw=1.2)
        axes[3].plot(s["speed_time_s"], s["speed_mm_s"], ".", label=name, ms=4)  # dots: steps may have gaps
    for ax, label in zip(axes[:4], ("x (mm)", "y (mm)", "z (mm)", "speed (mm/s)")):
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if has_opening:
        for name, i in summary["instruments"].items():
            if "opening_deg" in i["series"]:
                axes[4].plot(i["series"]["time_s"], i["series"]["opening_deg"], label=name, lw=1.2)
        axes[4].set_ylabel("jaw opening (deg)")
        axes[4].grid(alpha=0.3)
        axes[4].legend(loc="upper right", fontsize=8)
    if summary["parts"]:
        axes[0].legend(loc="upper right", fontsize=8, ncol=min(4, len(summary["parts"])))
    axes[-1].set_xlabel("time (s)")
    axes[0].set_title(Path(summary["file"]).name)
    fig.tight_layout()
    png_path = Path(png_path)
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
    return png_path

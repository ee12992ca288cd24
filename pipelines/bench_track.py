"""Tracking benchmark: tracked-frame cost per part, end-to-end frames/s, and tracking versus per-frame
estimation on a synthetic clip with ground truth.

    python pipelines/bench_track.py [--model CKPT] [--seconds 30] [--fps 30] [--parts wrist,shaft]
                                    [--clip DIR] [--device cpu|cuda] [--threads N]
                                    [--keyframe-every N] [--no-kinematic] [--preset P] [--views N]

Makes (or reuses, with --clip) a 640x512 synthetic clip of the Large Needle Driver crossed by a second tool
(``surftrack synth-clip``), keeps the boxes of the chosen parts (default: two, wrist and shaft), then:

1. runs the tracker (the main command's code path, MCAP written to a temporary file) and reports the
   tracked-frame cost per part (LK + PnP + Kalman, frames where the part was propagated by flow), the
   point-refresh cost, the estimator cost on keyframes, and end-to-end frames/s (decode, tracking, MCAP);
2. runs the estimator on every frame with the same boxes (no temporal model; the same instrument-level
   kinematic fit as the tracker's unless ``--no-kinematic``);
3. prints both against the ground truth side by side: ADD-10 (SurgRIPE diameter, share of frames where
   the part is visible; a frame without a pose counts as a miss), RE / TE medians, jitter (mean
   frame-to-frame pose change minus the ground truth's).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def _filtered_boxes(clip: Path, parts: list[str], out: Path) -> Path:
    from surftrack.synth.detections import write_detections

    doc = json.loads((clip / "det.json").read_text())
    keep = {k for k, v in doc["parts"].items() if v["instrument"] == "large_needle_driver" and v["part"] in parts}
    doc["parts"] = {k: v for k, v in doc["parts"].items() if k in keep}
    for f in doc["frames"]:
        f["detections"] = [d for d in f["detections"] if str(d["part_id"]) in keep]
    write_detections(out, doc)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", help="checkpoint (default: the bundled model)")
    ap.add_argument("--clip", help="an existing synth-clip folder (default: make one)")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--parts", default="wrist,shaft")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, help="torch intra-op threads")
    ap.add_argument("--keyframe-every", type=int)
    ap.add_argument("--preset", help="estimator preset (default: the tracking config's)")
    ap.add_argument("--views", type=int, help="crop views per box (default: the preset's)")
    ap.add_argument("--no-kinematic", action="store_true",
                    help="leave per-part poses as estimated (no instrument-level kinematic fit), in both runs")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    from surftrack.annotate import AnnotateOptions, annotate_video
    from surftrack.io.video import read_video_frames
    from surftrack.model.checkpoint import load_checkpoint
    from surftrack.paths import default_model_path
    from surftrack.pose import PoseEstimator
    from surftrack.pose.kinematic import apply_kinematics
    from surftrack.synth.clip import ClipConfig, make_clip
    from surftrack.track import PartState, load_track_config
    from surftrack.track.clip_eval import ClipGroundTruth, TrackScore, format_summary

    tmp = Path(tempfile.mkdtemp(prefix="bench_track_"))
    clip = Path(args.clip) if args.clip else tmp / "clip"
    if not args.clip:
        t0 = time.perf_counter()
        make_clip(clip, "lnd", ClipConfig(seconds=args.seconds, fps=args.fps), seed=args.seed, progress=False)
        print(f"clip: {args.seconds:g} s at {args.fps:g} fps, 640x512, made in {time.perf_counter() - t0:.0f} s ({clip})")
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    boxes = _filtered_boxes(clip, parts, tmp / "det.json")
    model_path = Path(args.model) if args.model else default_model_path()
    cfg = load_track_config()
    if args.keyframe_every:
        cfg = cfg.replace(keyframe_every=args.keyframe_every)
    if args.no_kinematic:
        cfg = cfg.replace(kinematic=False)
    if args.preset:
        cfg = cfg.replace(preset=args.preset)
    if args.views:
        cfg = cfg.replace(views=args.views)
    gt = ClipGroundTruth(clip / "gt.json")

    # 1. tracking
    score = TrackScore(gt)
    flow_ms, refresh_ms, est_ms = {}, [], []

    def on_frame(index, time_s, states):
        score.add_frame(index, time_s, states)
        for s in states:
            if s.status == "tracking" and "flow_ms" in s.info:
                flow_ms.setdefault(s.spec.part, []).append(s.info["flow_ms"])
            if "refresh_ms" in s.info:
                refresh_ms.append(s.info["refresh_ms"])
            if "estimator_ms" in s.info:
                est_ms.append(s.info["estimator_ms"])

    # joints off: the per-frame kinematic fit is its own output (about 35 ms a frame), timed apart below
    opts = AnnotateOptions(model=model_path, camera=clip / "camera.json", out=tmp / "track.mcap", config=cfg,
                           device=args.device, progress=False, joints=False)
    run = annotate_video(clip / "video.mp4", boxes, opts, on_frame=on_frame)
    track_summary = score.summary()

    # 2. per-frame estimation with the same boxes
    model, tcfg, _ = load_checkpoint(model_path, args.device)
    est = PoseEstimator(model, cfg.estimator_preset(), device=args.device, crop_size=tcfg.data.crop,
                        box_scale=tcfg.data.scale)
    K = np.asarray(json.loads((clip / "camera.json").read_text())["K"], np.float64)
    det = json.loads(boxes.read_text())
    per_frame = {f["index"]: f["detections"] for f in det["frames"]}
    specs = {}
    from surftrack.annotate import match_parts

    for s in match_parts(det, model, str(boxes))[0]:
        specs[s.track_id] = s
    kin = cfg.kinematic_config()
    score_est = TrackScore(gt)
    t0 = time.perf_counter()
    n = 0
    for index, (t_s, frame) in enumerate(read_video_frames(clip / "video.mp4")):
        best = {}
        for d in per_frame.get(index, []):
            if d["score"] >= cfg.min_box_score and (d["part_id"] not in best or d["score"] > best[d["part_id"]][1]):
                best[d["part_id"]] = (tuple(d["bbox"]), d["score"])
        pids = sorted(best)
        res = est.estimate(frame, [(specs[p].obj_id, best[p][0]) for p in pids], K) if pids else []
        if kin is not None:
            res = apply_kinematics(res, [specs[p].instance for p in pids], model.parts, kin)
        got = {p: r for p, r in zip(pids, res) if r.ok}
        states = [PartState(s, "keyframe" if p in got else "lost", 1.0 if p in got else 0.0,
                            got[p].R if p in got else None, got[p].t if p in got else None, None)
                  for p, s in specs.items()]
        score_est.add_frame(index, t_s, states)
        n += 1
    est_wall = time.perf_counter() - t0
    est_summary = score_est.summary()

    on_gpu = torch.device(args.device).type == "cuda"
    dev = torch.cuda.get_device_name(args.device) if on_gpu else f"CPU, {torch.get_num_threads()} threads"
    print(f"\nmodel {model_path}, preset {cfg.preset}, {cfg.estimator_preset().views} crop view(s), "
          f"keyframe every {cfg.keyframe_every} frames, "
          f"kinematic fit {'on' if cfg.kinematic else 'off'}, device {dev}")
    print(f"frames: {run['frames']}; tracking end to end (decode, tracker, MCAP) {run['fps']:.1f} frames/s, "
          f"the tracker alone {run['track_ms_per_frame']:.1f} ms/frame; per-frame estimation (decode, estimator) "
          f"{n / est_wall:.2f} frames/s = {1e3 * est_wall / n:.1f} ms/frame -> tracking "
          f"{run['fps'] / (n / est_wall):.1f}x faster end to end, {1e3 * est_wall / n / run['track_ms_per_frame']:.1f}x "
          f"comparing the tracker with the estimator")
    for part, v in sorted(flow_ms.items()):
        print(f"tracked-frame cost (LK + PnP + KF), {part}: median {statistics.median(v):.2f} ms, "
              f"p90 {np.percentile(v, 90):.2f} ms over {len(v)} frames")
    if refresh_ms:
        print(f"flow point refresh: median {statistics.median(refresh_ms):.2f} ms ({len(refresh_ms)} refreshes)")
    if est_ms:
        print(f"estimator on keyframes: median {statistics.median(est_ms):.0f} ms per part ({len(est_ms)} calls)")
    for name, p in run["parts"].items():
        print(f"  {name}: " + ", ".join(f"{k} {v}" for k, v in sorted(p["frames"].items())))
    print("\ntracking:")
    print(format_summary(track_summary), end="")
    print("per-frame estimation:")
    print(format_summary(est_summary), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())

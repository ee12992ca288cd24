"""Tracking benchmark: per-frame estimation against causal and smoothed tracking on synthetic clips with
ground truth, in one run.

    python pipelines/bench_track.py [--model CKPT] [--clip DIR ...] [--seconds 10] [--fps 30] [--seed 3]
                                    [--parts shaft,wrist,jaw_left,jaw_right] [--device cpu|cuda]
                                    [--threads N] [--keyframe-every N] [--no-kinematic] [--preset P]
                                    [--views N] [--lag-s S] [--config YAML] [--solver-seed N]

Makes (or reuses, with --clip, repeatable) a 640x512 synthetic clip of the Large Needle Driver crossed by
a second tool (``surftrack synth-clip``), keeps the boxes of the chosen parts, then per clip:

1. runs the tracker causally (the main command's code path with ``--causal``, MCAP to a temporary file):
   end-to-end frames/s (decode, tracking, MCAP), the tracked-frame cost per part, estimator calls;
2. smooths that run's filter states exactly as the default run does (:class:`LagSmoother` with the
   config's ``smooth_lag_s`` and smoother prior) and adds the smoothing time to the causal run's to give
   the default's frames/s (the tracking itself is the same computation);
3. runs the estimator on every frame with the same boxes (no temporal model; the same instrument-level
   kinematic fit unless ``--no-kinematic``);
4. prints the three against the ground truth (:mod:`surftrack.track.clip_eval`): ADD-10 (SurgRIPE
   diameter, share of visible frames; no pose = miss), RE / TE medians, jitter, path length est / gt,
   speed error, confidence calibration; for the default, where its paths' error comes from (right-track
   steps, wrong-track steps, restart jumps left out).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

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
    ap.add_argument("--clip", action="append", help="an existing synth-clip folder (repeatable; default: make one)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--parts", default="shaft,wrist,jaw_left,jaw_right")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, help="torch intra-op threads")
    ap.add_argument("--keyframe-every", type=int)
    ap.add_argument("--preset", help="estimator preset (default: the tracking config's)")
    ap.add_argument("--solver-seed", type=int, help="the estimator's RANSAC seed (default: the tracking config's)")
    ap.add_argument("--views", type=int, help="crop views per box (default: the preset's)")
    ap.add_argument("--anchor-views", type=int, help="crop views of the instrument fit's anchor part "
                    "(default: the config's)")
    ap.add_argument("--config", help="tracking YAML (default: configs/track/default.yaml)")
    ap.add_argument("--lag-s", type=float, help="smoothing lag (default: the tracking config's)")
    ap.add_argument("--no-kinematic", action="store_true",
                    help="leave per-part poses as estimated (no instrument-level kinematic fit), in every run")
    ap.add_argument("--no-per-frame", action="store_true", help="skip per-frame estimation (tuning runs)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    from surftrack.annotate import AnnotateOptions, annotate_video, score_per_frame
    from surftrack.instruments import load_instrument
    from surftrack.model.checkpoint import load_checkpoint
    from surftrack.paths import default_model_path
    from surftrack.synth.clip import ClipConfig, make_clip
    from surftrack.track import ended_revisions, filter_steps, load_track_config
    from surftrack.track.clip_eval import (ClipGroundTruth, TrackScore, format_path_causes, format_summary,
                                           format_tip_summary)
    from surftrack.track.smoother import LagSmoother

    tmp = Path(tempfile.mkdtemp(prefix="bench_track_"))
    clips = [Path(c) for c in args.clip or []]
    if not clips:
        clips = [tmp / "clip"]
        t0 = time.perf_counter()
        make_clip(clips[0], "lnd", ClipConfig(seconds=args.seconds, fps=args.fps), seed=args.seed, progress=False)
        print(f"clip: {args.seconds:g} s at {args.fps:g} fps, seed {args.seed}, 640x512, made in "
              f"{time.perf_counter() - t0:.0f} s ({clips[0]})")
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    model_path = Path(args.model) if args.model else default_model_path()
    cfg = load_track_config(args.config)
    for key in ("keyframe_every", "preset", "views", "anchor_views"):
        if getattr(args, key):
            cfg = cfg.replace(**{key: getattr(args, key)})
    if args.solver_seed is not None:
        cfg = cfg.replace(solver_seed=args.solver_seed)
    if args.keyframe_every:
        cfg = cfg.replace(keyframe_max_s=0.0)  # frames, as asked (as the main command's --keyframe-every)
    if args.lag_s is not None:
        cfg = cfg.replace(smooth_lag_s=args.lag_s)
    if args.no_kinematic:
        cfg = cfg.replace(kinematic=False)
    model, tcfg, _ = load_checkpoint(model_path, args.device)
    on_gpu = torch.device(args.device).type == "cuda"
    dev = torch.cuda.get_device_name(args.device) if on_gpu else f"CPU, {torch.get_num_threads()} threads"
    anchor = "".join(f" ({n} on the {p})" for p, n in cfg.estimator_preset().part_views)
    print(f"model {model_path}, preset {cfg.preset}, {cfg.estimator_preset().views} crop view(s){anchor}, keyframe every "
          f"{cfg.keyframe_every} frames{f' and {cfg.keyframe_max_s:g} s' if cfg.keyframe_max_s else ''} at most, kinematic fit {'on' if cfg.kinematic else 'off'}, smoothing lag "
          f"{cfg.smooth_lag_s:g} s, parts {', '.join(parts)}, device {dev}")

    lnd = load_instrument("lnd")
    tools = {lnd.name: lnd}
    for clip in clips:
        boxes = _filtered_boxes(clip, parts, tmp / f"{clip.name}.det.json")
        gt = ClipGroundTruth(clip / "gt.json")
        fps = json.loads((clip / "gt.json").read_text()).get("fps") or args.fps
        causal, smoothed = TrackScore(gt, instruments=tools), TrackScore(gt, instruments=tools)
        tracked_ms, est_calls, kinds, restarts = {}, Counter(), Counter(), Counter()
        smoother = LagSmoother(round(cfg.smooth_lag_s * fps), prior=cfg.smoother_prior())
        smooth_s = 0.0

        def score_smoothed(ready):
            for (index, time_s, states), steps in ready:
                smoothed.add_frame(index, time_s, [s.settle(steps, cfg) for s in states])

        def on_frame(index, time_s, states):
            nonlocal smooth_s
            causal.add_frame(index, time_s, states)
            for s in states:
                kinds[s.status] += 1
                if s.status == "tracking":  # prediction (+ flow), plus the part's share of the silhouette fit
                    tracked_ms.setdefault(s.spec.part, []).append((s.info.flow_ms or 0.0) + (s.info.region_ms or 0.0))
                if s.info.estimator is not None:
                    est_calls[s.info.estimator] += 1
                restarts[s.spec.part] += bool(s.info.restarted)
            t0 = time.perf_counter()
            ready = smoother.push((index, time_s, states), filter_steps(states), ended_revisions(states))
            smooth_s += time.perf_counter() - t0
            score_smoothed(ready)

        # joints off: the per-frame kinematic fit is its own output (about 35 ms a frame), not tracking
        opts = AnnotateOptions(model=model_path, camera=clip / "camera.json", out=tmp / "track.mcap",
                               config=cfg.replace(smooth_lag_s=0.0), device=args.device, progress=False,
                               joints=False)
        run = annotate_video(clip / "video.mp4", boxes, opts, on_frame=on_frame, checkpoint=(model, tcfg))
        t0 = time.perf_counter()
        ready = smoother.flush()
        smooth_s += time.perf_counter() - t0
        score_smoothed(ready)
        fps_smoothed = run["frames"] / (run["seconds"] + smooth_s)
        print(f"\n## {clip} ({run['frames']} frames)\n")
        print(f"tracking end to end (decode, tracker, MCAP): causal {run['fps']:.2f} frames/s, smoothed "
              f"{fps_smoothed:.2f} frames/s (smoothing {1e3 * smooth_s / run['frames']:.1f} ms/frame); "
              f"part-frames: " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
        print("estimator runs: " + ", ".join(f"{k} {v}" for k, v in est_calls.most_common()))
        print("restarts (kalman.max_rejections estimates in a row outside the gate): "
              + ", ".join(f"{part} {restarts[part]}" for part in parts))
        for part, v in sorted(tracked_ms.items()):
            print(f"tracked-frame cost (filter, flow, silhouette), {part}: median {statistics.median(v):.2f} ms over "
                  f"{len(v)} frames")
        if not args.no_per_frame:
            *est_summary, est_fps = score_per_frame(clip, boxes, model, tcfg, cfg, args.device)
            print(f"per-frame estimation (decode, estimator{', kinematic fit' if cfg.kinematic else ''}): "
                  f"{est_fps:.2f} frames/s -> smoothed tracking {fps_smoothed / est_fps:.1f}x faster")
            print("\nper-frame estimation:\n" + format_summary(est_summary[0]), end="")
            print(format_tip_summary(est_summary[1]), end="")
        print("\ncausal tracking (--causal):\n" + format_summary(causal.summary()), end="")
        print(format_tip_summary(causal.tip_summary()), end="")
        print("\nsmoothed tracking (default):\n" + format_summary(smoothed.summary()), end="")
        print(format_tip_summary(smoothed.tip_summary()), end="")
        print("\nwhere the smoothed paths' error comes from:\n" + format_path_causes(smoothed.summary()), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())

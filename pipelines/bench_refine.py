"""Per-frame estimation refined by the same frame's silhouette: how much a frame's own outline adds to the
estimate with the instrument fit, on synthetic clips with ground truth.

    python pipelines/bench_refine.py --clip DIR [--clip DIR ...] [--every 2] [--solver-seed 0] [--model CKPT]

For every ``--every``-th frame of each clip (``surftrack synth-clip`` or a suite clip: video.mp4,
camera.json, gt.json, det.json) a fresh :class:`~surftrack.track.Tracker` with the default tracking
config steps twice on the same frame at the same time plus 1 ms, with the clip's best box per part:

1. the first step is a keyframe: the estimator with the instrument fit (per-frame estimation), its
   masks teaching the silhouette measurement's colours (``region_colors: network``);
2. the second measures the silhouette of the same image from that pose and fuses it through the filter
   (one frame's evidence: no motion, no other frame).

Printed per clip and part: ADD-10 (SurgRIPE diameter) over the part's visible frames after each step,
and the median absolute depth error (mm, along the camera's z). A diagnostic for issue 21's per-frame
target (docs/results/2026-12-06-exit-revision.md), not a mode of the product.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from surftrack.annotate import best_boxes, match_parts
from surftrack.eval.metrics import add, diameter_bbox_diagonal
from surftrack.io.video import read_video_frames
from surftrack.model.checkpoint import load_checkpoint
from surftrack.paths import default_model_path
from surftrack.pose import PoseEstimator
from surftrack.track import TrackConfig, Tracker
from surftrack.track.clip_eval import ClipGroundTruth


def refine_clip(clip: Path, model, train_cfg, cfg: TrackConfig, every: int) -> dict[str, dict]:
    """Per part of ``clip``: {"frames": n, "hits": (estimate, refined) ADD-10 counts, "dz": (lists of
    |depth error| mm)} over the visible frames sampled."""
    K = np.asarray(json.loads((clip / "camera.json").read_text())["K"], np.float64)
    det = json.loads((clip / "det.json").read_text())
    specs = match_parts(det, model, str(clip / "det.json"))[0]
    per_frame = {f["index"]: f["detections"] for f in det["frames"]}
    gt = ClipGroundTruth(clip / "gt.json")
    est = PoseEstimator(model, cfg.estimator_preset(), crop_size=train_cfg.data.crop, box_scale=train_cfg.data.scale)
    known = {s.track_id for s in specs}
    limits = {s.name: 0.1 * diameter_bbox_diagonal(s.vertices) for s in specs}  # ADD-10, SurgRIPE diameter
    out: dict[str, dict] = {}
    for index, (t_s, frame) in enumerate(read_video_frames(clip / "video.mp4")):
        if index % every:
            continue
        boxes = {pid: [b] for pid, b in best_boxes(per_frame.get(index, []), known, cfg.min_box_score).items()}
        tracker = Tracker(est, K, (frame.shape[1], frame.shape[0]), specs, cfg)
        try:
            first = tracker.step(frame, t_s, boxes)
            second = tracker.step(frame, t_s + 1e-3, boxes)
        finally:
            tracker.close()
        for a, b in zip(first, second):
            Rg, tg, visible = gt.pose(index, a.spec.track_id)
            if visible < 1:
                continue
            row = out.setdefault(a.spec.name, {"frames": 0, "hits": [0, 0], "dz": ([], [])})
            row["frames"] += 1
            for k, s in enumerate((a, b)):
                if s.R is not None:
                    row["hits"][k] += add(s.R, s.t, Rg, tg, a.spec.vertices) < limits[a.spec.name]
                    row["dz"][k].append(abs(float(s.t[2] - tg[2])))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clip", action="append", required=True, help="a clip folder (repeatable)")
    ap.add_argument("--model", default=None, help="checkpoint (default: the bundled model)")
    ap.add_argument("--every", type=int, default=2, help="every N-th frame (default 2)")
    ap.add_argument("--solver-seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    args = ap.parse_args(argv)
    if args.every < 1:
        ap.error("--every must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    model, train_cfg, _ = load_checkpoint(args.model or default_model_path(), "cpu")
    cfg = TrackConfig(solver_seed=args.solver_seed, twin_boxes=True)
    print(f"model {args.model or default_model_path()}, preset {cfg.preset}, solver seed {args.solver_seed}, "
          f"every {args.every} frame(s)\n")
    print("| clip | part | frames | ADD-10 estimate -> refined (%) | median abs depth error (mm) |")
    print("|---|---|---|---|---|")
    for clip in map(Path, args.clip):
        for name, r in refine_clip(clip, model, train_cfg, cfg, args.every).items():
            n = max(r["frames"], 1)
            dz = [f"{np.median(d):.2f}" if d else "-" for d in r["dz"]]
            print(f"| {clip.name} | {name} | {r['frames']} | {100 * r['hits'][0] / n:.1f} -> {100 * r['hits'][1] / n:.1f} "
                  f"| {dz[0]} -> {dz[1]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

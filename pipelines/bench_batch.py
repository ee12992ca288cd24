"""Batch throughput: the same synthetic clips tracked by a plain loop in this process and by
``surftrack.batch.run_batch`` on a local Ray with 1 and 2 workers, in one run.

Prints videos/hour and frames/s for each, and Ray's overhead on one worker against the plain loop (which
loads the model once too). Usage: ``python pipelines/bench_batch.py [--clips 4] [--seconds 3] [--fps 10]``.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from surftrack.annotate import AnnotateOptions, annotate_video
from surftrack.batch import batch_jobs, run_batch
from surftrack.model.checkpoint import load_checkpoint
from surftrack.paths import default_model_path
from surftrack.synth.clip import ClipConfig, make_clip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--clips", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--fps", type=float, default=10.0)
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    videos, boxes = root / "videos", root / "boxes"
    videos.mkdir()
    boxes.mkdir()
    cfg = ClipConfig(seconds=args.seconds, fps=args.fps, width=320, height=256, hfov_deg=70.0)
    for k in range(args.clips):
        clip = make_clip(root / f"clip{k}", "lnd", cfg, seed=100 + k)
        shutil.copy(clip["video"], videos / f"clip{k}.mp4")
        shutil.copy(clip["det"], boxes / f"clip{k}.json")
    camera = Path(clip["camera"])
    jobs = batch_jobs(videos, boxes, camera, root / "plain")
    (root / "plain").mkdir()

    t0 = time.perf_counter()
    loaded = load_checkpoint(default_model_path())[:2]
    frames = 0
    for j in jobs:
        s = annotate_video(j.video, j.boxes, AnnotateOptions(camera=camera, out=j.out, progress=False),
                           checkpoint=loaded)
        frames += s["frames"]
    results = {"plain loop": (time.perf_counter() - t0, frames)}
    for workers in (1, 2):
        out = root / f"ray{workers}"
        t0 = time.perf_counter()
        rows = run_batch(batch_jobs(videos, boxes, camera, out), out, AnnotateOptions(progress=False),
                         workers=workers, progress=False)
        assert all(r["status"] == "done" for r in rows), rows
        results[f"Ray, {workers} worker(s)"] = (time.perf_counter() - t0, sum(r["frames"] for r in rows))
    print(f"{len(jobs)} clips of {args.seconds:g} s at {args.fps:g} fps (320x256), bundled model, default config")
    print("| run | seconds | videos/hour | frames/s |\n|---|---|---|---|")
    for name, (sec, n) in results.items():
        print(f"| {name} | {sec:.1f} | {3600 * len(jobs) / sec:.0f} | {n / sec:.2f} |")
    plain, ray1 = results["plain loop"][0], results["Ray, 1 worker(s)"][0]
    print(f"Ray's overhead on one worker: {ray1 / plain:.2f}x the plain loop's time "
          f"(start-up, model load in the worker, transfers)")
    shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()

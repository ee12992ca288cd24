"""Annotating an archive: one tracking run per video, spread over Ray workers.

``run_batch(jobs, out_dir, ...)`` checks every input first (a bad video, boxes or camera file is reported
and skipped; the others run), then sends one Ray task per video. Without an address it starts a local Ray
on this machine; ``"auto"`` or ``"ray://host:port"`` joins a cluster, whose workers must see the inputs and
``out_dir`` on shared storage. A worker process loads the model once and keeps it for every video it is
given (Ray reuses worker processes), and asks for a GPU when the cluster has one. Each video writes
``OUT/<stem>.mcap``; ``OUT/manifest.jsonl`` gets one line per video as it ends: status (``done``,
``partial``: the video stopped decoding part of the way through, ``failed``, ``skipped``: done before,
``stopped``: the batch was stopped first), frames, seconds, frames/s and the error line. The progress
bar counts videos and shows the frames done over all of them, running ones included (each reports its
count every 10 frames in ``OUT/.progress/``, removed at the end).

A batch stopped by Ctrl-C or SIGTERM cancels the videos not yet started and writes ``OUT/.stop``; a running
video checks for that file after every frame and stops as a single run does on Ctrl-C, finalising its
outputs. A file rather than Ray's task cancellation, which did not interrupt a running video here, and
which a worker on another machine sees through the shared output folder.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

from surftrack.annotate import AnnotateOptions, annotate_video
from surftrack.track.inputs import InputError, load_boxes, load_camera, probe_video

__all__ = ["BatchJob", "batch_jobs", "check_job", "run_batch"]

#: statuses of a manifest row that count as finished
FINISHED = ("done", "skipped")
#: what a folder of videos holds
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")


@dataclass(frozen=True)
class BatchJob:
    """One video of a batch: its boxes (None when none was found), its camera file (None: the one beside
    the video) and its MCAP output."""

    video: Path
    boxes: Path | None
    camera: Path | None
    out: Path


def batch_jobs(videos: str | Path, boxes: str | Path | None, camera: str | Path | None,
               out_dir: str | Path) -> list[BatchJob]:
    """The jobs of ``videos``: a folder of videos (``boxes``: a folder of ``<stem>.json`` or
    ``<stem>.det.json``; ``camera``: one file for all, or a folder of ``<stem>.json``), or a CSV manifest
    with columns ``video``, ``boxes`` and optionally ``camera`` (paths relative to the CSV's folder).
    A missing boxes file is left for :func:`check_job` to report, so that one video cannot stop the batch."""
    videos, out_dir = Path(videos), Path(out_dir)
    if videos.is_file() and videos.suffix.lower() == ".csv":
        jobs = []
        with open(videos, newline="") as f:
            reader = csv.DictReader(f)
            if not reader.fieldnames or not {"video", "boxes"} <= set(reader.fieldnames):
                raise InputError(f"{videos}: a batch manifest needs the columns video and boxes (and camera)")
            for row in reader:
                v = videos.parent / row["video"]
                c = row.get("camera") or None
                jobs.append(BatchJob(v, videos.parent / row["boxes"] if row["boxes"] else None,
                                     videos.parent / c if c else None, out_dir / f"{v.stem}.mcap"))
    elif videos.is_dir():
        if boxes is None or not Path(boxes).is_dir():
            raise InputError(f"{boxes}: with a folder of videos, --boxes must be a folder of <video stem>.json files")
        jobs = []
        for v in sorted(p for p in videos.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES):
            b = next((c for c in (Path(boxes) / f"{v.stem}.json", Path(boxes) / f"{v.stem}.det.json")
                      if c.is_file()), None)
            c = None
            if camera is not None:
                c = Path(camera) / f"{v.stem}.json" if Path(camera).is_dir() else Path(camera)
            jobs.append(BatchJob(v, b, c, out_dir / f"{v.stem}.mcap"))
    else:
        raise InputError(f"{videos}: not a folder of videos or a CSV manifest")
    if not jobs:
        raise InputError(f"{videos}: no video to process ({', '.join(VIDEO_SUFFIXES)})")
    stems: dict[str, Path] = {}
    for j in jobs:
        if j.out in stems:
            raise InputError(f"{videos}: {stems[j.out]} and {j.video} would both write {j.out}; rename one")
        stems[j.out] = j.video
    return jobs


def check_job(job: BatchJob) -> str | None:
    """None when the video decodes and its boxes and camera fit it; else the problem in one line."""
    try:
        info = probe_video(job.video)
        if job.boxes is None:
            return f"{job.video}: no boxes ({job.video.stem}.json or {job.video.stem}.det.json)"
        load_boxes(job.boxes, (info.width, info.height))
        camera = job.camera or next((c for c in (job.video.with_suffix(".camera.json"),
                                                 job.video.parent / "camera.json") if c.is_file()), None)
        if camera is None:
            return f"{job.video}: no intrinsics (a camera column, --camera, or camera.json beside the video)"
        load_camera(camera, (info.width, info.height))
    except InputError as e:
        return str(e)
    return None


def _finished_before(job: BatchJob, previous: dict[str, dict]) -> bool:
    """Whether an earlier run of the batch finished ``job``: its manifest row says so and its MCAP is a
    finished file (summary and footer)."""
    from mcap.reader import make_reader

    row = previous.get(str(job.video))
    if not row or row.get("status") not in FINISHED or not job.out.is_file():
        return False
    try:
        with open(job.out, "rb") as f:
            return make_reader(f).get_summary() is not None
    except Exception:  # noqa: BLE001 - any reading problem means: run it again
        return False


_LOADED: dict[tuple[str, str], tuple] = {}  # per worker process: (model path, device) -> (model, config)


def _track(job: BatchJob, opts: AnnotateOptions, stop_file: Path) -> dict:
    """One video in a worker: the manifest row. It stops after the frame during which ``stop_file``
    appears."""
    from surftrack.model.checkpoint import CheckpointError, load_checkpoint
    from surftrack.paths import default_model_path

    t0 = time.perf_counter()
    row = _row(job, "failed", "")
    try:
        key = (str(opts.model or default_model_path()), opts.device or "cpu")
        if key not in _LOADED:
            _LOADED[key] = load_checkpoint(key[0], key[1])[:2]
        progress, done = _progress_file(stop_file, job), [0]

        def on_frame(*_) -> None:
            _stop_if(stop_file)
            done[0] += 1
            if done[0] % 10 == 0:  # the driver's bar shows the frames done over every running video
                _report(progress, done[0])

        s = annotate_video(job.video, job.boxes, replace(opts, out=job.out, camera=job.camera),
                           checkpoint=_LOADED[key], on_frame=on_frame)
        row.update(status="partial" if s["partial"] else "done", frames=s["frames"], fps=round(s["fps"], 3))
        if s["partial"]:
            p = s["partial"]
            row["error"] = (f"partial: {p['frames_decoded']} of {p['frames_in_video'] or '?'} frames, decoding "
                            f"stopped at t = {p['stopped_at_s']:.3f} s ({p['error']})")
    except (InputError, CheckpointError, OSError, ValueError) as e:
        row["error"] = " ".join(str(e).split())
    except KeyboardInterrupt as e:  # the batch was stopped: annotate_video has finalised the outputs
        row.update(status="stopped", frames=getattr(e, "frames_done", 0), error="stopped before the end")
    row["seconds"] = round(time.perf_counter() - t0, 3)
    if row["status"] != "failed":  # annotate_video finalised its MCAP
        row["mcap"] = str(job.out)
    return row


def _progress_dir(stop_file: Path) -> Path:
    """Where running videos report their frames done (beside the stop file, in the output folder)."""
    return stop_file.parent / ".progress"


def _progress_file(stop_file: Path, job: BatchJob) -> Path:
    return _progress_dir(stop_file) / f"{job.out.stem}.frames"


def _report(progress: Path, frames: int) -> None:
    """Best effort (a progress line must never fail a video), replaced atomically (never read half-written)."""
    try:
        tmp = progress.with_suffix(".tmp")
        tmp.write_text(str(frames))
        os.replace(tmp, progress)
    except OSError:
        pass


def _frames_running(stop_file: Path, jobs) -> int:
    total = 0
    for job in jobs:
        try:
            total += int(_progress_file(stop_file, job).read_text() or 0)
        except (OSError, ValueError):
            continue
    return total


def _stop_if(stop_file: Path) -> None:
    if stop_file.exists():
        raise KeyboardInterrupt


def _row(job: BatchJob, status: str, error: str, earlier: dict | None = None) -> dict:
    """A manifest row of ``job`` that tracked nothing in this run: its MCAP and figures are ``earlier``'s,
    the row of the run that finished it, if given (else none)."""
    earlier = earlier or {}
    return {"video": str(job.video), "mcap": earlier.get("mcap"), "status": status,
            "frames": earlier.get("frames", 0), "seconds": earlier.get("seconds", 0.0),
            "fps": earlier.get("fps", 0.0), "error": error}


def run_batch(jobs: list[BatchJob], out_dir: str | Path, opts: AnnotateOptions | None = None, *,
              address: str | None = None, workers: int | None = None, force: bool = False,
              progress: bool = True) -> list[dict]:
    """Run ``jobs`` on Ray (see the module docstring) and return the manifest rows of this run, in the
    order the videos ended. ``opts``: the tracking options for every video (``out`` and ``camera`` are
    the jobs'). ``workers``: concurrent videos on a local Ray (default: the cores). ``force``: redo videos
    an earlier run finished. Ctrl-C or SIGTERM cancels the running videos, which finalise their outputs,
    marks the rest ``stopped`` in the manifest and re-raises."""
    import ray
    from tqdm import tqdm

    opts = opts or AnnotateOptions()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest, stop_file = out_dir / "manifest.jsonl", out_dir / ".stop"
    stop_file.unlink(missing_ok=True)
    previous: dict[str, dict] = {}
    if manifest.is_file():
        for line in manifest.read_text().splitlines():
            try:
                r = json.loads(line)
                previous[r["video"]] = r
            except (json.JSONDecodeError, KeyError, TypeError):
                continue
    rows: list[dict] = []

    def record(row: dict) -> None:
        rows.append(row)
        with open(manifest, "a") as f:
            f.write(json.dumps(row) + "\n")

    todo = []
    for job in jobs:
        if not force and _finished_before(job, previous):
            record(_row(job, "skipped", "finished by an earlier run", previous[str(job.video)]))
        elif (problem := check_job(job)) is not None:
            record(_row(job, "failed", problem))
        else:
            todo.append(job)
    if not todo:
        return rows
    started_here = not ray.is_initialized()
    if started_here:
        # ray.init installs its own SIGTERM handler, which kills the driver without finalising anything:
        # keep the caller's (the CLI turns SIGTERM into a KeyboardInterrupt that cancels the videos).
        handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        if address is None:
            # "local": a cluster of our own; without it ray.init joins any cluster already running on the
            # machine (another batch's), where num_cpus is refused
            ray.init(address="local", num_cpus=workers or os.cpu_count() or 1, include_dashboard=False,
                     log_to_driver=False, configure_logging=False)
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
        if threading.current_thread() is threading.main_thread():
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
    try:
        gpus = 1 if ray.cluster_resources().get("GPU", 0) >= 1 else 0
        task = ray.remote(num_cpus=1, num_gpus=gpus, max_retries=0)(_track)
        if gpus:
            opts = replace(opts, device=opts.device or "cuda")
        shutil.rmtree(_progress_dir(stop_file), ignore_errors=True)
        _progress_dir(stop_file).mkdir(exist_ok=True)
        pending = {task.remote(job, opts, stop_file): job for job in todo}
        bar = tqdm(total=len(todo), unit="video", desc="batch", disable=not progress)
        frames = 0
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                if ready:
                    job = pending.pop(ready[0])
                    try:
                        record(ray.get(ready[0]))
                    except Exception as e:  # noqa: BLE001 - a crash in one video (a worker died) fails that video only
                        record(_row(job, "failed", " ".join(f"{type(e).__name__}: {e}".split())[:500]))
                    frames += rows[-1]["frames"]
                    bar.update(1)
                bar.set_postfix(frames=frames + _frames_running(stop_file, pending.values()))
        except KeyboardInterrupt:
            stop_file.touch()  # running videos stop after their current frame and finalise their outputs
            for ref in pending:
                ray.cancel(ref)  # those not started never start
            for ref, job in pending.items():
                try:
                    row = ray.get(ref)
                except Exception:  # noqa: BLE001 - cancelled before it started, or gone
                    row = _row(job, "stopped", "stopped before it ran")
                record(row)
            raise
        finally:
            bar.close()
            stop_file.unlink(missing_ok=True)
            shutil.rmtree(_progress_dir(stop_file), ignore_errors=True)
    finally:
        if started_here:
            ray.shutdown()
    return rows

"""The main job: track every part of every instrument through a video and write the results.

``annotate_video(video, boxes, ...)`` validates all inputs before heavy work (video decodable, camera
and detections consistent with it, model knows the parts, outputs writable), then streams the video
frame by frame through :class:`surftrack.track.Tracker` (memory flat in the video's length), smooths the
poses with a fixed lag (:class:`surftrack.track.smoother.LagSmoother`; none with ``--causal``) and hands
every frame to the output sinks (:mod:`surftrack.io.sinks`):

* an MCAP file for Foxglove (:class:`surftrack.io.TrackWriter`): per part pose and status on every frame,
  ``/tf``, camera calibration, part meshes, joint angles, optional JPEG frames with annotations, metadata;
* optionally an overlay video, TUM trajectories (one file per part) and a joint-angle CSV.

Every output is finalised when the run stops early (bad frame, Ctrl-C, SIGTERM): the frames waiting in
the smoother are written, and what was written stays valid.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from surftrack import __version__
from surftrack.instruments import BUILTIN, InstrumentRegistry
from surftrack.io.sinks import FrameSink, JointsSink, McapSink, OverlaySink, TumSink
from surftrack.io.video import read_video_frames
from surftrack.track import PartSpec, PartState, TrackConfig, Tracker, ended_revisions, filter_steps
from surftrack.track.smoother import LagSmoother
from surftrack.track.inputs import CameraInput, InputError, VideoInfo, load_boxes, load_camera, probe_video

@dataclass
class AnnotateOptions:
    """What to write and how to track. ``start``/``end``: seconds of video time (None = from the start /
    to the end). ``mcap_images``: JPEG frames plus annotations in the MCAP (bigger files). ``joints``:
    fit each instrument's joint angles every frame (foxglove.JointStates in the MCAP; also CSV to
    ``joints_csv``). ``instruments``: where instrument names are looked up (the CLI's ``--instrument`` and
    ``$SURFTRACK_INSTRUMENTS``)."""

    model: str | Path | None = None
    camera: str | Path | None = None
    out: str | Path | None = None
    config: TrackConfig = field(default_factory=TrackConfig)
    device: str | None = None
    start: float | None = None
    end: float | None = None
    overlay: str | Path | None = None
    export_tum: str | Path | None = None
    joints: bool = True
    joints_csv: str | Path | None = None
    mcap_images: bool = False
    progress: bool = True
    instruments: InstrumentRegistry = BUILTIN


def match_parts(doc: dict, model, source: str,
                instruments: InstrumentRegistry = BUILTIN) -> tuple[list[PartSpec], list[str]]:
    """PartSpecs for the det.json parts the model knows, and a note per skipped instrument. An
    instrument the model knows with a part name it lacks is an error (a typo, not another tool); no known
    part at all is an error. Aliases are resolved through ``instruments``."""

    def canonical(name: str) -> str:
        try:
            return instruments.load(name).name
        except Exception:  # noqa: BLE001 - an instrument we do not ship is still a valid name
            return name

    by_key = {(p.instrument, p.name): p for p in model.parts}
    known_instruments = {p.instrument for p in model.parts}
    specs, skipped = [], {}
    for pid, d in sorted(doc["parts"].items(), key=lambda kv: int(kv[0])):
        inst = canonical(d["instrument"])
        info = by_key.get((inst, d["part"]))
        if info is None:
            if inst in known_instruments:
                names = sorted(p.name for p in model.parts if p.instrument == inst)
                raise InputError(f"{source}: $.parts.{pid}: {inst} has no part {d['part']!r} in the model "
                                 f"(its parts: {', '.join(names)})")
            skipped.setdefault(inst, []).append(int(pid))
            continue
        specs.append(PartSpec(int(pid), info.obj_id, inst, int(d["instance"]), d["part"],
                              np.asarray(info.vertices, np.float64), np.asarray(info.faces, np.int64)))
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"{source}: several part ids denote the same part {dup[0]} (instrument, instance, part)")
    if not specs:
        raise InputError(f"{source}: none of its parts is known to the model (model instruments: "
                         f"{', '.join(sorted(known_instruments))}; file: {', '.join(sorted(skipped))})")
    notes = [f"{inst}: parts {ids} are not in the model and are not tracked" for inst, ids in skipped.items()]
    return specs, notes


def _undistort_box(box: tuple, cam) -> tuple:
    """The box (pixel edges) around the undistorted positions of points on the box's outline."""
    x, y, w, h = box
    s = np.linspace(0.0, 1.0, 9)
    edge = np.concatenate([np.c_[x + w * s, np.full(9, y)], np.c_[x + w * s, np.full(9, y + h)],
                           np.c_[np.full(9, x), y + h * s], np.c_[np.full(9, x + w), y + h * s]]) - 0.5
    und = cv2.undistortPoints(edge.reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K).reshape(-1, 2) + 0.5
    x0, y0 = np.clip(und.min(0), 0, [cam.width, cam.height])
    x1, y1 = np.clip(und.max(0), 0, [cam.width, cam.height])
    return (float(x0), float(y0), float(x1 - x0), float(y1 - y0))


def _frame_boxes(doc: dict, cam) -> dict[int, dict[int, list]]:
    """frame index -> part id -> [(box, score)], boxes moved into the undistorted frames."""
    distorted = bool(np.any(cam.dist))
    out: dict[int, dict[int, list]] = {}
    for f in doc["frames"]:
        per = out.setdefault(int(f["index"]), {})
        for d in f["detections"]:
            box = tuple(float(v) for v in d["bbox"])
            per.setdefault(int(d["part_id"]), []).append((_undistort_box(box, cam) if distorted else box,
                                                          float(d["score"])))
    return out


class DecodeError(InputError):
    """A video that stops decoding part of the way through (truncated or corrupt data)."""


def _video_frames(path: Path):
    """read_video_frames with an opening failure as InputError and a decoding failure (truncated, corrupt)
    as DecodeError."""
    try:
        it = read_video_frames(path)
    except ValueError as e:
        raise InputError(str(e)) from None
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except ValueError as e:
            raise DecodeError(str(e)) from None
        yield item


def _frames_to_read(info, end: float | None) -> int | None:
    """Frames the progress bar counts (those before ``--start`` included): up to ``end`` seconds, or the
    container's frame count; None when unknown."""
    if end is not None and info.fps > 0:
        upto = int(end * info.fps + 1e-6) + 1
        return min(upto, info.frames) if info.frames else upto
    return info.frames or None


def check_span(start: float | None, end: float | None) -> None:
    """:class:`InputError` unless ``start`` / ``end`` (s of video from its start, None = open) make a
    stretch to track."""
    for flag, v in (("--start", start), ("--end", end)):
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise InputError(f"{flag} {v:g}: give seconds of video from its start (>= 0)")
    if start is not None and end is not None and end <= start:
        raise InputError(f"--end {end} must be after --start {start}")


def _check_outputs(video: Path, boxes: Path, camera: Path, model: Path, out: Path, opts: AnnotateOptions,
                   size: tuple[int, int]) -> None:
    """Refuse, before the model loads and any file is opened, outputs that would overwrite an input or one
    another, output files of the wrong kind or where no file can be written, and an overlay its writer
    would only refuse after the MCAP had been started."""
    from surftrack.io.overlay import check_overlay_video

    taken = {Path(p).resolve(): what for what, p in (("the input video", video), ("the boxes", boxes),
                                                     ("the camera file", camera), ("the model", model))}
    for what, p, suffix in (("the MCAP", out, ".mcap"), ("--overlay", opts.overlay, None),
                            ("--joints-csv", opts.joints_csv, ".csv")):
        if p is None:
            continue
        p = Path(p)
        r = p.resolve()
        if r in taken:
            raise InputError(f"{p}: {what} would overwrite {taken[r]}")
        taken[r] = what
        if suffix is not None and p.suffix.lower() != suffix:
            raise InputError(f"{p}: {what} must be a {suffix} file")
        _output_folder(p, what)
    if opts.export_tum is not None:
        tum = Path(opts.export_tum)
        if tum.resolve() in taken:
            raise InputError(f"{tum}: --export-tum would overwrite {taken[tum.resolve()]}")
        if tum.exists() and not tum.is_dir():
            raise InputError(f"{tum}: --export-tum names a file; give a folder")
    if opts.overlay is not None:
        try:
            check_overlay_video(opts.overlay, *size)
        except ValueError as e:
            raise InputError(f"--overlay: {e}") from None


def _check_tum_names(boxes: Path, specs: list[PartSpec]) -> None:
    """Refuse parts whose TUM files (``--export-tum``) would be unnamable or share a name."""
    from surftrack.io.tum import tum_filename

    files: dict[str, str] = {}
    for s in specs:
        try:
            f = tum_filename(s.name)
        except ValueError as e:
            raise InputError(f"{boxes}: {e}") from None
        if f in files:
            raise InputError(f"{boxes}: parts {files[f]!r} and {s.name!r} would share the TUM file {f}")
        files[f] = s.name


def _output_folder(path: Path, what: str) -> None:
    """:class:`InputError` naming ``path`` unless an output file can go there (its folder exists)."""
    if path.is_dir():
        raise InputError(f"{path}: {what} names a folder; give a file")
    if not path.parent.is_dir():
        raise InputError(f"{path}: no folder {path.parent} for {what}")


@dataclass
class _Run:
    """What one tracking run works from, every input checked (:func:`_prepare`) before an output is opened:
    ``out`` the MCAP's path, the video's ``info``, the camera ``cam``, the parts ``specs``, ``notes`` for the
    summary, the ``tracker``, the MCAP's metadata ``meta``.
    ``per_frame``: frame index -> track id -> [(box, score)] (undistorted); ``det_times``: frame index ->
    the boxes' time for that frame (empty for boxes converted from COCO, which carry none); ``fitters``:
    (instrument, instance) -> the per-frame joint fit written as the joints outputs."""

    out: Path
    info: VideoInfo
    cam: CameraInput
    specs: list[PartSpec]
    notes: list[str]
    tracker: Tracker
    per_frame: dict[int, dict[int, list]]
    det_times: dict[int, float]
    meta: dict
    fitters: dict = field(default_factory=dict)


def _prepare(video: Path, boxes: Path, opts: AnnotateOptions, checkpoint: tuple | None) -> _Run:
    """Check the inputs of a run (video, intrinsics, boxes, model, outputs; :class:`InputError` naming the
    file on the first problem) and build its tracker and joint fitters."""
    from surftrack.model.checkpoint import load_checkpoint
    from surftrack.paths import default_model_path
    from surftrack.pose import PoseEstimator

    info = probe_video(video)
    size = (info.width, info.height)
    doc = load_boxes(boxes, size)
    camera = opts.camera
    if camera is None:
        camera = next((c for c in (video.with_suffix(".camera.json"), video.parent / "camera.json") if c.is_file()),
                      None)
        if camera is None:
            raise InputError(f"{video}: no intrinsics: pass --camera camera.json (K, width, height), or put a "
                             f"camera.json beside the video")
    cam = load_camera(camera, size)
    check_span(opts.start, opts.end)
    if opts.start is not None and info.duration_s and opts.start >= info.duration_s:
        raise InputError(f"{video}: --start {opts.start:g} s is past the end of the video "
                         f"({info.duration_s:.2f} s)")
    model_path = Path(opts.model) if opts.model is not None else default_model_path()
    if not model_path.is_file():
        raise InputError(f"{model_path}: no such model file (pass --model, or train one with `surftrack train`)")
    out = Path(opts.out) if opts.out is not None else video.with_suffix(".mcap")
    _check_outputs(video, boxes, Path(camera), model_path, out, opts, size)
    model, train_cfg = checkpoint or load_checkpoint(model_path, opts.device or "cpu")[:2]
    specs, notes = match_parts(doc, model, str(boxes), opts.instruments)
    if opts.export_tum is not None:
        _check_tum_names(boxes, specs)
    estimator = PoseEstimator(model, opts.config.estimator_preset(), device=opts.device,
                              crop_size=train_cfg.data.crop, box_scale=train_cfg.data.scale,
                              instruments=opts.instruments)
    config = opts.config.for_fps(info.fps)  # the keyframe bound in seconds, as frames of this video
    tracker = Tracker(estimator, cam.K, size, specs, config, opts.instruments)
    det_times = {} if doc.get("meta", {}).get("converted_from") == "coco" else \
        {int(f["index"]): float(f["time"]) for f in doc["frames"]}
    meta = {"video": str(video), "boxes": str(boxes), "camera": str(camera), "model": str(model_path),
            "config": config.to_dict(), "surftrack_version": __version__,
            "parts": {s.name: {"track_id": s.track_id, "obj_id": s.obj_id} for s in specs}}
    run = _Run(out, info, cam, specs, notes, tracker, _frame_boxes(doc, cam), det_times, meta)
    joints = opts.joints or opts.joints_csv is not None
    if joints or opts.config.kinematic:
        from surftrack.pose.kinematic import described_instrument, instrument_parts
        from surftrack.track.articulation import ArticulationTracker

        by_instrument = instrument_parts(model.parts)
        for inst in sorted({s.instrument for s in specs}):
            described, why = described_instrument(inst, by_instrument[inst], caller_reports=True,
                                                  registry=opts.instruments)
            if described is None:
                lost = " and ".join(w for w, on in (("no joint angles", joints),
                                                    ("no instrument-consistent fit", opts.config.kinematic)) if on)
                notes.append(f"{why}: {lost} for it")
            elif joints:
                run.fitters.update({(s.instrument, s.instance): ArticulationTracker(described)
                                    for s in specs if s.instrument == inst})
    return run


def _open_sinks(stack: contextlib.ExitStack, run: _Run, opts: AnnotateOptions, timing: Counter
                ) -> tuple[object, list[FrameSink], dict[str, str]]:
    """Open the run's outputs on ``stack`` (each closed and finalised by it, however the run ends): the
    MCAP first (before heavy work), then the overlay, TUM and joints sinks asked for. Returns the MCAP's
    :class:`~surftrack.io.TrackWriter`, the sinks and the outputs' paths by kind."""
    from surftrack.io import TrackWriter

    outputs = {"mcap": str(run.out)}
    writer = stack.enter_context(TrackWriter(run.out, run.meta))
    stack.callback(run.tracker.close)
    sinks: list[FrameSink] = [McapSink(writer, run.specs, run.cam.K, images=opts.mcap_images)]
    if opts.overlay is not None:
        from surftrack.io.overlay import OverlayWriter

        outputs["overlay"] = str(opts.overlay)
        sinks.append(OverlaySink(stack.enter_context(
            OverlayWriter(opts.overlay, run.info.fps, run.info.width, run.info.height, run.cam.K))))
    if opts.export_tum is not None:
        from surftrack.io.tum import TumWriter

        outputs["tum"] = str(opts.export_tum)
        sinks.append(TumSink(stack.enter_context(TumWriter(opts.export_tum))))
    joints_csv = None
    if opts.joints_csv is not None:
        from surftrack.io.joints_csv import JointCsvWriter

        outputs["joints_csv"] = str(opts.joints_csv)
        joints_csv = stack.enter_context(JointCsvWriter(opts.joints_csv))
    if run.fitters:
        sinks.append(JointsSink(writer, run.fitters, joints_csv, timing))
    return writer, sinks, outputs


def annotate_video(video: str | Path, boxes: str | Path, opts: AnnotateOptions | None = None,
                   on_frame: Callable[[int, float, list[PartState]], None] | None = None,
                   checkpoint: tuple | None = None) -> dict:
    """Track ``video`` with the detections ``boxes``; returns a summary (frames, frames/s, statuses per
    part, outputs; ``partial``: None, or for a video that stops decoding part of the way through, what was
    tracked: ``frames_decoded``, ``frames_in_video`` (0 when the container does not say),
    ``stopped_at_s`` (the last decoded frame's time) and ``error``). ``on_frame(index, time_s, states)``
    is called after every processed frame. ``checkpoint``: (model, training config) already loaded from
    ``opts.model`` (a batch worker loads it once for all its videos)."""
    from tqdm import tqdm

    opts = opts or AnnotateOptions()
    video, boxes = Path(video), Path(boxes)
    run = _prepare(video, boxes, opts, checkpoint)
    info, cam, tracker, per_frame, det_times = run.info, run.cam, run.tracker, run.per_frame, run.det_times
    notes = run.notes
    undistort = cam.undistorter()
    half_frame = 0.5 / info.fps
    counts = {s.name: Counter() for s in run.specs}
    conf_sum = {s.name: 0.0 for s in run.specs}
    timing = Counter()
    n_done, t_first, last_t = 0, None, None
    with contextlib.ExitStack() as outputs_open:  # every output is finished, whatever stops the run
        writer, sinks, outputs = _open_sinks(outputs_open, run, opts, timing)
        bar = tqdm(total=_frames_to_read(info, opts.end), unit="frame", desc=video.name,
                   disable=not opts.progress)
        keep_frames = opts.overlay is not None or opts.mcap_images

        unwritten: deque = deque()  # frames the smoother let go that are not written yet

        def release(ready: list, notify: bool = True) -> None:
            """Write ``ready`` (and anything an interruption left unwritten), oldest first."""
            nonlocal n_done
            unwritten.extend(ready)
            while unwritten:
                (index, t_s, frame, states), steps = unwritten.popleft()
                states = [s.settle(steps, opts.config) for s in states]
                for s in states:
                    counts[s.spec.name][s.status] += 1
                    conf_sum[s.spec.name] += s.confidence
                for sink in sinks:
                    sink.write(index, t_s, frame, states)
                n_done += 1  # its outputs are written: counted even when on_frame stops the run
                if notify and on_frame is not None:
                    on_frame(index, t_s, states)

        # frames wait here until the smoother has seen enough of their future (none when causal)
        smoother = LagSmoother(round(opts.config.smooth_lag_s * info.fps), prior=opts.config.smoother_prior())
        wall0 = time.perf_counter()
        index, read_to_end, partial = -1, False, None

        def track_frames() -> None:
            nonlocal index, read_to_end, partial, last_t, t_first
            try:
                for index, (t_s, frame) in enumerate(_video_frames(video)):
                    if opts.start is not None and t_s < opts.start - 1e-9:
                        bar.update(1)
                        continue
                    if opts.end is not None and t_s > opts.end + 1e-9:
                        break
                    if last_t is not None and t_s <= last_t:
                        raise InputError(f"{video}: frame {index} has time {t_s:.6f} s, not after the previous "
                                         f"frame's {last_t:.6f} s (broken timestamps; remux the video)")
                    last_t = t_s
                    if index in det_times and abs(det_times[index] - t_s) > half_frame:
                        raise InputError(f"{boxes}: frame {index} is at {det_times[index]:.3f} s there but at "
                                         f"{t_s:.3f} s in {video}: the boxes belong to another video or frame rate")
                    frame = undistort(frame)
                    if t_first is None:
                        t_first = t_s
                        writer.camera_calibration(t_s, cam.K, info.width, info.height)
                    t0 = time.perf_counter()
                    states = tracker.step(frame, t_s, per_frame.get(index))
                    timing["track_s"] += time.perf_counter() - t0
                    release(smoother.push((index, t_s, frame if keep_frames else None, states),
                                          filter_steps(states), ended_revisions(states)))
                    bar.update(1)
                    bar.set_postfix(fps=f"{n_done / max(time.perf_counter() - wall0, 1e-9):.1f}")
                else:
                    read_to_end = True
            except DecodeError as e:  # keep what decoded: the outputs close normally and the summary says so
                if n_done + len(smoother) == 0:
                    raise
                partial = {"frames_decoded": index + 1, "frames_in_video": info.frames, "stopped_at_s": last_t,
                           "error": str(e)}
            release(smoother.flush())  # the last frames, smoothed with the future there is

        try:
            track_frames()
        except KeyboardInterrupt as e:  # Ctrl-C or a stop signal: what was tracked is written, then closed
            release(smoother.flush(), notify=False)
            e.outputs = list(outputs.values())
            e.frames_done = n_done
            raise
        except BaseException:
            release(smoother.flush(), notify=False)  # what was tracked before the error is written too
            raise
        finally:
            bar.close()
        wall = time.perf_counter() - wall0
    if n_done == 0:
        raise InputError(f"{video}: no frame between --start and --end")
    beyond = sorted(k for k in per_frame if k > index)
    if read_to_end and beyond:
        notes.append(f"{boxes}: boxes for {len(beyond)} frame(s) after the video's last frame ({index}), from "
                     f"{beyond[0]}: frames are numbered from 0; were these numbered from 1, or made for "
                     f"another video?")
    return {"video": str(video), "frames": n_done, "partial": partial, "seconds": wall,
            "fps": n_done / max(wall, 1e-9),
            "track_ms_per_frame": 1e3 * timing["track_s"] / n_done,
            "joints_ms_per_frame": 1e3 * timing["joints_s"] / n_done, "notes": notes,
            "parts": {name: {"frames": dict(c), "mean_confidence": conf_sum[name] / n_done}
                      for name, c in counts.items()},
            "outputs": outputs}


def best_boxes(detections: Sequence[Mapping], known, min_score: float) -> dict[int, tuple[tuple, float]]:
    """One frame's detections (det.json records: ``part_id``, ``bbox``, ``score``) reduced to each known part's
    highest-scoring box at ``min_score`` or above: track id -> (box (x, y, w, h), score). ``known``: the
    track ids to keep (any container)."""
    best: dict[int, tuple[tuple, float]] = {}
    for d in detections:
        pid = d["part_id"]
        if pid in known and d["score"] >= min_score and (pid not in best or d["score"] > best[pid][1]):
            best[pid] = (tuple(d["bbox"]), d["score"])
    return best


def score_per_frame(clip: str | Path, boxes: str | Path, model, train_cfg, cfg: TrackConfig, device: str | None = None,
                    instruments: InstrumentRegistry = BUILTIN) -> tuple[dict, dict, float]:
    """Per-frame estimation (no temporal model) of a synthetic clip (``surftrack synth-clip``: video.mp4,
    camera.json, gt.json) scored against its ground truth: every frame, each part the model knows from its
    best box in ``boxes`` with ``cfg``'s estimator preset and solver seed, then ``cfg``'s instrument fit.
    ``model`` and ``train_cfg``: a loaded checkpoint. Returns (per-part summary, tool-tip summary, frames/s),
    as :class:`~surftrack.track.clip_eval.TrackScore` reports them."""
    from surftrack.pose import PoseEstimator
    from surftrack.pose.kinematic import apply_kinematics
    from surftrack.track.clip_eval import ClipGroundTruth, TrackScore

    clip, boxes = Path(clip), Path(boxes)
    est = PoseEstimator(model, cfg.estimator_preset(), device=device, crop_size=train_cfg.data.crop,
                        box_scale=train_cfg.data.scale, instruments=instruments)
    K = np.asarray(json.loads((clip / "camera.json").read_text())["K"], np.float64)
    det = json.loads(boxes.read_text())
    per_frame = {f["index"]: f["detections"] for f in det["frames"]}
    specs = {s.track_id: s for s in match_parts(det, model, str(boxes), instruments)[0]}
    kin = cfg.kinematic_config()
    tools = {}
    for s in specs.values():
        # an instrument ``instruments`` does not know still scores per part; only its tool tip is left out
        with contextlib.suppress(Exception):
            tools.setdefault(s.instrument, instruments.load(s.instrument))
    score = TrackScore(ClipGroundTruth(clip / "gt.json"), instruments=tools)
    t0, n = time.perf_counter(), 0
    for index, (t_s, frame) in enumerate(read_video_frames(clip / "video.mp4")):
        best = best_boxes(per_frame.get(index, []), specs, cfg.min_box_score)
        pids = sorted(best)
        groups = [specs[p].instance for p in pids]
        res = (est.estimate(frame, [(specs[p].obj_id, best[p][0]) for p in pids], K,
                            groups=groups if cfg.twin_boxes else None) if pids else [])
        if kin is not None:
            res = apply_kinematics(res, groups, model.parts, kin, instruments)
        got = {p: r for p, r in zip(pids, res) if r.ok}
        states = [PartState(s, "keyframe" if p in got else "lost",
                            float(1.0 - np.exp(-max(got[p].score, 0.0))) if p in got else 0.0,
                            got[p].R if p in got else None, got[p].t if p in got else None, None)
                  for p, s in specs.items()]
        score.add_frame(index, t_s, states)
        n += 1
    return score.summary(), score.tip_summary(), n / max(time.perf_counter() - t0, 1e-9)


def _pooled(summary: Mapping[str, Mapping], parts: Sequence[str], key: str) -> float:
    """A per-part percentage of :meth:`TrackScore.summary` (``key``) over the parts' visible frames pooled
    (a part without it, as its instrument has no roll twin, counts with its ``add10_pct``)."""
    hits = sum((summary[n][key] if summary[n][key] is not None else summary[n]["add10_pct"])
               / 100.0 * summary[n]["visible_frames"] for n in parts)
    return 100.0 * hits / max(sum(summary[n]["visible_frames"] for n in parts), 1)


def evaluate_clips(checkpoint: str | Path, names: list[str], folders: dict[str, Path], seeds: list[int],
                   preset: str = "fast", views: int = 0, kinematic: bool = True, device: str | None = None,
                   instruments: InstrumentRegistry = BUILTIN, progress: bool = False,
                   anchor_views: int = 0) -> dict[str, dict]:
    """:func:`score_per_frame` on each clip (``folders[name]``, with its own det.json) for every solver seed
    (``views`` crop views per box, ``anchor_views`` for the fit's anchor; 0: the preset's):
    name -> {"frames": n, "parts": {part: ADD-10 % mean over seeds}, "per_seed": [ADD-10 % over all
    part-frames, per seed], "per_seed_twin": the same with roll twins counted as a symmetry, or None}, what
    :func:`surftrack.pose.suite.clip_table` prints. A part's column is its name, or
    ``instrument.instance.part`` where several instruments are scored."""
    from surftrack.model.checkpoint import load_checkpoint

    model, train_cfg, _ = load_checkpoint(checkpoint, device or "cpu")
    # the estimator's figures: its jaws' box assignment on, as in ``surftrack eval``'s image sets
    base = TrackConfig(preset=preset, views=views, kinematic=kinematic, twin_boxes=True, anchor_views=anchor_views)
    table = {}
    for name in names:
        folder = Path(folders[name])
        runs = []
        for seed in seeds:
            summary = score_per_frame(folder, folder / "det.json", model, train_cfg, base.replace(solver_seed=seed),
                                      device, instruments)[0]
            runs.append(summary)
            if progress:
                print(f"clip {name}, solver seed {seed}: ADD-10 " + ", ".join(
                    f"{k} {v['add10_pct']:.1f}" for k, v in summary.items()) + " %")
        parts = list(runs[0])
        label = {n: n.rsplit(".", 1)[-1] if len({m.rsplit(".", 1)[0] for m in parts}) == 1 else n for n in parts}
        table[name] = {
            "frames": len(json.loads((folder / "gt.json").read_text())["frames"]),
            "parts": {label[n]: float(np.mean([r[n]["add10_pct"] for r in runs])) for n in parts},
            # pooled over part-frames: each part weighs by its visible frames
            "per_seed": [_pooled(r, parts, "add10_pct") for r in runs],
            "per_seed_twin": ([_pooled(r, parts, "add10_twin_pct") for r in runs]
                              if any(r[n]["add10_twin_pct"] is not None for r in runs for n in parts) else None)}
    return table

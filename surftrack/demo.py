"""``surftrack demo``: the main job end to end on built-in data, with no download and no GPU.

1. Make a short synthetic clip (``surftrack synth-clip``): the Large Needle Driver moving under its trocar,
   crossed by a second tool (occlusion), leaving the view and coming back; with its det.json and ground
   truth.
2. Track it with the bundled default model (``surftrack VIDEO --boxes det.json``): MCAP for Foxglove
   (with JPEG frames and annotations), an overlay video and TUM trajectories.
3. Score the tracks against the ground truth (per part ADD-10, RE, TE, jitter) and write a summary.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from surftrack.annotate import AnnotateOptions, annotate_video
from surftrack.jsonsafe import json_safe
from surftrack.synth.clip import ClipConfig, make_clip
from surftrack.track import load_track_config
from surftrack.instruments import load_instrument
from surftrack.track.clip_eval import ClipGroundTruth, TrackScore, format_summary, format_tip_summary


def run_demo(out_dir: Path, seconds: float = 6.0, fps: float = 15.0, seed: int = 0, model: str | None = None,
             progress: bool = True) -> dict:
    """Make the clip, track it, score it; everything goes to ``out_dir``. Returns the summary (also
    written to ``summary.json`` and, as a table, ``summary.md``)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    clip_dir = out_dir / "clip"
    clip = make_clip(clip_dir, "lnd", ClipConfig(seconds=seconds, fps=fps), seed=seed, progress=progress)
    t_clip = time.perf_counter() - t0
    lnd = load_instrument("lnd")
    score = TrackScore(ClipGroundTruth(clip_dir / "gt.json"), instruments={lnd.name: lnd})
    opts = AnnotateOptions(model=model, camera=clip_dir / "camera.json", out=out_dir / "tracks.mcap",
                           config=load_track_config(), overlay=out_dir / "overlay.mp4",
                           export_tum=out_dir / "tum", mcap_images=True, progress=progress)
    run = annotate_video(clip_dir / "video.mp4", clip_dir / "det.json", opts,
                         on_frame=lambda i, t, states: score.add_frame(i, t, states))
    accuracy, tips = score.summary(), score.tip_summary()
    summary = {
        "clip": {"folder": str(clip_dir), "seconds": seconds, "fps": fps, "seed": seed,
                 "frames_out_of_view": clip.get("main_out_of_view_frames"), "frames_occluded": clip.get("occluded_frames"),
                 "made_in_s": round(t_clip, 1)},
        "tracking": {k: run[k] for k in ("frames", "seconds", "fps", "track_ms_per_frame", "notes", "parts")},
        "accuracy": accuracy,
        "tool_tip": tips,
        "outputs": run["outputs"],
        "total_s": round(time.perf_counter() - t0, 1),
    }
    (out_dir / "summary.json").write_text(json.dumps(json_safe(summary), indent=2, allow_nan=False))
    (out_dir / "summary.md").write_text(
        f"Tracking {run['frames']} frames at {run['fps']:.1f} frames/s. Against the ground truth (ADD-10 with "
        f"the SurgRIPE diameter; frames where the part is visible, a frame without a pose counts as a miss):\n\n"
        + format_summary(accuracy) + "\n" + format_tip_summary(tips))
    return summary

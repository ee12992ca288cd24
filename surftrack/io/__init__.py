"""Output formats: MCAP tracking logs for Foxglove, overlay videos, TUM trajectories, joint-track CSV,
summaries of a tracking log, and video reading and writing.

io is the last stage, with one exception: :mod:`surftrack.io.video` is a leaf module (it imports nothing
from surftrack) that earlier stages may import, as :mod:`surftrack.synth.clip` does to write its clips.
So that importing it does not import the rest of io (and the later stages those modules use), this
package imports its modules lazily: ``from surftrack.io import TrackWriter`` loads
:mod:`surftrack.io.mcap_writer` on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

# name -> the module of this package that defines it
_EXPORTS = {
    "analyze_mcap": "analyze", "format_analysis": "analyze", "plot_analysis": "analyze",
    "JOINT_CSV_COLUMNS": "joints_csv", "JointCsvWriter": "joints_csv", "write_joint_csv": "joints_csv",
    "SCHEMAS": "mcap_writer", "TrackWriter": "mcap_writer", "time_to_ns": "mcap_writer",
    "OverlayWriter": "overlay", "PartOverlay": "overlay", "draw_overlay": "overlay", "mesh_outline": "overlay",
    "project_axes": "overlay",
    "TumWriter": "tum", "read_tum": "tum",
    "VideoWriter": "video", "read_video_frames": "video",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    """The exported ``name``, imported from its module on first access (PEP 562)."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))

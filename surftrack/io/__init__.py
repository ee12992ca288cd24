"""Output formats: MCAP tracking logs for Foxglove, overlay videos, TUM trajectories, joint-track CSV,
and summaries of a tracking log."""

from surftrack.io.analyze import analyze_mcap, format_analysis, plot_analysis
from surftrack.io.joints_csv import JOINT_CSV_COLUMNS, JointCsvWriter, write_joint_csv
from surftrack.io.mcap_writer import SCHEMAS, TrackWriter, time_to_ns
from surftrack.io.overlay import OverlayWriter, PartOverlay, draw_overlay, mesh_outline, project_axes
from surftrack.io.tum import TumWriter, read_tum

__all__ = [
    "JOINT_CSV_COLUMNS", "JointCsvWriter", "OverlayWriter", "PartOverlay", "SCHEMAS", "TrackWriter", "TumWriter", "analyze_mcap",
    "draw_overlay", "format_analysis", "mesh_outline", "plot_analysis", "project_axes", "read_tum",
    "time_to_ns", "write_joint_csv",
]

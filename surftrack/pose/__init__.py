"""Per-part 6D pose estimation with SurfSurg6D (SurfEmb-style inference), batched and vectorised.

``PoseEstimator(checkpoint_or_model, preset="accurate" | "fast").estimate(image, boxes, K)`` -> one
:class:`PartPose` per box. Modules: :mod:`.p3p` (batched P3P / 4-point solver), :mod:`.surface` (cached
surface keys), :mod:`.correspondence` (correspondence distributions on the downsampled grid),
:mod:`.hypotheses`, :mod:`.scoring`, :mod:`.refine`, :mod:`.solver` (the per-crop pipeline),
:mod:`.preset`, :mod:`.estimator`, :mod:`.kinematic` (instrument-consistent poses from the part estimates),
:mod:`.evaluate` (evaluation on a BOP split: metrics, tables, BOP CSV)
and :mod:`.synthetic` (correspondence fields from rendered object coordinates, for tests and benchmarks).
"""

from surftrack.pose.correspondence import CorrField, build_field, grid_camera, pool_to_grid
from surftrack.pose.evaluate import evaluate, evaluate_seeds, markdown_table, seed_table, summarize, write_eval_outputs
from surftrack.pose.estimator import PartPose, PoseEstimator
from surftrack.pose.p3p import p3p, p4p, solve_quartic
from surftrack.pose.preset import PRESETS, Preset, get_preset
from surftrack.pose.solver import Solution, solve_field
from surftrack.pose.surface import SurfaceBank, clear_bank_cache, part_bank

__all__ = ["CorrField", "PRESETS", "PartPose", "PoseEstimator", "Preset", "Solution", "SurfaceBank",
           "build_field", "clear_bank_cache", "evaluate", "evaluate_seeds", "get_preset", "grid_camera",
           "markdown_table", "p3p", "p4p", "part_bank", "pool_to_grid", "seed_table", "solve_field", "solve_quartic",
           "summarize", "write_eval_outputs"]

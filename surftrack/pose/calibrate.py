"""A trained network's depth bias, per part, measured on images it was not trained on and stored in its
checkpoint (``PartInfo.depth_scale``) for :class:`~surftrack.pose.estimator.PoseEstimator` to remove.

Why: one camera sees depth only through a part's apparent size, and the bundled model's correspondences
make some parts look larger than they are. Measured on fresh images (the paper's ranges and the whole
reach, 150 each, solver seeds 0-2, per-part poses, no instrument fit), stage 7 placed the jaws 2.3-2.9 %
too close, the wrist 0.6 % too close and the shaft 0.7 % too far, the same within about half a percent on
either set and at every grid stride and mask threshold of the solver: a property of the trained weights,
not of the solver. At 80 mm from the lens the jaws' 2 mm is more than their ADD-10 threshold (1.3 mm);
through the instrument fit the whole instrument sat about 1.2 % (1 mm) too close.

How: per-part poses (no instrument fit, so each part shows its own bias) on one or more BOP datasets with
several solver seeds; per part the median of :func:`~surftrack.pose.evaluate.depth_error_rel` over the
estimates that are right up to scale (relative depth error within ``max_rel``, rotation within
``max_re_deg``: a wrong pose says nothing about the scale); the part's factor becomes its current one
times ``1 / (1 + median)``, so calibrating a calibrated model refines it. A part with fewer than
``min_count`` such estimates keeps its factor.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from surftrack.model.checkpoint import FORMAT, CheckpointError, load_checkpoint


@dataclass(frozen=True)
class DepthBias:
    """One part's measurement: ``n`` estimates right up to scale, their median relative depth error
    ``bias`` (None below ``min_count``), the part's factor before and after."""

    obj_id: int
    part: str
    n: int
    bias: float | None
    scale_before: float
    scale: float


def measure_depth_bias(checkpoint, data_dirs: Sequence[str | Path], split: str = "train",
                       preset: str = "fast", seeds: Sequence[int] = (0, 1, 2), max_rel: float = 0.1,
                       max_re_deg: float = 20.0, min_count: int = 50, device: str | None = None,
                       progress: bool = False) -> list[DepthBias]:
    """Each part's depth bias on the datasets ``data_dirs`` (BOP folders with ``split``) and the factor
    that removes it (see the module docstring), one entry per part of the model. ``checkpoint``: a path,
    or a :class:`~surftrack.pose.estimator.PoseEstimator` (``preset`` and ``device`` are then its own).
    Raises :class:`surftrack.data.DatasetError` and :class:`~surftrack.model.checkpoint.CheckpointError`
    as :func:`~surftrack.pose.evaluate.evaluate` does."""
    from surftrack.pose.estimator import PoseEstimator
    from surftrack.pose.evaluate import evaluate_seeds

    if not data_dirs:
        raise ValueError("depth calibration needs at least one dataset")
    if not (0 < max_rel < 1 and 0 < max_re_deg <= 180 and min_count >= 1):
        raise ValueError(f"need 0 < max_rel < 1, 0 < max_re_deg <= 180 and min_count >= 1, got {max_rel}, "
                         f"{max_re_deg}, {min_count}")
    est = checkpoint if isinstance(checkpoint, PoseEstimator) else PoseEstimator(checkpoint, preset, device=device)
    errors: dict[int, list[float]] = {p.obj_id: [] for p in est.model.parts}
    for data in data_dirs:
        for result in evaluate_seeds(est, data, list(seeds), split=split, progress=progress):
            for r in result["instances"]:
                e, rot = r.get("depth_err_rel"), r.get("re")
                if e is not None and rot is not None and abs(e) < max_rel and math.isfinite(rot) and rot < max_re_deg:
                    errors[r["obj_id"]].append(e)
    out = []
    for p in est.model.parts:
        e = errors[p.obj_id]
        bias = float(np.median(e)) if len(e) >= min_count else None
        scale = p.depth_scale / (1.0 + bias) if bias is not None else p.depth_scale
        out.append(DepthBias(p.obj_id, p.name, len(e), bias, p.depth_scale, float(scale)))
    return out


def write_depth_scales(src: str | Path, dst: str | Path, biases: Sequence[DepthBias], about: dict) -> Path:
    """Copy checkpoint ``src`` to ``dst`` (atomically; may be the same file) with each measured part's
    ``depth_scale`` set and ``about`` (what it was measured on) kept under ``extra.depth_calibration``.
    Everything else, the weights included, is copied unchanged."""
    src, dst = Path(src), Path(dst)
    load_checkpoint(src)  # the usual checks and messages for a bad file
    blob = torch.load(src, map_location="cpu", weights_only=True)
    if blob.get("format") != FORMAT:
        raise CheckpointError(f"{src}: not a surftrack SurfSurg6D checkpoint")
    by_id = {b.obj_id: b for b in biases}
    for part in blob["parts"]:
        b = by_id.get(int(part["obj_id"]))
        if b is not None:
            part["depth_scale"] = float(b.scale)
    blob["extra"] = {**(blob.get("extra") or {}), "depth_calibration": dict(about)}
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(dst.name + ".tmp")
    torch.save(blob, tmp)
    os.replace(tmp, dst)
    return dst


def format_depth_biases(biases: Sequence[DepthBias]) -> str:
    """A markdown table of :func:`measure_depth_bias`'s result."""
    lines = ["| part | estimates right up to scale | depth bias (%) | depth scale before -> after |",
             "|---|---|---|---|"]
    for b in biases:
        bias = "too few" if b.bias is None else f"{100 * b.bias:+.2f}"
        lines.append(f"| {b.part} | {b.n} | {bias} | {b.scale_before:.4f} -> {b.scale:.4f} |")
    return "\n".join(lines) + "\n"

"""Where the estimator fails: an evaluation's ADD-10 binned by the conditions of each instance.

A synthetic set made by ``surftrack synth`` records, per instance, the instrument's joint angles
(``scene_gt.json``'s ``joints_deg``) next to BOP's visibility and boxes. Binning the per-instance
results of :func:`~surftrack.pose.evaluate.evaluate` by depth, visible box size, visible fraction and
each joint separates the candidate causes of failure (small far parts, occlusion, strong pitch or yaw,
a tool rolled away from what the model was trained on) on one set; a set made to isolate one cause then
confirms it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: (title, key, bin edges) of the tables :func:`cause_tables` prints.
BINS: tuple[tuple[str, str, tuple[float, ...]], ...] = (
    ("depth z (mm)", "z", (0, 60, 80, 100, 130, np.inf)),
    ("visible box side (px)", "side", (0, 40, 60, 90, 140, np.inf)),
    ("visible fraction", "visib", (0, 0.5, 0.75, 0.9, 1)),
    ("|roll| (deg)", "roll", (0, 30, 60, 120, 180)),
    ("|pitch| (deg)", "pitch", (0, 20, 40, 60, 90)),
    ("|yaw| (deg)", "yaw", (0, 20, 40, 60, 90)),
)


@dataclass(frozen=True)
class InstanceConditions:
    """One evaluated instance: its part label, whether ADD-10 (SurgRIPE diameter) holds, and its
    conditions: depth ``z`` (mm), the visible box's longer side (px), visible fraction and |joint| (deg)."""

    part: str
    add10: bool
    values: Mapping[str, float]
    add10_twin: bool | None = None  # with the instrument's roll twin counted as a symmetry (None: not scored)


def instance_conditions(result: Mapping, data_dir: str | Path, split: str = "test") -> list[InstanceConditions]:
    """Join an evaluation result (``evaluate``'s dict or its JSON) with the set's ground truth (read by
    :class:`~surftrack.data.BopDataset`): depth, visible box, visible fraction, and the joint angles a
    set made by ``surftrack synth`` records with each instance (other BOP sets get no joint bins)."""
    from surftrack.data.bop import BopDataset

    bop = BopDataset(data_dir, split, min_visib_fract=0.0, min_px_visib=0, load_models_now=False)
    gt = {(i.scene_id, i.im_id, i.gt_index): i for i in bop.instances}
    out = []
    for r in result["instances"]:
        inst = gt[(int(r["scene_id"]), int(r["im_id"]), int(r["gt_index"]))]
        w, h = inst.bbox_visib[2:]  # BOP: xmax - xmin over pixel indices; an unseen instance has -1
        values = {"z": float(inst.t[2]), "side": float(max(w, h) + 1 if min(w, h) >= 0 else 0),
                  "visib": float(inst.visib_fract)}
        values.update({k: abs(float(v)) for k, v in (inst.extra.get("joints_deg") or {}).items()})
        twin = r.get("add10_twin_surgripe")
        out.append(InstanceConditions(str(r["part"]), bool(r["add10_surgripe"]), values,
                                      None if twin is None else bool(twin)))
    return out


def cause_tables(conditions: Sequence[InstanceConditions], bins=BINS) -> str:
    """Markdown: per condition, ADD-10 (%) and the instance count per bin, for all parts and per part.
    Bins are [lo, hi); the last one also takes what lies beyond."""
    parts = sorted({c.part for c in conditions})
    lines = [f"{len(conditions)} instances, ADD-10 {100 * np.mean([c.add10 for c in conditions]):.1f} %"
             if conditions else "no instances", ""]
    for title, key, edges in bins:
        have = [c for c in conditions if key in c.values]
        if not have:
            continue
        heads = [f"{lo:g}-{hi:g}" if np.isfinite(hi) else f">= {lo:g}" for lo, hi in zip(edges[:-1], edges[1:])]
        lines += [f"| {title} | " + " | ".join(heads) + " |", "|---|" + "---|" * len(heads)]
        for part in ["all parts", *parts]:
            sel = [c for c in have if part == "all parts" or c.part == part]
            cells = [f"{100 * np.mean([c.add10 for c in b]):.0f} ({len(b)})" if b else "-"
                     for b in _binned(sel, key, edges)]
            lines.append(f"| {part} | " + " | ".join(cells) + " |")
        lines.append("")
    roll_edges = {k: e for _, k, e in bins}.get("roll")
    twins = [c for c in conditions if c.add10_twin is not None and "roll" in c.values]
    if twins and roll_edges is not None:
        # a tool rolled away from the training range mostly fails as its roll twin (instruments.twin)
        heads = [f"{lo:g}-{hi:g}" for lo, hi in zip(roll_edges[:-1], roll_edges[1:])]
        lines += ["ADD-10 (%) as scored / with the instrument's roll twin counted as a symmetry, by |roll| (deg):", "",
                  "| part | " + " | ".join(heads) + " |", "|---|" + "---|" * len(heads)]
        for part in ["all parts", *parts]:
            sel = [c for c in twins if part == "all parts" or c.part == part]
            cells = [f"{100 * np.mean([c.add10 for c in b]):.0f} / {100 * np.mean([c.add10_twin for c in b]):.0f} "
                     f"({len(b)})" if b else "-" for b in _binned(sel, "roll", roll_edges)]
            lines.append(f"| {part} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _binned(conditions: Sequence[InstanceConditions], key: str,
            edges: Sequence[float]) -> list[list[InstanceConditions]]:
    """``conditions`` per bin [lo, hi) of ``values[key]``; the last bin also holds its upper edge and what
    lies beyond (a fraction of 1, 180 deg)."""
    last = len(edges) - 2
    return [[c for c in conditions if lo <= c.values[key] < hi or (k == last and c.values[key] >= hi)]
            for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:]))]

"""Evaluate a SurfSurg6D checkpoint on a BOP split: per-instance pose errors, per-part summaries split by
occlusion (the layout of the paper's SurgRIPE table), timings, and the output files.

``evaluate(checkpoint, data_dir, split="test", preset="accurate")`` runs :class:`PoseEstimator` on every
instance of the split with the GROUND-TRUTH visible box (``bbox_visib`` ->
:func:`surftrack.geometry.box_from_bop`), several images per :meth:`PoseEstimator.estimate_batch` call, and
returns a JSON-ready dict;
``write_eval_outputs(result, "out/eval.json")`` writes the JSON, a markdown table (``.md``), a BOP results
CSV (``.bop.csv``) and an ADD accuracy-threshold plot (``.png``) next to each other.

Definitions (all errors from :mod:`surftrack.eval`, bop_toolkit's definitions):

* RE: geodesic rotation error (deg); TE: ``||t_e - t_g||`` (mm); ADD / ADD-S: mean (closest-)point distance
  over the model's mesh vertices (mm; at most ``max_points`` vertices, a fixed random subset beyond that).
* ADD-10: fraction of instances with ADD < 10 % of the part's diameter, ALWAYS reported under both diameter
  conventions: ``add10_bop`` with the BOP diameter (largest distance between two model vertices,
  :func:`surftrack.eval.diameter_max_pairwise`) and ``add10_surgripe`` with the SurgRIPE one (the diagonal of
  the model's axis-aligned bounding box, :func:`surftrack.eval.diameter_bbox_diagonal`; >= the BOP one).
* Avg ACC 0-5 mm: area under the accuracy-vs-threshold curve of ADD on [0, 5] mm (VOCap,
  :func:`surftrack.eval.auc`), also for ADD-S.
* ``depth_err_rel`` (per instance): the signed depth error relative to the true distance
  (:func:`depth_error_rel`); the depth bias: its median over the estimates right up to scale (RE < 20 deg,
  depth within 10 %). Monocular depth is the pose's least certain direction, and the bundled model's small
  parts come out 2-3 % too close on still images (docs/decisions.md, "A depth calibration per part").
* Occlusion: SurgRIPE splits its scenes into occlusion / non-occlusion sequences; a BOP split has no such
  label, so an instance counts as OCCLUDED when its visible fraction (BOP ``visib_fract``, visible pixels /
  pixels of the unoccluded silhouette) is below ``occlusion_threshold`` (default 0.9), else NON-OCCLUDED.
* The "all" group (the table's "Avg" columns) pools every instance, and the "overall" entry (the table's
  "Avg" row) pools every part: both are instance-weighted, like the paper's Avg column (e.g. its MegaPose
  row: 132.30 / 125.96 -> 129.83, not the plain mean of the two).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
import warnings
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from surftrack.eval import add, adds, auc, diameter_bbox_diagonal, diameter_max_pairwise, re, te
from surftrack.geometry import box_from_bop
from surftrack.instruments import BUILTIN, InstrumentRegistry
from surftrack.jsonsafe import json_safe
from surftrack.pose.kinematic import (
    KinematicConfig,
    apply_kinematics,
    check_anchor,
    described_instrument,
    instrument_parts,
)

__all__ = ["GROUPS", "evaluate", "evaluate_seeds", "group_stats", "markdown_table", "pose_errors", "seed_table",
           "summarize", "write_eval_outputs"]

#: Occlusion groups: key -> table heading.
GROUPS = {"non_occ": "Non-occ", "occ": "occ", "all": "Avg"}
_DNAME = {"bop": "BOP", "surgripe": "SurgRIPE"}
AUC_MAX_MM = 5.0
CURVE_MAX_MM = 10.0
DIAMETERS = {
    "bop": "BOP diameter: the largest distance between two model vertices (max pairwise)",
    "surgripe": "SurgRIPE diameter: the diagonal of the model's axis-aligned bounding box",
}


# ------------------------------------------------------------------------------------------ per instance
def pose_errors(R_e, t_e, R_g, t_g, pts: np.ndarray) -> dict[str, float]:
    """RE (deg), TE (mm), ADD and ADD-S (mm) of one estimate; non-finite estimates give inf errors."""
    R_e, t_e = np.asarray(R_e, np.float64), np.asarray(t_e, np.float64).reshape(3)
    if not (np.all(np.isfinite(R_e)) and np.all(np.isfinite(t_e))):
        return {"re": math.inf, "te": math.inf, "add": math.inf, "adds": math.inf}
    return {"re": re(R_e, R_g), "te": te(t_e, t_g), "add": add(R_e, t_e, R_g, t_g, pts),
            "adds": adds(R_e, t_e, R_g, t_g, pts)}


def depth_error_rel(t_e, t_g) -> float | None:
    """Signed depth error of an estimate relative to the true distance: the estimated translation's
    excess along the true line of sight, over the true distance (negative: too close to the camera; a
    factor ``1 / (1 + e)`` on the translation removes it). None for a non-finite estimate."""
    t_e, t_g = np.asarray(t_e, np.float64).reshape(3), np.asarray(t_g, np.float64).reshape(3)
    dist = float(np.linalg.norm(t_g))
    if not (np.all(np.isfinite(t_e)) and dist > 0):
        return None
    return float((t_e - t_g) @ t_g / dist ** 2)


def _finite(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def group_stats(records: Sequence[Mapping], diameters: Mapping[int, Mapping[str, float]]) -> dict:
    """Summary of a group of per-instance records (keys ``obj_id``, ``re``, ``te``, ``add``, ``adds``, and
    optionally ``ok``, ``add10_twin_surgripe``, ``depth_err_rel``); ``diameters[obj_id]`` = {"bop": mm,
    "surgripe": mm}. ADD-10 compares each instance with 10 % of ITS part's diameter; ``depth_bias`` is the
    median ``depth_err_rel`` of the ``depth_bias_count`` estimates right up to scale. Every statistic is None
    for an empty group."""
    n = len(records)
    keys = ("re_mean", "re_median", "te_mean", "te_median", "add_mean", "add_median", "adds_mean", "adds_median",
            "add10_bop", "add10_surgripe", "adds10_bop", "adds10_surgripe", "auc_add_0_5mm", "auc_adds_0_5mm")
    out: dict = {"count": n, "failures": sum(1 for r in records if not r.get("ok", True))}
    if n == 0:
        return out | {k: None for k in keys} | {"add10_twin_surgripe": None, "twin_count": 0, "depth_bias": None,
                                                 "depth_bias_count": 0}
    col = {k: np.array([float(r[k]) for r in records]) for k in ("re", "te", "add", "adds")}
    for k, v in col.items():
        out[f"{k}_mean"] = _finite(np.mean(v))
        out[f"{k}_median"] = _finite(np.median(v))
    for conv in DIAMETERS:
        d = np.array([float(diameters[int(r["obj_id"])][conv]) for r in records])
        out[f"add10_{conv}"] = float(np.mean(col["add"] < 0.1 * d))
        out[f"adds10_{conv}"] = float(np.mean(col["adds"] < 0.1 * d))
    out["auc_add_0_5mm"] = auc(col["add"], AUC_MAX_MM)
    out["auc_adds_0_5mm"] = auc(col["adds"], AUC_MAX_MM)
    twin = [bool(r["add10_twin_surgripe"]) for r in records if "add10_twin_surgripe" in r]
    out["add10_twin_surgripe"] = float(np.mean(twin)) if twin else None
    out["twin_count"] = len(twin)
    depth = [float(r["depth_err_rel"]) for r in records if _right_up_to_scale(r)]
    out["depth_bias"] = float(np.median(depth)) if depth else None
    out["depth_bias_count"] = len(depth)
    return {k: out[k] for k in ("count", "failures", *keys, "add10_twin_surgripe", "twin_count", "depth_bias",
                                "depth_bias_count")}


def _right_up_to_scale(record: Mapping) -> bool:
    """An estimate whose rotation is right (RE < 20 deg) and depth within 10 %: its depth error measures the
    estimator's depth bias (a wrong pose's says nothing about it)."""
    e, rot = record.get("depth_err_rel"), record.get("re")
    return e is not None and rot is not None and abs(float(e)) < 0.1 and float(rot) < 20.0


def summarize(records: Sequence[Mapping], parts: Mapping[int, Mapping], occlusion_threshold: float = 0.9) -> dict:
    """Per-part and overall statistics, each split into ``non_occ`` / ``occ`` / ``all``.

    ``records``: per-instance dicts with ``obj_id``, ``visib_fract``, ``re``, ``te``, ``add``, ``adds`` (and
    optionally ``ok``); ``parts[obj_id]``: {"label", "diameter_bop_mm", "diameter_surgripe_mm", ...}.
    An instance is occluded when ``visib_fract < occlusion_threshold``. Returns {"parts": {label: {...,
    "non_occ", "occ", "all"}}, "overall": {"non_occ", "occ", "all"}} (parts in obj_id order, only those
    with at least one record)."""
    diam = {int(o): {"bop": float(p["diameter_bop_mm"]), "surgripe": float(p["diameter_surgripe_mm"])}
            for o, p in parts.items()}

    def split(recs):
        occ = [r for r in recs if float(r["visib_fract"]) < occlusion_threshold]
        non = [r for r in recs if float(r["visib_fract"]) >= occlusion_threshold]
        return {"non_occ": group_stats(non, diam), "occ": group_stats(occ, diam), "all": group_stats(recs, diam)}

    by_obj: dict[int, list] = defaultdict(list)
    for r in records:
        by_obj[int(r["obj_id"])].append(r)
    out_parts = {}
    for o in sorted(by_obj):
        p = parts[o]
        out_parts[p["label"]] = {k: v for k, v in p.items() if k != "label"} | {"obj_id": o} | split(by_obj[o])
    return {"parts": out_parts, "overall": split(list(records))}


def accuracy_curve(errors: Iterable[float], thresholds: np.ndarray) -> list[float]:
    e = np.asarray(list(errors), np.float64)
    if e.size == 0:
        return [0.0] * len(thresholds)
    return [float(np.mean(e < d)) for d in thresholds]


# ------------------------------------------------------------------------------------------ evaluation
def part_labels(infos: Mapping[int, tuple[str, str]]) -> dict[int, str]:
    """obj_id -> the label results and tables use: "instrument part" (the part alone when the instrument is
    unnamed), with " (obj N)" where two parts would read alike. ``infos``: obj_id -> (instrument, part)."""
    raw = {o: (name if inst in ("", "unknown") else f"{inst} {name}") for o, (inst, name) in infos.items()}
    counts = defaultdict(int)
    for v in raw.values():
        counts[v] += 1
    return {o: (v if counts[v] == 1 else f"{v} (obj {o})") for o, v in raw.items()}


def _model_points(part, max_points: int) -> np.ndarray:
    v = np.asarray(part.mesh.vertices, np.float64)
    if len(v) > max_points:
        v = v[np.sort(np.random.default_rng(0).choice(len(v), max_points, replace=False))]
    return v


def _instrument_groups(instances: Sequence) -> list:
    """Instrument-instance key of each ground-truth instance of one image: ``instrument_index`` where the
    data has it, else one group per image unless an object repeats (then one group per instance: no fit)."""
    if all("instrument_index" in i.extra for i in instances):
        return [i.extra["instrument_index"] for i in instances]
    ids = [i.obj_id for i in instances]
    return [0] * len(ids) if len(set(ids)) == len(ids) else list(range(len(ids)))


def evaluate(checkpoint, data_dir, split: str = "test", preset="accurate", max_images: int | None = None,
             occlusion_threshold: float = 0.9, *, device=None, images_per_batch: int = 4,
             min_visib_fract: float = 0.1, min_px_visib: int = 64, max_points: int = 5000,
             images: Iterable[tuple[int, int]] | None = None, progress: bool = False,
             kinematic=None, instruments: InstrumentRegistry = BUILTIN) -> dict:
    """Run the estimator (a checkpoint path or a :class:`PoseEstimator`) on the split ``split`` of the BOP
    dataset ``data_dir`` with ground-truth boxes and return the JSON-ready result:

    ``{"checkpoint", "data_dir", "split", "preset", "views" (crop views per box), "part_views" (part name ->
    its own views, where it differs), "device", "n_images", "n_instances", "occlusion", "diameters",
    "parts": {label: {obj_id, instrument, part, diameter_bop_mm, diameter_surgripe_mm, non_occ|occ|all:
    stats}}, "overall": {non_occ|occ|all: stats}, "timings", "accuracy_curve",
    "instances": [...], "warnings": [...]}`` with stats as :func:`group_stats`.

    ``max_images``: only the first N images (in (scene_id, im_id) order); ``images``: only these
    (scene_id, im_id) pairs (e.g. the held-out images of a training run). ``kinematic`` (a
    :class:`surftrack.pose.kinematic.KinematicConfig`, or True for the defaults): evaluate the
    instrument-consistent poses of :func:`surftrack.pose.kinematic.apply_kinematics` instead of the raw
    per-part ones; the parts of an image are grouped by the ground truth's ``instrument_index`` (our
    generated data). Without it they are grouped by instrument name, which assumes one instance of each
    instrument per image (as in SurgRIPE); images that repeat an object are then not fitted.
    ``instruments``: where the fit finds the instruments' descriptions. Instances
    are those kept by
    :class:`BopDataset` with ``min_visib_fract`` / ``min_px_visib`` (BOP's 10 % visibility rule by default)
    whose object the model knows (others are counted in ``skipped_unknown_obj``). Raises
    :class:`surftrack.data.DatasetError` (bad data / split / empty selection) and
    :class:`surftrack.model.checkpoint.CheckpointError` (bad checkpoint)."""
    return _evaluate(checkpoint, data_dir, split, preset, max_images, occlusion_threshold, device=device,
                     images_per_batch=images_per_batch, min_visib_fract=min_visib_fract, min_px_visib=min_px_visib,
                     max_points=max_points, images=images, progress=progress, kinematic=kinematic,
                     instruments=instruments)[0]


def evaluate_seeds(checkpoint, data_dir, seeds: Sequence[int], **kwargs) -> list[dict]:
    """:func:`evaluate` once per pose-solver seed in ``seeds`` (replacing the preset's), with one network
    forward per batch for all of them: ``result[k]`` equals ``evaluate`` with the preset's seed set to
    ``seeds[k]``, except for the timings (each seed's per-image time is its poses' stage timings, the
    shared forward counted in each). On ~100 images ADD-10 moves by a few points with the seed, so compare
    models on the mean over seeds (:func:`seed_table`). ``kwargs``: as :func:`evaluate`."""
    from surftrack.pose.estimator import check_seeds

    return _evaluate(checkpoint, data_dir, seeds=check_seeds(seeds), **kwargs)


def _evaluate(checkpoint, data_dir, split: str = "test", preset="accurate", max_images: int | None = None,
              occlusion_threshold: float = 0.9, *, device=None, images_per_batch: int = 4,
              min_visib_fract: float = 0.1, min_px_visib: int = 64, max_points: int = 5000,
              images: Iterable[tuple[int, int]] | None = None, progress: bool = False,
              kinematic=None, seeds: Sequence[int] | None = None,
              instruments: InstrumentRegistry = BUILTIN) -> list[dict]:
    """:func:`evaluate` / :func:`evaluate_seeds`: one result per seed (the preset's when ``seeds`` is None,
    through :meth:`PoseEstimator.estimate_batch`)."""
    from surftrack.data.bop import BopDataset, DatasetError
    from surftrack.pose.estimator import PoseEstimator

    if max_images is not None and int(max_images) < 1:
        raise ValueError(f"max_images must be positive, got {max_images}")
    if not 0.0 < float(occlusion_threshold) <= 1.0:
        raise ValueError(f"occlusion_threshold must be in (0, 1], got {occlusion_threshold}")
    if images_per_batch < 1:
        raise ValueError(f"images_per_batch must be >= 1, got {images_per_batch}")
    est = checkpoint if isinstance(checkpoint, PoseEstimator) else PoseEstimator(checkpoint, preset, device=device,
                                                                                instruments=instruments)
    if kinematic is True:
        kinematic = KinematicConfig()
    if kinematic:
        check_anchor(kinematic, est.model.parts)
    bop = BopDataset(data_dir, split, min_visib_fract=min_visib_fract, min_px_visib=min_px_visib)
    warn: list[str] = []
    fitted: list[str] = []
    for name, parts in sorted(instrument_parts(est.model.parts).items()) if kinematic else []:
        inst, why = described_instrument(name, parts, caller_reports=True, registry=instruments)
        if inst is None:
            warn.append(f"{why}: its parts are evaluated on their per-part poses")
        else:
            fitted.append(name)

    known = {p.obj_id: p for p in est.model.parts}
    for o, info in known.items():
        if o in bop.models and not bop.models[o].same_geometry(info.vertices, info.faces):
            warn.append(f"obj {o}: the dataset's model differs from the checkpoint's mesh ({info.name}); "
                        f"errors use the dataset's model")
    insts = [i for i in bop.instances if i.obj_id in known]
    skipped = len(bop.instances) - len(insts)
    if skipped:
        warn.append(f"{skipped} instances of objects the model does not know "
                    f"({sorted({i.obj_id for i in bop.instances} - set(known))}) skipped")
    by_image: dict[tuple[int, int], list] = defaultdict(list)
    for i in insts:
        by_image[(i.scene_id, i.im_id)].append(i)
    keys = sorted(by_image)
    if images is not None:
        wanted = {(int(s), int(m)) for s, m in images}
        keys = [k for k in keys if k in wanted]
    if max_images is not None:
        keys = keys[:int(max_images)]
    if not keys:
        raise DatasetError(f"{bop.root / split}: no images with instances of the model's objects "
                           f"{sorted(known)} to evaluate")

    obj_used = sorted({i.obj_id for k in keys for i in by_image[k]})
    labels = part_labels({o: (known[o].instrument, known[o].name) for o in obj_used})
    parts_info, points = {}, {}
    for o in obj_used:
        part = bop.models[o]
        points[o] = _model_points(part, max_points)
        v = np.asarray(part.mesh.vertices, np.float64)
        parts_info[o] = {"label": labels[o], "instrument": known[o].instrument, "part": known[o].name,
                         "diameter_bop_mm": diameter_max_pairwise(v), "diameter_surgripe_mm": diameter_bbox_diagonal(v)}

    twins_of = {}  # instrument -> its roll twin, scored as a symmetry alongside ADD-10
    for name, parts in instrument_parts(est.model.parts).items():
        inst = described_instrument(name, parts, registry=instruments)[0]
        if inst is not None and inst.roll_twin is not None:
            twins_of[name] = inst.roll_twin
    shared = seeds is not None
    seeds = list(seeds) if shared else [est.preset.seed]
    records: dict[int, list[dict]] = {sd: [] for sd in seeds}
    image_s: dict[int, list[float]] = {sd: [] for sd in seeds}
    load_s = 0.0
    t_start = time.perf_counter()
    batches = [keys[s:s + images_per_batch] for s in range(0, len(keys), images_per_batch)]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(keys), desc="eval", unit="image")
    for chunk in batches:
        t0 = time.perf_counter()
        imgs = [bop.load_rgb(*k) for k in chunk]
        load_s += time.perf_counter() - t0
        boxes = [[(i.obj_id, box_from_bop(i.bbox_visib)) for i in by_image[k]] for k in chunk]
        Ks = [by_image[k][0].K for k in chunk]
        t0 = time.perf_counter()
        groups = [_instrument_groups(by_image[k]) for k in chunk]
        by_seed = (est.estimate_batch_seeds(imgs, boxes, Ks, seeds, groups=groups) if shared
                   else [est.estimate_batch(imgs, boxes, Ks, groups=groups)])
        est_s = time.perf_counter() - t0
        for sd, poses in zip(seeds, by_seed):
            t0 = time.perf_counter()
            if kinematic:  # timed with the estimator: it is part of what the tracker outputs
                poses = [apply_kinematics(pl, g, est.model.parts, kinematic, instruments)
                         for g, pl in zip(groups, poses)]
            kin_s = time.perf_counter() - t0
            for k, plist in zip(chunk, poses):
                # one forward for all seeds: each seed's time is its poses' stage timings (forward included)
                per_image = (sum(p.timings.get("total", 0.0) for p in plist) * 1e-3 if shared else
                             est_s / len(chunk)) + kin_s / len(chunk)
                image_s[sd].append(per_image)
                recs = [_record(inst, p, points[inst.obj_id], parts_info[inst.obj_id], per_image, occlusion_threshold)
                        for inst, p in zip(by_image[k], plist)]
                _score_twins(by_image[k], plist, recs, points, parts_info, known, twins_of)
                records[sd].extend(recs)
        if bar is not None:
            bar.update(len(chunk))
    if bar is not None:
        bar.close()
    wall_s = time.perf_counter() - t_start
    for w in warn:
        warnings.warn(w, stacklevel=3)
    ckpt = str(checkpoint) if not isinstance(checkpoint, PoseEstimator) else None
    common = {"checkpoint": ckpt, "data_dir": str(data_dir), "split": split, "preset": est.preset.name,
              "views": est.preset.views, "part_views": dict(est.preset.part_views),
              "kinematic": dataclasses.asdict(kinematic) if kinematic else None, "kinematic_instruments": list(fitted),
              "device": str(est.device), "n_images": len(keys), "skipped_unknown_obj": skipped}
    return [_result(common, sd, records[sd], image_s[sd], load_s, load_s + sum(image_s[sd]) if shared else wall_s,
                    images_per_batch, shared, parts_info, obj_used, occlusion_threshold, list(warn)) for sd in seeds]


def _score_twins(instances: Sequence, poses: Sequence, records: list[dict], points: Mapping, parts_info: Mapping,
                 known: Mapping, twins_of: Mapping) -> None:
    """Add ``add10_twin_surgripe`` to the records of one image's instruments that have a roll twin
    (:mod:`surftrack.instruments.twin`) and whose parts were all estimated: ADD-10 with the twin counted
    as a symmetry of the instrument (BOP's treatment of a symmetric object), i.e. of the estimates or of
    their twin, whichever is nearer the truth over the instrument's parts (each part's ADD capped at its
    diameter)."""
    groups: dict = defaultdict(dict)
    for i, (inst, g) in enumerate(zip(instances, _instrument_groups(instances))):
        groups[(known[inst.obj_id].instrument, g)][known[inst.obj_id].name] = i
    for (name, _), members in groups.items():
        twin = twins_of.get(name)
        if twin is None or not twin.closed(members) or not all(poses[i].ok for i in members.values()):
            continue

        def capped_add(part: str, R: np.ndarray, t: np.ndarray) -> float:
            inst = instances[members[part]]
            return min(pose_errors(R, t, inst.R, inst.t, points[inst.obj_id])["add"],
                       parts_info[inst.obj_id]["diameter_surgripe_mm"])

        chosen, _ = twin.nearer({part: (poses[i].R, poses[i].t) for part, i in members.items()}, capped_add)
        for part, i in members.items():
            records[i]["add10_twin_surgripe"] = bool(
                capped_add(part, *chosen[part]) < 0.1 * parts_info[instances[i].obj_id]["diameter_surgripe_mm"])


def _record(inst, p, points: np.ndarray, d: Mapping, per_image: float, occlusion_threshold: float) -> dict:
    """One instance's JSON record: ground truth identity, the estimate and its errors."""
    err = pose_errors(p.R, p.t, inst.R, inst.t, points)
    return {
        "scene_id": inst.scene_id, "im_id": inst.im_id, "gt_index": inst.gt_index,
        "obj_id": inst.obj_id, "part": d["label"], "visib_fract": float(inst.visib_fract),
        "occluded": bool(inst.visib_fract < occlusion_threshold), "ok": bool(p.ok),
        "score": float(p.score), "n_inliers": int(p.n_inliers), **err,
        "depth_err_rel": depth_error_rel(p.t, inst.t),
        "add10_bop": bool(err["add"] < 0.1 * d["diameter_bop_mm"]),
        "add10_surgripe": bool(err["add"] < 0.1 * d["diameter_surgripe_mm"]),
        "R": np.asarray(p.R, np.float64).reshape(-1).tolist(),
        "t": np.asarray(p.t, np.float64).reshape(-1).tolist(),
        "time_s": per_image, "timings_ms": dict(p.timings)}


def _result(common: Mapping, seed: int, records: list[dict], image_s: list[float], load_s: float, total_s: float,
            images_per_batch: int, shared: bool, parts_info: Mapping, obj_used: Sequence[int],
            occlusion_threshold: float, warn: list[str]) -> dict:
    """The JSON-ready result of one seed's records (see :func:`evaluate`)."""
    from surftrack.pose.estimator import STAGES

    stage_ms = {s: float(np.mean([r["timings_ms"].get(s, 0.0) for r in records])) for s in (*STAGES, "total")}
    keys_ms = [r["timings_ms"]["keys"] for r in records if "keys" in r["timings_ms"]]
    how = ("the sum of its instances' stage timings (the network forward, shared by the seeds of one "
           "evaluate_seeds call, counted in each)" if shared else "estimate_batch wall time / images in the call")
    timings = {
        "per_instance_ms_mean": stage_ms,
        "surface_keys_ms_first_use": float(np.mean(keys_ms)) if keys_ms else None,
        "per_image_s_mean": float(np.mean(image_s)), "per_image_s_median": float(np.median(image_s)),
        "image_load_s_total": load_s, "total_s": total_s,
        "images_per_s": common["n_images"] / max(total_s, 1e-9),
        "images_per_batch": images_per_batch,
        "note": f"per-image time = {how} (crops, network, solver, the kinematic fit if any; image loading "
                "excluded); total_s = " + ("image loading + the per-image times" if shared else
                                           "wall time of the evaluation loop") +
                "; per-instance ms are the estimator's stage timings",
    }
    thresholds = np.linspace(0.0, CURVE_MAX_MM, 101)
    curve = {"thresholds_mm": thresholds.tolist(),
             "add": {parts_info[o]["label"]: accuracy_curve((r["add"] for r in records if r["obj_id"] == o), thresholds)
                     for o in obj_used} | {"all": accuracy_curve((r["add"] for r in records), thresholds)}}
    summary = summarize(records, parts_info, occlusion_threshold)
    return {
        **common, "kinematic_instruments": list(common["kinematic_instruments"]), "seed": seed,
        "n_instances": len(records),
        "occlusion": {"threshold": float(occlusion_threshold),
                      "definition": f"occluded = visib_fract < {occlusion_threshold} (BOP visib_fract: visible "
                                    "pixels / pixels of the unoccluded silhouette); non-occluded otherwise"},
        "diameters": dict(DIAMETERS),
        "metrics": {"re": "geodesic rotation error (deg)", "te": "translation error (mm)",
                    "add": "ADD (mm), mean over model vertices", "adds": "ADD-S (mm)",
                    "add10_bop / add10_surgripe": "fraction with ADD < 10% of the BOP / SurgRIPE diameter",
                    "auc_add_0_5mm": "area under the ADD accuracy-threshold curve on [0, 5] mm (VOCap)",
                    "all / overall": "instance-weighted pools of all instances / all parts",
                    "boxes": "ground-truth bbox_visib"},
        **summary, "timings": timings, "accuracy_curve": curve, "instances": records, "warnings": warn,
    }


# ------------------------------------------------------------------------------------------ outputs
def _fmt(v, scale: float = 1.0) -> str:
    return "–" if v is None else f"{v * scale:.2f}"


def markdown_table(result: Mapping, diameter: str = "surgripe", stat: str = "mean") -> str:
    """The paper's table: rows = parts + Avg, column groups Non-occ / occ / Avg with RE (deg), TE (mm),
    ADD-10 (%) and Avg ACC 0-5 mm (%); ``diameter`` ("surgripe" or "bop") picks the ADD-10 diameter,
    ``stat`` ("mean" or "median") the RE / TE statistic. A second table gives the counts, the medians /
    means not shown and ADD-10 under the other diameter convention."""
    if diameter not in DIAMETERS or stat not in ("mean", "median"):
        raise ValueError(f"diameter must be one of {sorted(DIAMETERS)} and stat 'mean' or 'median'")
    other_d = "bop" if diameter == "surgripe" else "surgripe"
    other_s = "median" if stat == "mean" else "mean"
    rows = [(label, p) for label, p in result["parts"].items()] + [("**Avg**", result["overall"])]
    head = ["Part"] + [f"{GROUPS[g]} {c}" for g in GROUPS
                       for c in ("RE (°) ↓", "TE (mm) ↓", "ADD-10 (%) ↑", "Avg ACC 0-5 mm (%) ↑")]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, p in rows:
        cells = [label]
        for g in GROUPS:
            s = p[g]
            cells += [_fmt(s[f"re_{stat}"]), _fmt(s[f"te_{stat}"]), _fmt(s[f"add10_{diameter}"], 100),
                      _fmt(s["auc_add_0_5mm"], 100)]
        lines.append("| " + " | ".join(cells) + " |")
    occ = result["occlusion"]
    lines += ["", f"RE, TE: {stat} over instances. ADD-10: ADD < 10 % of the {DIAMETERS[diameter]}. "
                  f"Avg ACC 0-5 mm: area under the ADD accuracy-threshold curve on [0, 5] mm. "
                  f"{occ['definition']}. Avg columns / row pool all instances. Ground-truth boxes; preset "
                  f"{result.get('preset')}, split {result.get('split')}, {result.get('n_images')} images"
                  + (f"; instrument-consistent poses (kinematic fit) of {', '.join(result['kinematic_instruments'])}"
                     if result.get("kinematic") and result.get("kinematic_instruments") else "") + ".", ""]
    head2 = ["Part", "n non-occ", "n occ", "failures", f"RE {other_s} (°)", f"TE {other_s} (mm)",
             f"ADD {stat} (mm)", f"ADD-10 {_DNAME[other_d]} diam. (%)",
             "ADD-S AUC 0-5 mm (%)"]
    lines += ["| " + " | ".join(head2) + " |", "|" + "---|" * len(head2)]
    for label, p in rows:
        a = p["all"]
        lines.append("| " + " | ".join([label, str(p["non_occ"]["count"]), str(p["occ"]["count"]), str(a["failures"]),
                                        _fmt(a[f"re_{other_s}"]), _fmt(a[f"te_{other_s}"]), _fmt(a[f"add_{stat}"]),
                                        _fmt(a[f"add10_{other_d}"], 100), _fmt(a["auc_adds_0_5mm"], 100)]) + " |")
    lines += ["", f"All instances (non-occ + occ). ADD-10 here uses the {DIAMETERS[other_d]}."]
    twins = [(label, p["all"]) for label, p in rows if p["all"].get("twin_count")]
    if twins:
        lines += ["", "ADD-10 (%, SurgRIPE diameter) with each instrument's roll twin counted as a symmetry (half a "
                      "turn about the shaft, the jaws exchanged: one image cannot tell them apart; instances whose "
                      "instrument was estimated whole): "
                  + ", ".join(f"{label.strip('*')} {100 * a['add10_twin_surgripe']:.2f} ({a['twin_count']})"
                              for label, a in twins) + "."]
    depth = [(label, p["all"]) for label, p in rows if p["all"].get("depth_bias_count")]
    if depth:
        lines += ["", "Depth bias (% of the distance along the line of sight; negative: too close to the camera), "
                      "median over the estimates right up to scale (RE < 20 deg, depth within 10 %): "
                  + ", ".join(f"{label.strip('*')} {100 * a['depth_bias']:+.2f} ({a['depth_bias_count']})"
                              for label, a in depth) + "."]
    return "\n".join(lines) + "\n"


def seed_table(results: Sequence[Mapping], diameter: str = "surgripe") -> str:
    """ADD-10 (%) per part and overall of evaluations that differ only in the pose solver's seed: a column
    per seed, then their mean and range. On ~100 images one seed's figure moves by a few points, so models
    are best compared on the mean."""
    if diameter not in DIAMETERS:
        raise ValueError(f"diameter must be one of {sorted(DIAMETERS)}")
    if not results:
        raise ValueError("seed_table needs at least one evaluation")
    key = f"add10_{diameter}"
    rows = [(label, [r["parts"].get(label, {}).get("all", {}).get(key) for r in results])
            for label in results[0]["parts"]]
    rows.append(("**Avg**", [r["overall"]["all"][key] for r in results]))
    head = ["Part", *(f"seed {r.get('seed')}" for r in results), "mean", "range"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for label, vals in rows:
        got = [v for v in vals if v is not None]
        stats = [_fmt(float(np.mean(got)) if got else None, 100),
                 f"{100 * min(got):.2f}-{100 * max(got):.2f}" if got else "–"]
        lines.append("| " + " | ".join([label, *(_fmt(v, 100) for v in vals), *stats]) + " |")
    lines += ["", f"ADD-10 (%): ADD < 10 % of the {DIAMETERS[diameter]}; preset {results[0].get('preset')}, "
                  f"{results[0].get('n_images')} images, one evaluation per pose-solver seed."]
    return "\n".join(lines) + "\n"


def write_bop_csv(result: Mapping, path: str | Path) -> Path:
    """BOP challenge results: ``scene_id,im_id,obj_id,score,R,t,time``; R 9 space-separated values
    (row-major), t in mm (3 values), time in seconds per image (the same for all estimates of an image)."""
    path = Path(path)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene_id", "im_id", "obj_id", "score", "R", "t", "time"])
        for r in result["instances"]:
            R, t = np.asarray(r["R"], np.float64), np.asarray(r["t"], np.float64)
            if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
                continue
            w.writerow([r["scene_id"], r["im_id"], r["obj_id"], f"{r['score']:.6g}",
                        " ".join(f"{v:.9g}" for v in R), " ".join(f"{v:.6f}" for v in t), f"{r['time_s']:.6f}"])
    return path


def plot_accuracy(result: Mapping, path: str | Path) -> Path:
    """ADD accuracy vs threshold (0-10 mm), one curve per part and the pooled one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = result["accuracy_curve"]
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, acc in c["add"].items():
        ax.plot(c["thresholds_mm"], [100 * a for a in acc], lw=2.5 if label == "all" else 1.5,
                color="k" if label == "all" else None, label="all parts" if label == "all" else label)
    ax.axvline(AUC_MAX_MM, color="grey", ls=":", lw=1)
    ax.set_xlim(0, CURVE_MAX_MM)
    ax.set_ylim(0, 100)
    ax.set_xlabel("ADD threshold (mm)")
    ax.set_ylabel("accuracy (%)")
    ax.set_title(f"ADD accuracy, {result.get('split')} ({result.get('n_instances')} instances)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Path(path)


def write_eval_outputs(result: Mapping, out_json: str | Path) -> dict[str, Path]:
    """Write ``out_json`` and next to it ``<stem>.md`` (:func:`markdown_table`), ``<stem>.bop.csv``
    (:func:`write_bop_csv`) and ``<stem>.png`` (:func:`plot_accuracy`); returns the four paths."""
    out = Path(out_json)
    out.parent.mkdir(parents=True, exist_ok=True)
    paths = {"json": out, "markdown": out.with_suffix(".md"), "bop_csv": out.with_suffix(".bop.csv"),
             "plot": out.with_suffix(".png")}
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(json_safe(result), indent=1))
    tmp.replace(out)
    paths["markdown"].write_text(markdown_table(result))
    write_bop_csv(result, paths["bop_csv"])
    plot_accuracy(result, paths["plot"])
    return paths

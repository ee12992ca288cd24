"""COCO keypoint evaluation: Object Keypoint Similarity (OKS) and OKS mAP, in numpy.

A re-implementation of pycocotools' ``COCOeval`` with ``iouType='keypoints'`` (Lin et al., "Microsoft
COCO", ECCV 2014; cocodataset.org/#keypoints-eval) for one area range and one ``maxDets``, written to give
the same numbers: the same OKS formula (including its ``np.spacing(1)`` guard), the same greedy per-image
matching, the same 101-point interpolated precision and the same averaging.

Input format (plain dicts, as in COCO json files; keypoints in pixels, COCO layout ``[x, y, v] * k``):

- ground truth: ``{"image_id", "keypoints", "area", "bbox", ["category_id"=1], ["iscrowd"=0],
  ["num_keypoints"]}``. ``area`` is the scale ``s^2`` of the OKS (pixels^2); when absent the box area
  ``w * h`` of ``bbox = [x, y, w, h]`` is used (the SurfSurg6D convention).
  ``num_keypoints`` defaults to the number of labelled keypoints (``v > 0``); a GT with none is ignored,
  as COCO does. ``bbox`` is only required for such GTs (COCO's distance-to-enlarged-box OKS).
- detections: ``{"image_id", "keypoints", "score", ["category_id"=1]}``; the visibility entries of
  detections are not used.

The evaluated images are all image ids seen in either list (COCO: all images of the GT file), so
detections on an image without GT count as false positives.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

#: COCO's OKS thresholds 0.50:0.05:0.95 and 101 recall points, built exactly as ``COCOeval.Params``.
OKS_THRESHOLDS = np.linspace(0.5, 0.95, int(np.round((0.95 - 0.5) / 0.05)) + 1, endpoint=True)
RECALL_THRESHOLDS = np.linspace(0.0, 1.00, int(np.round((1.00 - 0.0) / 0.01)) + 1, endpoint=True)
#: COCO's area range "all" for keypoints.
AREA_ALL = (0.0, 1e5**2)


class OksMAP(NamedTuple):
    """COCO keypoint AP: mean over OKS thresholds 0.50:0.05:0.95 (``mAP``), at 0.50 and at 0.75."""

    mAP: float
    AP50: float
    AP75: float


# ----------------------------------------------------------------------------------------------- parsing
def _keypoints(kp: Any, k: int | None, what: str) -> np.ndarray:
    a = np.asarray(kp, dtype=np.float64).reshape(-1)
    if a.size == 0 or a.size % 3:
        raise ValueError(f"{what}: keypoints must be a flat [x, y, v] * k list, got {a.size} values")
    if k is not None and a.size != 3 * k:
        raise ValueError(f"{what}: expected {k} keypoints ({3 * k} values, one per sigma), got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: keypoints contain non-finite values")
    return a


def _sigmas(sigmas: Sequence[float] | None, k: int) -> np.ndarray:
    s = np.full(k, 0.1) if sigmas is None else np.asarray(sigmas, dtype=np.float64).reshape(-1)
    if s.size != k:
        raise ValueError(f"{s.size} sigmas given for {k} keypoints")
    if np.any(~np.isfinite(s)) or np.any(s <= 0):
        raise ValueError("sigmas must be positive and finite")
    return s


class _Gt(NamedTuple):
    kp: np.ndarray
    area: float
    bbox: np.ndarray | None
    iscrowd: bool
    ignore: bool


class _Dt(NamedTuple):
    kp: np.ndarray
    score: float
    area: float


def _parse_gt(g: Mapping[str, Any], i: int, k: int) -> _Gt:
    what = f"ground_truth[{i}]"
    for key in ("image_id", "keypoints"):
        if key not in g:
            raise ValueError(f"{what} lacks '{key}'")
    kp = _keypoints(g["keypoints"], k, what)
    bbox = None
    if g.get("bbox") is not None:
        bbox = np.asarray(g["bbox"], dtype=np.float64).reshape(-1)
        if bbox.size != 4:
            raise ValueError(f"{what}: bbox must be [x, y, w, h]")
    if "area" in g and g["area"] is not None:
        area = float(g["area"])
    elif bbox is not None:
        area = float(bbox[2] * bbox[3])
    else:
        raise ValueError(f"{what} needs 'area' (OKS scale s^2) or 'bbox' to take the box area from")
    if not np.isfinite(area) or area < 0:
        raise ValueError(f"{what}: area must be finite and >= 0, got {area}")
    n_kp = int(g["num_keypoints"]) if "num_keypoints" in g else int(np.count_nonzero(kp[2::3] > 0))
    if np.count_nonzero(kp[2::3] > 0) == 0 and bbox is None:
        raise ValueError(f"{what} has no labelled keypoint, so COCO's box-distance OKS needs its 'bbox'")
    iscrowd = bool(g.get("iscrowd", 0))
    # COCOeval._prepare: ignore = iscrowd, then for keypoints also num_keypoints == 0
    return _Gt(kp, area, bbox, iscrowd, iscrowd or n_kp == 0)


def _parse_dt(d: Mapping[str, Any], i: int, k: int) -> _Dt:
    what = f"detections[{i}]"
    for key in ("image_id", "keypoints", "score"):
        if key not in d:
            raise ValueError(f"{what} lacks '{key}'")
    kp = _keypoints(d["keypoints"], k, what)
    score = float(d["score"])
    if not np.isfinite(score):
        raise ValueError(f"{what}: score must be finite")
    x, y = kp[0::3], kp[1::3]
    area = float((x.max() - x.min()) * (y.max() - y.min()))  # COCO.loadRes: keypoint extent box
    return _Dt(kp, score, area)


# ------------------------------------------------------------------------------------------------- OKS
def keypoint_oks(
    gt_keypoints: Sequence[float],
    gt_area: float,
    dt_keypoints: Sequence[float],
    sigmas: Sequence[float] | None = None,
    gt_bbox: Sequence[float] | None = None,
) -> float:
    """Object Keypoint Similarity of one detection to one GT (COCO, ``COCOeval.computeOks``):

    ``OKS = mean_{i: v_i > 0} exp(-e_i)``, ``e_i = d_i^2 / (2 s^2 k_i^2)`` written as COCO does,
    ``e_i = d_i^2 / k_i^2 / (s^2 + eps) / 2`` with ``k_i = 2 sigma_i``, ``s^2`` = GT area and
    ``eps = np.spacing(1)``. If the GT has no labelled keypoint, ``d_i`` is the distance of the detected
    keypoint to the GT box enlarged by its size on each side and the mean runs over all k keypoints.
    ``sigmas`` defaults to 0.1 per keypoint.
    """
    g = _keypoints(gt_keypoints, None, "gt_keypoints")
    k = g.size // 3
    d = _keypoints(dt_keypoints, k, "dt_keypoints")
    var = (2.0 * _sigmas(sigmas, k)) ** 2
    xg, yg, vg = g[0::3], g[1::3], g[2::3]
    xd, yd = d[0::3], d[1::3]
    labelled = vg > 0
    if np.any(labelled):
        dx = xd - xg
        dy = yd - yg
    else:
        if gt_bbox is None:
            raise ValueError("a GT without labelled keypoints needs gt_bbox for COCO's box-distance OKS")
        bx, by, bw, bh = np.asarray(gt_bbox, dtype=np.float64).reshape(4)
        x0, x1 = bx - bw, bx + 2.0 * bw
        y0, y1 = by - bh, by + 2.0 * bh
        z = np.zeros(k)
        dx = np.maximum(z, x0 - xd) + np.maximum(z, xd - x1)
        dy = np.maximum(z, y0 - yd) + np.maximum(z, yd - y1)
    e = (dx**2 + dy**2) / var / (float(gt_area) + np.spacing(1)) / 2
    if np.any(labelled):
        e = e[labelled]
    return float(np.sum(np.exp(-e)) / e.shape[0])


def _oks_matrix(gts: list[_Gt], dts: list[_Dt], sigmas: np.ndarray) -> np.ndarray:
    out = np.zeros((len(dts), len(gts)))
    for j, g in enumerate(gts):
        for i, d in enumerate(dts):
            out[i, j] = keypoint_oks(g.kp, g.area, d.kp, sigmas, g.bbox)
    return out


# ------------------------------------------------------------------------------------------- matching
def _evaluate_image(
    gts: list[_Gt], dts: list[_Dt], sigmas: np.ndarray, area_range: tuple[float, float], max_dets: int
) -> dict[str, np.ndarray] | None:
    """COCOeval.computeOks + evaluateImg for one (image, category)."""
    if not gts and not dts:
        return None
    dts = [dts[i] for i in np.argsort([-d.score for d in dts], kind="mergesort")][:max_dets]
    g_ign = np.array([g.ignore or g.area < area_range[0] or g.area > area_range[1] for g in gts], dtype=bool)
    order = np.argsort(g_ign, kind="mergesort")  # non-ignored GTs first
    gts = [gts[i] for i in order]
    g_ign = g_ign[order]
    crowd = [g.iscrowd for g in gts]
    ious = _oks_matrix(gts, dts, sigmas)
    T, G, D = len(OKS_THRESHOLDS), len(gts), len(dts)
    gt_matched = np.zeros((T, G), dtype=bool)
    dt_matched = np.zeros((T, D), dtype=bool)
    dt_ign = np.zeros((T, D), dtype=bool)
    if G and D:
        for ti, thr in enumerate(OKS_THRESHOLDS):
            for di in range(D):
                best = min(thr, 1 - 1e-10)
                m = -1
                for gi in range(G):
                    if gt_matched[ti, gi] and not crowd[gi]:
                        continue  # already taken
                    if m > -1 and not g_ign[m] and g_ign[gi]:
                        break  # a regular GT is matched; ignored GTs come after
                    if ious[di, gi] < best:
                        continue
                    best = ious[di, gi]
                    m = gi
                if m == -1:
                    continue
                dt_ign[ti, di] = g_ign[m]
                dt_matched[ti, di] = True
                gt_matched[ti, m] = True
    d_out = np.array([d.area < area_range[0] or d.area > area_range[1] for d in dts], dtype=bool)
    dt_ign |= ~dt_matched & d_out[None, :]
    return {
        "scores": np.array([d.score for d in dts], dtype=np.float64),
        "dt_matched": dt_matched,
        "dt_ignore": dt_ign,
        "gt_ignore": g_ign,
    }


def _precision(evals: list[dict[str, np.ndarray]]) -> np.ndarray | None:
    """COCOeval.accumulate for one category: (T, R) interpolated precision, None without regular GT."""
    scores = np.concatenate([e["scores"] for e in evals])
    order = np.argsort(-scores, kind="mergesort")
    dtm = np.concatenate([e["dt_matched"] for e in evals], axis=1)[:, order]
    dti = np.concatenate([e["dt_ignore"] for e in evals], axis=1)[:, order]
    n_pos = int(np.count_nonzero(~np.concatenate([e["gt_ignore"] for e in evals])))
    if n_pos == 0:
        return None
    tp_sum = np.cumsum(dtm & ~dti, axis=1).astype(np.float64)
    fp_sum = np.cumsum(~dtm & ~dti, axis=1).astype(np.float64)
    out = np.zeros((len(OKS_THRESHOLDS), len(RECALL_THRESHOLDS)))
    for t, (tp, fp) in enumerate(zip(tp_sum, fp_sum)):
        nd = tp.size
        if nd == 0:
            continue
        rc = tp / n_pos
        pr = tp / (fp + tp + np.spacing(1))
        pr = np.maximum.accumulate(pr[::-1])[::-1]  # precision envelope (non-increasing in recall)
        idx = np.searchsorted(rc, RECALL_THRESHOLDS, side="left")
        ok = idx < nd  # recall levels never reached keep precision 0
        out[t, ok] = pr[idx[ok]]
    return out


def _precision_table(
    ground_truth: Sequence[Mapping[str, Any]],
    detections: Sequence[Mapping[str, Any]],
    sigmas: Sequence[float] | None,
    max_dets: int,
    area_range: tuple[float, float],
) -> np.ndarray:
    """(T, R, C) precision table over categories C; categories without regular GT are all -1 (COCO)."""
    if not ground_truth and not detections:
        raise ValueError("no ground truth and no detections")
    if int(max_dets) < 1:
        raise ValueError(f"max_dets must be >= 1, got {max_dets}")
    lo, hi = float(area_range[0]), float(area_range[1])
    if not lo <= hi:
        raise ValueError(f"area_range must be (min, max) with min <= max, got {area_range}")
    first = (ground_truth or detections)[0]
    k = _keypoints(first.get("keypoints", []), None, "first annotation").size // 3
    sig = _sigmas(sigmas, k)

    per: dict[tuple[Any, Any], tuple[list[_Gt], list[_Dt]]] = {}
    images, cats = set(), set()
    for i, g in enumerate(ground_truth):
        key = (g.get("category_id", 1), g["image_id"] if "image_id" in g else None)
        per.setdefault(key, ([], []))[0].append(_parse_gt(g, i, k))
        images.add(key[1])
        cats.add(key[0])
    for i, d in enumerate(detections):
        key = (d.get("category_id", 1), d["image_id"] if "image_id" in d else None)
        per.setdefault(key, ([], []))[1].append(_parse_dt(d, i, k))
        images.add(key[1])
        cats.add(key[0])

    table = -np.ones((len(OKS_THRESHOLDS), len(RECALL_THRESHOLDS), len(cats)))
    for c, cat in enumerate(sorted(cats)):
        evals = []
        for img in sorted(images):  # COCOeval.Params.imgIds is sorted
            gts, dts = per.get((cat, img), ([], []))
            e = _evaluate_image(gts, dts, sig, (lo, hi), int(max_dets))
            if e is not None:
                evals.append(e)
        p = _precision(evals) if evals else None
        if p is not None:
            table[:, :, c] = p
    return table


def _mean_valid(a: np.ndarray) -> float:
    v = a[a > -1]
    return float(np.mean(v)) if v.size else float("nan")


def oks_ap_per_threshold(
    ground_truth: Sequence[Mapping[str, Any]],
    detections: Sequence[Mapping[str, Any]],
    sigmas: Sequence[float] | None = None,
    max_dets: int = 20,
    area_range: tuple[float, float] = AREA_ALL,
) -> np.ndarray:
    """COCO keypoint AP at each OKS threshold of :data:`OKS_THRESHOLDS` (shape (10,)), averaged over
    categories that have at least one non-ignored GT; NaN where there is none. See :func:`oks_map`."""
    table = _precision_table(ground_truth, detections, sigmas, max_dets, area_range)
    return np.array([_mean_valid(table[t]) for t in range(table.shape[0])])


def oks_map(
    ground_truth: Sequence[Mapping[str, Any]],
    detections: Sequence[Mapping[str, Any]],
    sigmas: Sequence[float] | None = None,
    max_dets: int = 20,
    area_range: tuple[float, float] = AREA_ALL,
) -> OksMAP:
    """COCO keypoint mAP, AP50 and AP75 as pycocotools ``COCOeval(iouType='keypoints')`` reports them
    (``stats[0:3]``; Lin et al. 2014).

    Per image and category, detections sorted by score (stable) and cut to ``max_dets`` are matched
    greedily to the unmatched GT of highest OKS (:func:`keypoint_oks`) at or above each threshold in
    0.50:0.05:0.95; detections matched to ignored GTs (crowd, no labelled keypoint, area outside
    ``area_range``) are ignored. Over all images, precision ``tp / (tp + fp)`` after each score-sorted
    detection is made non-increasing in recall and read at the 101 recall points 0:0.01:1 (0 beyond the
    highest recall reached); AP is the mean of those 101 values, averaged over categories.
    ``sigmas`` defaults to 0.1 per keypoint (``k_i = 2 sigma_i``). Returns NaN values when no category has
    a non-ignored GT (COCO prints -1). Input format: see the module docstring.
    """
    table = _precision_table(ground_truth, detections, sigmas, max_dets, area_range)
    t50 = int(np.flatnonzero(np.isclose(OKS_THRESHOLDS, 0.50))[0])
    t75 = int(np.flatnonzero(np.isclose(OKS_THRESHOLDS, 0.75))[0])
    return OksMAP(_mean_valid(table), _mean_valid(table[t50]), _mean_valid(table[t75]))

"""The detection file ``det.json`` the tracker reads, and a simulated noisy detector that writes it.

A detection file lists, per video frame, boxes of instrument parts::

    {"format": "surftrack-detections", "version": 1, "image_size": [W, H],
     "parts": {"1": {"instrument": "large_needle_driver", "instance": 0, "part": "wrist"}, ...},
     "frames": [{"index": 0, "time": 0.0,
                 "detections": [{"part_id": 1, "bbox": [x, y, w, h], "score": 0.93}, ...]}, ...]}

``parts`` maps a track id (an integer written as a string key) to the part it denotes. Boxes are in
pixel-EDGE coordinates: pixel ``u`` spans ``[u, u + 1]``, the full image is ``[0, 0, W, H]`` and a box
covers ``[x, x + w] x [y, y + h]``. A BOP box ``[x, y, w, h]`` over pixel indices (``w = xmax - xmin``)
is therefore the edge box ``[x, y, w + 1, h + 1]``. Writers clip boxes to the image. ``score`` is in [0, 1]; ``time`` is the frame's
presentation time in seconds. A false detection carries the id of some listed part. An optional
``meta`` object holds free-form provenance.

The published JSON Schema (``configs/schemas/det.schema.json``) checks the structure;
:func:`validate_detections` adds what a schema cannot: every ``part_id`` is listed in ``parts``, frame
indices strictly increase, times never decrease, numbers are finite and boxes lie inside the image.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, fields
from functools import lru_cache
from pathlib import Path

import numpy as np
from jsonschema import Draft202012Validator
from jsonschema.exceptions import best_match

from surftrack.atomic import write_atomic
from surftrack.geometry.boxes import Box
from surftrack.paths import configs_dir

FORMAT = "surftrack-detections"
VERSION = 1
SCHEMA_PATH = configs_dir() / "schemas" / "det.schema.json"
BOX_TOLERANCE_PX = 1e-3  # how far a box may poke outside the image (rounding of written numbers)


@lru_cache(maxsize=None)
def _load_schema_cached(path: str) -> dict:
    with open(path, encoding="utf-8") as f:
        schema = json.load(f)
    Draft202012Validator.check_schema(schema)
    return schema


def load_schema() -> dict:
    """The published JSON Schema of ``det.json`` (draft 2020-12)."""
    return _load_schema_cached(str(SCHEMA_PATH))


def _jsonable(doc: dict, source: str) -> dict:
    """``doc`` as JSON would read it back: tuples become lists and numpy scalars Python numbers."""
    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        raise TypeError(f"{type(o).__name__} is not JSON serialisable")

    try:
        return json.loads(json.dumps(doc, default=default))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{source}: not representable as JSON ({e})") from None


def _short(text: str, limit: int = 200) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def validate_detections(doc: dict, source: str = "det.json") -> None:
    """Raise ``ValueError("<source>: <JSON path>: <reason>")`` (one line) unless ``doc`` is a valid
    detection document: the schema, then part ids, frame order, finite numbers and boxes in the image."""
    doc = _jsonable(doc, source)
    error = best_match(Draft202012Validator(load_schema()).iter_errors(doc))
    if error is not None:
        raise ValueError(f"{source}: {error.json_path}: {_short(error.message)}")
    width, height = doc["image_size"]
    parts = {int(k) for k in doc["parts"]}
    prev_index, prev_time = None, None
    for i, frame in enumerate(doc["frames"]):
        where = f"$.frames[{i}]"
        index, time = frame["index"], frame["time"]
        if not math.isfinite(time):
            raise ValueError(f"{source}: {where}.time: {time} is not a finite number")
        if prev_index is not None and index <= prev_index:
            raise ValueError(f"{source}: {where}.index: {index} does not increase (previous frame has {prev_index})")
        if prev_time is not None and time < prev_time:
            raise ValueError(f"{source}: {where}.time: {time} is before the previous frame's time {prev_time}")
        prev_index, prev_time = index, time
        for j, det in enumerate(frame["detections"]):
            dwhere = f"{where}.detections[{j}]"
            if det["part_id"] not in parts:
                raise ValueError(f"{source}: {dwhere}.part_id: {det['part_id']} is not listed in $.parts")
            x, y, w, h = det["bbox"]
            if not all(math.isfinite(v) for v in (x, y, w, h, det["score"])):
                raise ValueError(f"{source}: {dwhere}: bbox and score must be finite numbers")
            tol = BOX_TOLERANCE_PX
            if x < -tol or y < -tol or x + w > width + tol or y + h > height + tol:
                raise ValueError(f"{source}: {dwhere}.bbox: {[x, y, w, h]} extends outside the "
                                 f"{width}x{height} image (writers clip boxes to [0, 0, {width}, {height}])")


def detections_document(image_size: tuple[int, int], parts: dict, frames: list[dict] | None = None,
                        meta: dict | None = None) -> dict:
    """A detection document for ``image_size`` = (W, H); ``parts`` maps track id (int or str) to
    ``{"instrument": ..., "instance": ..., "part": ...}``; ``frames`` defaults to none yet."""
    doc = {"format": FORMAT, "version": VERSION, "image_size": [int(image_size[0]), int(image_size[1])],
           "parts": {str(int(k)): dict(v) for k, v in sorted(parts.items(), key=lambda kv: int(kv[0]))},
           "frames": list(frames) if frames is not None else []}
    if meta is not None:
        doc["meta"] = dict(meta)
    return doc


def load_detections(path: str | Path) -> dict:
    """Read and validate a detection file; a one-line ``ValueError`` naming the file if it is missing,
    not JSON, or not a valid detection document."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{path}: no such detection file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: cannot read ({_short(str(e))})") from None

    def reject_constant(name: str):
        raise ValueError(f"{name} is not valid JSON")

    try:
        doc = json.loads(text, parse_constant=reject_constant)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except ValueError as e:
        raise ValueError(f"{path}: invalid JSON: {e}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: $: a detection document must be a JSON object, got {type(doc).__name__}")
    validate_detections(doc, source=str(path))
    return doc


def write_detections(path: str | Path, doc: dict) -> None:
    """Validate ``doc`` and write it to ``path`` (atomically; one frame per line)."""
    path = Path(path)
    validate_detections(doc, source=str(path))
    doc = _jsonable(doc, str(path))
    head = {k: v for k, v in doc.items() if k != "frames"}
    pretty = json.dumps(head, indent=2, allow_nan=False)
    # Number lists such as image_size on one line (the match spans newlines, so it never edits strings).
    pretty = re.sub(r"\[\n\s*(-?[\d.eE+-]+(?:,\n\s*-?[\d.eE+-]+)*)\n\s*\]",
                    lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]", pretty)
    lines = pretty.splitlines()
    frames = [json.dumps(f, allow_nan=False, separators=(", ", ": ")) for f in doc["frames"]]
    body = ",\n".join("    " + f for f in frames)
    text = "\n".join(lines[:-1]) + ",\n" + ('  "frames": [\n' + body + "\n  ]\n}\n" if frames else '  "frames": []\n}\n')
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, text)


def clip_box(bbox: Box, image_size: tuple[int, int]) -> Box | None:
    """``bbox`` (x, y, w, h) clipped to the image [0, W] x [0, H]; None if nothing of it is left.
    Coordinates already inside are returned unchanged (bit for bit)."""
    x, y, w, h = (float(v) for v in bbox)
    width, height = image_size
    if x < 0.0:
        w, x = w + x, 0.0
    if y < 0.0:
        h, y = h + y, 0.0
    if x + w > width:
        w = width - x
    if y + h > height:
        h = height - y
    if w <= 0.0 or h <= 0.0:
        return None
    return x, y, w, h


@dataclass(frozen=True)
class DetectionNoise:
    """How a simulated detector deviates from the ground truth.

    ``center_std``, ``scale_std``: box centre jitter (Gaussian, as a fraction of the box's width / height)
    and log-normal size jitter. ``miss_prob``: probability a detectable part is missed. ``false_prob``:
    per-frame probability of one false box. ``score_range``: scores of true boxes (false ones score lower).
    ``min_visible_px``: parts with fewer visible pixels are not detected.
    """

    center_std: float = 0.03
    scale_std: float = 0.05
    miss_prob: float = 0.05
    false_prob: float = 0.02
    score_range: tuple[float, float] = (0.6, 1.0)
    min_visible_px: int = 30

    def __post_init__(self) -> None:
        for name in ("center_std", "scale_std"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("miss_prob", "false_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {getattr(self, name)}")
        lo, hi = (float(v) for v in self.score_range)
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError(f"score_range must be (lo, hi) with 0 <= lo <= hi <= 1, got {self.score_range}")
        object.__setattr__(self, "score_range", (lo, hi))
        if self.min_visible_px < 0:
            raise ValueError(f"min_visible_px must be >= 0, got {self.min_visible_px}")

    @classmethod
    def from_dict(cls, d: dict) -> DetectionNoise:
        """Noise from a config mapping (e.g. YAML); keys are the field names, missing ones keep defaults."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown detection noise key(s) {unknown}; known keys are {sorted(known)}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})

    @classmethod
    def none(cls) -> DetectionNoise:
        """A perfect detector: every part with a visible pixel, its exact box, score 1."""
        return cls(center_std=0.0, scale_std=0.0, miss_prob=0.0, false_prob=0.0, score_range=(1.0, 1.0),
                   min_visible_px=1)


def simulate_detections(gt_boxes: dict[int, Box | None], visible_px: dict[int, int],
                        image_size: tuple[int, int], noise: DetectionNoise,
                        rng: np.random.Generator) -> list[dict]:
    """The ``detections`` list of one frame from a simulated detector.

    ``gt_boxes`` maps every part id to its ground-truth visible box (x, y, w, h; pixel edges) or None;
    ``visible_px`` its visible pixel count (missing = 0). A part is detected if it has at least
    ``noise.min_visible_px`` visible pixels and is not missed; its box centre is jittered by
    ``center_std`` times its size, its width and height scaled by ``exp(N(0, scale_std))``, and the box
    clipped to the image. With probability ``false_prob`` one false box is added: the id of a random
    part, a size like this frame's real boxes, a random place in the image and a lower score.
    Deterministic for a given ``rng`` state; each part uses the same number of draws whether or not it
    is detected.
    """
    width, height = int(image_size[0]), int(image_size[1])
    lo, hi = noise.score_range
    out: list[dict] = []
    sizes = []
    for pid in sorted(gt_boxes):
        box = gt_boxes[pid]
        u_miss, n = rng.random(), rng.standard_normal(4)
        score = rng.uniform(lo, hi)
        if box is None:
            continue
        x, y, w, h = (float(v) for v in box)
        sizes.append((w, h))
        if visible_px.get(pid, 0) < noise.min_visible_px or u_miss < noise.miss_prob:
            continue
        w2, h2 = w * math.exp(noise.scale_std * n[2]), h * math.exp(noise.scale_std * n[3])
        # Centre moves by the jitter; the corner keeps the centre under the new size.
        x2 = x + noise.center_std * w * n[0] - 0.5 * (w2 - w)
        y2 = y + noise.center_std * h * n[1] - 0.5 * (h2 - h)
        clipped = clip_box((x2, y2, w2, h2), (width, height))
        if clipped is None:
            continue
        out.append({"part_id": int(pid), "bbox": [float(v) for v in clipped], "score": float(score)})
    if gt_boxes and rng.random() < noise.false_prob:
        ids = sorted(gt_boxes)
        pid = ids[int(rng.integers(len(ids)))]
        if sizes:
            tw, th = np.median(np.asarray(sizes), axis=0)
        else:
            tw, th = width / 8.0, height / 8.0
        w = float(min(max(tw * math.exp(rng.normal(0.0, 0.3)), 2.0), width))
        h = float(min(max(th * math.exp(rng.normal(0.0, 0.3)), 2.0), height))
        x, y = float(rng.uniform(0.0, width - w)), float(rng.uniform(0.0, height - h))
        # False boxes score in the lower part of the range, stretched downwards.
        score = float(rng.uniform(0.7 * lo, lo + 0.5 * (hi - lo)))
        at = int(rng.integers(len(out) + 1))
        clipped = clip_box((x, y, w, h), (width, height))  # guards against rounding at the far edge
        out.insert(at, {"part_id": int(pid), "bbox": [float(v) for v in clipped], "score": score})
    return out

"""Inputs of a tracking run, validated before any heavy work: intrinsics, detections and the video.

Every problem raises :class:`InputError` with one line naming the file and what is wrong.

* Camera: ``camera.json`` (``{"K": 3x3, "width", "height", "dist": [...]}``, as written by
  ``surftrack synth-clip``) or a BOP ``scene_camera.json`` (first entry's ``cam_K``; the size is the
  video's). Distortion coefficients (OpenCV order, 4/5/8/12/14 values) are removed from every frame.
* Detections: our ``det.json`` (:mod:`surftrack.synth.detections`) or a COCO-style file with ``images``
  (``id``, and ``frame_index`` or, failing that, the last number in ``file_name``; both are 0-based
  decoded-frame indices: renumber frames extracted by ffmpeg's 1-based ``%06d``), ``annotations`` (``image_id``,
  ``category_id``, ``bbox`` [x, y, w, h] in pixel-edge coordinates as COCO's, optional ``score``) and
  ``categories`` (``id``, ``name`` = part, ``supercategory`` = instrument; or ``name`` =
  ``"<instrument>/<part>"``).
* Video: opened and its first frame decoded up front (missing, corrupt or empty files fail here).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np

from surftrack.synth.detections import detections_document, validate_detections


class InputError(ValueError):
    """A bad input file; the message is one line naming the file."""


@dataclass
class CameraInput:
    """Intrinsics for the tracker: ``K`` of the (undistorted) frames, size (W, H), and the undistortion
    maps when the input had distortion."""

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray
    source: str

    def undistorter(self):
        """A function frame -> undistorted frame (identity without distortion)."""
        if not np.any(self.dist):
            return lambda frame: frame
        m1, m2 = cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, (self.width, self.height),
                                             cv2.CV_16SC2)
        return lambda frame: cv2.remap(frame, m1, m2, cv2.INTER_LINEAR)


def _read_json(path: Path, what: str):
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such {what} file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read ({e.__class__.__name__}: {e})") from None
    try:
        return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(f"{c} is not JSON")))
    except ValueError as e:
        raise InputError(f"{path}: invalid JSON ({str(e).splitlines()[0]})") from None


def load_camera(path: str | Path, video_size: tuple[int, int]) -> CameraInput:
    """Intrinsics from ``camera.json`` or a BOP ``scene_camera.json``, checked against the video size."""
    path = Path(path)
    doc = _read_json(path, "camera")
    W, H = video_size
    dist: list = []
    if isinstance(doc, dict) and "K" in doc:
        K, dist = doc["K"], doc.get("dist") or []
        size = (doc.get("width"), doc.get("height"))
    elif isinstance(doc, dict) and doc and all(isinstance(v, dict) and "cam_K" in v for v in doc.values()):
        first = doc[min(doc, key=lambda k: int(k) if str(k).isdigit() else math.inf)]
        K, size = first["cam_K"], (W, H)
    else:
        raise InputError(f"{path}: not a camera file: expected {{\"K\": ..., \"width\": ..., \"height\": ...}} "
                         f"or a BOP scene_camera.json with cam_K")
    try:
        Km = np.asarray(K, dtype=np.float64).reshape(3, 3)
        dist_a = np.asarray(dist, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{path}: K must be 3x3 numbers (or 9 in a row) and dist a list of numbers") from None
    if not (np.all(np.isfinite(Km)) and np.all(np.isfinite(dist_a))):
        raise InputError(f"{path}: K and dist must be finite numbers")
    if len(dist_a) not in (0, 4, 5, 8, 12, 14):
        raise InputError(f"{path}: dist must have 0, 4, 5, 8, 12 or 14 OpenCV coefficients, got {len(dist_a)}")
    fx, fy, cx, cy = Km[0, 0], Km[1, 1], Km[0, 2], Km[1, 2]
    if not (fx > 0 and fy > 0) or Km[1, 0] != 0 or Km[2, 0] != 0 or Km[2, 1] != 0 or Km[2, 2] != 1:
        raise InputError(f"{path}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    if Km[0, 1] != 0:
        raise InputError(f"{path}: K has skew {Km[0, 1]:g}; only zero-skew intrinsics are supported")
    try:
        w, h = int(size[0]), int(size[1])
    except (TypeError, ValueError):
        raise InputError(f"{path}: width and height must be integers") from None
    if (w, h) != (W, H):
        raise InputError(f"{path}: intrinsics are for {w}x{h} images but the video is {W}x{H}")
    if not (0 < cx < W and 0 < cy < H):
        raise InputError(f"{path}: principal point ({cx:g}, {cy:g}) lies outside the {W}x{H} image")
    if not 0.05 < fx / W < 20 or not 0.2 < fx / fy < 5:
        raise InputError(f"{path}: implausible focal lengths fx={fx:g}, fy={fy:g} px for a {W}px-wide image")
    return CameraInput(Km, W, H, dist_a, str(path))


def _coco_to_det(doc: dict, path: Path, video_size: tuple[int, int]) -> dict:
    """Our detection document from a COCO-style one (times filled in later from the video)."""
    try:
        return _coco_to_det_checked(doc, path, video_size)
    except InputError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"{path}: malformed COCO file ({e.__class__.__name__}: {e})") from None


def _coco_to_det_checked(doc: dict, path: Path, video_size: tuple[int, int]) -> dict:
    try:
        cats = {int(c["id"]): c for c in doc["categories"]}
        images = doc["images"]
        anns = doc["annotations"]
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{path}: a COCO file needs images, annotations and categories (with ids)") from None
    parts, pid_of = {}, {}
    for cid, c in sorted(cats.items()):
        name = str(c.get("name", ""))
        inst, part = (name.split("/", 1) if "/" in name else (str(c.get("supercategory", "")), name))
        if not inst or not part:
            raise InputError(f"{path}: category {cid} must name an instrument and a part "
                             f"(supercategory + name, or name 'instrument/part'), got {c!r}")
        m = re.match(r"^(.*?)(?:#(\d+))?$", inst)
        parts[str(cid)] = {"instrument": m.group(1), "instance": int(m.group(2) or 0), "part": part}
        pid_of[cid] = cid
    frame_of = {}
    for k, im in enumerate(images):
        try:
            iid = int(im["id"])
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{path}: images[{k}] has no integer id") from None
        if "frame_index" in im:
            frame_of[iid] = int(im["frame_index"])
        else:
            nums = re.findall(r"\d+", Path(str(im.get("file_name", ""))).stem)
            if not nums:
                raise InputError(f"{path}: images[{k}] needs frame_index or a frame number in file_name")
            frame_of[iid] = int(nums[-1])
    frames: dict[int, list] = {}
    for k, a in enumerate(anns):
        try:
            iid, cid = int(a["image_id"]), int(a["category_id"])
            bbox = [float(v) for v in a["bbox"]]
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{path}: annotations[{k}] needs image_id, category_id and bbox [x, y, w, h]") from None
        if iid not in frame_of:
            raise InputError(f"{path}: annotations[{k}].image_id {iid} is not in images")
        if cid not in cats:
            raise InputError(f"{path}: annotations[{k}].category_id {cid} is not in categories")
        if not (len(bbox) == 4 and bbox[2] > 0 and bbox[3] > 0):
            raise InputError(f"{path}: annotations[{k}].bbox must be [x, y, w, h] with w, h > 0, got {bbox}")
        frames.setdefault(frame_of[iid], []).append(
            {"part_id": pid_of[cid], "bbox": bbox, "score": float(a.get("score", 1.0))})
    out = detections_document(video_size, parts, [{"index": i, "time": 0.0, "detections": frames[i]}
                                                   for i in sorted(frames)], meta={"converted_from": "coco"})
    try:
        validate_detections(out, str(path))
    except ValueError as e:
        raise InputError(str(e).replace("$.frames", "frame")) from None
    return out


def load_boxes(path: str | Path, video_size: tuple[int, int]) -> dict:
    """A validated detection document (det.json or COCO) for a video of ``video_size`` (W, H). A COCO file
    has no frame times: its document says ``meta.converted_from == "coco"`` and its times are 0."""
    path = Path(path)
    doc = _read_json(path, "detection")
    if isinstance(doc, dict) and doc.get("format") == "surftrack-detections":
        try:
            validate_detections(doc, source=str(path))
        except ValueError as e:
            raise InputError(str(e)) from None
        if tuple(doc["image_size"]) != tuple(video_size):
            raise InputError(f"{path}: boxes are for {doc['image_size'][0]}x{doc['image_size'][1]} frames "
                             f"but the video is {video_size[0]}x{video_size[1]}")
    elif isinstance(doc, dict) and {"images", "annotations", "categories"} <= set(doc):
        doc = _coco_to_det(doc, path, video_size)
    else:
        raise InputError(f"{path}: not a detection file: expected a surftrack det.json "
                         f"(\"format\": \"surftrack-detections\") or a COCO file with images/annotations/categories")
    if not any(f["detections"] for f in doc["frames"]):
        raise InputError(f"{path}: contains no boxes at all; the tracker needs at least one box per part to start")
    return doc


@dataclass
class VideoInfo:
    path: Path
    width: int
    height: int
    fps: float
    frames: int  # 0 when the container does not say
    duration_s: float = 0.0  # the container's duration; 0 when it does not say


def probe_video(path: str | Path) -> VideoInfo:
    """Open ``path`` and decode its first frame; InputError if missing, not a video or undecodable."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such video file")
    try:
        with av.open(str(path)) as c:
            if not c.streams.video:
                raise InputError(f"{path}: has no video stream")
            s = c.streams.video[0]
            frame = next(c.decode(s), None)
            if frame is None:
                raise InputError(f"{path}: contains no decodable video frame")
            fps = float(s.average_rate or s.guessed_rate or 0) or 30.0
            if c.duration:
                duration = c.duration / av.time_base
            else:
                duration = float(s.duration * s.time_base) if s.duration and s.time_base else 0.0
            return VideoInfo(path, frame.width, frame.height, fps, int(s.frames or 0), float(duration))
    except InputError:
        raise
    except (av.FFmpegError, OSError, StopIteration) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else e.__class__.__name__
        raise InputError(f"{path}: cannot read as a video ({msg})") from None

"""Writing BOP-format datasets (bop_toolkit's layout, field names and units).

``<root>/<split>/<scene 06d>/`` holds ``rgb/<im 06d>.{jpg,png}``, ``depth/<im>.png`` (uint16, value *
``depth_scale`` = mm), ``mask/<im>_<gt 06d>.png`` and ``mask_visib/...`` (0/255; masks from an
instance-id buffer, not from BOP's depth tolerance), ``normal/<im>.png`` (uint8 RGB, ``(n + 1) / 2 *
255``, camera frame, 0 = no surface) and the scene JSON files. Each finished image first leaves a small
record in ``<scene>/records/<im>.json``; :func:`finalize_scene` merges the records into
``scene_camera.json``, ``scene_gt.json`` and ``scene_gt_info.json``, so an interrupted run is resumable
and every finalised scene is valid.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from surftrack.atomic import write_atomic


def scene_dir(root: Path, split: str, scene_id: int) -> Path:
    return Path(root) / split / f"{scene_id:06d}"


def record_path(root: Path, split: str, scene_id: int, im_id: int) -> Path:
    return scene_dir(root, split, scene_id) / "records" / f"{im_id:06d}.json"


def bbox_xywh(mask: np.ndarray, offset: int = 0) -> list[int]:
    """BOP box [x, y, w, h] (w = xmax - xmin) of a mask, shifted by ``-offset``; [-1] * 4 when empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(cols[0]) - offset, int(rows[0]) - offset
    return [x0, y0, int(cols[-1]) - offset - x0, int(rows[-1]) - offset - y0]


def encode_normals(normal: np.ndarray) -> np.ndarray:
    """Camera-frame unit normals (H, W, 3) as uint8 RGB ``round((n + 1) / 2 * 255)``; 0 where no surface
    (a valid normal never encodes to (0, 0, 0): that would need n = (-1, -1, -1))."""
    valid = np.linalg.norm(normal, axis=-1) > 0.5
    enc = np.clip(np.round((normal + 1.0) * 127.5), 0, 255).astype(np.uint8)
    enc[~valid] = 0
    return enc


def decode_normals(enc: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_normals` (renormalised); zeros where there is no surface."""
    n = enc.astype(np.float32) / 127.5 - 1.0
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where((enc.sum(-1, keepdims=True) > 0) & (norm > 0), n / np.maximum(norm, 1e-6), 0.0)


def _imwrite(path: Path, img: np.ndarray, params: list[int] | None = None) -> None:
    ok, buf = cv2.imencode(path.suffix, img, params or [])
    if not ok:
        raise OSError(f"{path}: cannot encode image")
    write_atomic(path, buf.tobytes())


def write_image(root: Path, split: str, scene_id: int, im_id: int, rgb: np.ndarray, depth: np.ndarray,
                normal: np.ndarray, masks: list[np.ndarray], masks_visib: list[np.ndarray], record: dict,
                rgb_format: str = "jpg", jpg_quality: int = 95, depth_scale: float = 0.1) -> None:
    """Write one image's files, then its record (the record marks the image as finished)."""
    d = scene_dir(root, split, scene_id)
    for sub in ("rgb", "depth", "mask", "mask_visib", "normal", "records"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    name = f"{im_id:06d}"
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpg_quality)] if rgb_format == "jpg" else []
    _imwrite(d / "rgb" / f"{name}.{rgb_format}", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    depth_u16 = np.clip(np.round(depth / depth_scale), 0, 65535).astype(np.uint16)
    _imwrite(d / "depth" / f"{name}.png", depth_u16)
    _imwrite(d / "normal" / f"{name}.png", cv2.cvtColor(encode_normals(normal), cv2.COLOR_RGB2BGR))
    for k, (m, mv) in enumerate(zip(masks, masks_visib)):
        _imwrite(d / "mask" / f"{name}_{k:06d}.png", m.astype(np.uint8) * 255)
        _imwrite(d / "mask_visib" / f"{name}_{k:06d}.png", mv.astype(np.uint8) * 255)
    write_atomic(record_path(root, split, scene_id, im_id), json.dumps(record).encode())


def finished_images(root: Path, split: str, scene_id: int) -> set[int]:
    """Image ids of a scene that have their record (or are already in a finalised scene_gt.json)."""
    d = scene_dir(root, split, scene_id)
    done = {int(p.stem) for p in (d / "records").glob("*.json")} if (d / "records").is_dir() else set()
    gt = d / "scene_gt.json"
    if gt.is_file():
        done |= {int(k) for k in json.loads(gt.read_text())}
    return done


def finalize_scene(root: Path, split: str, scene_id: int) -> int:
    """Merge the image records of a scene into the BOP scene JSON files; returns the image count."""
    d = scene_dir(root, split, scene_id)
    cams, gts, infos = {}, {}, {}
    for name, store in (("scene_camera.json", cams), ("scene_gt.json", gts), ("scene_gt_info.json", infos)):
        if (d / name).is_file():
            store.update(json.loads((d / name).read_text()))
    for p in sorted((d / "records").glob("*.json")) if (d / "records").is_dir() else []:
        rec = json.loads(p.read_text())
        key = str(int(p.stem))
        cams[key], gts[key], infos[key] = rec["scene_camera"], rec["scene_gt"], rec["scene_gt_info"]
    order = sorted(cams, key=int)
    for name, store in (("scene_camera.json", cams), ("scene_gt.json", gts), ("scene_gt_info.json", infos)):
        write_atomic(d / name, json.dumps({k: store[k] for k in order}, indent=1).encode())
    return len(order)

"""A contact sheet of generated images with their visible-mask outlines, for people to look at."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

_COLOURS = [(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
            (70, 240, 240), (240, 50, 230)]


def write_contact_sheet(root: str | Path, split: str = "train", count: int = 16, columns: int = 4,
                        tile_width: int = 320) -> Path | None:
    """Tile the first ``count`` images of the dataset with outlines of each instance's visible mask."""
    root = Path(root)
    tiles = []
    for scene in sorted((root / split).glob("[0-9]" * 6)):
        gt_path = scene / "scene_gt.json"
        if not gt_path.is_file():
            continue
        for im_key, gts in sorted(json.loads(gt_path.read_text()).items(), key=lambda kv: int(kv[0])):
            im = int(im_key)
            rgb_path = next(iter(sorted((scene / "rgb").glob(f"{im:06d}.*"))), None)
            if rgb_path is None:
                continue
            img = cv2.imread(str(rgb_path))
            for k in range(len(gts)):
                m = cv2.imread(str(scene / "mask_visib" / f"{im:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
                if m is None:
                    continue
                contours, _ = cv2.findContours((m > 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
                c = _COLOURS[k % len(_COLOURS)]
                cv2.drawContours(img, contours, -1, (c[2], c[1], c[0]), 2)
            s = tile_width / img.shape[1]
            tiles.append(cv2.resize(img, (tile_width, int(round(img.shape[0] * s))), interpolation=cv2.INTER_AREA))
            if len(tiles) >= count:
                break
        if len(tiles) >= count:
            break
    if not tiles:
        return None
    h, w = tiles[0].shape[:2]
    rows = (len(tiles) + columns - 1) // columns
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = t[:h, :w]
    path = root / "contact_sheet.png"
    cv2.imwrite(str(path), sheet)
    return path

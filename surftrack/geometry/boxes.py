"""Image boxes: the pixel-edge convention, BOP boxes, the square crop box around a detection, and the
overlap (IoU) of two boxes.

Pixel centres lie at integer coordinates (OpenCV), so pixel u covers the EDGE interval [u - 0.5, u + 0.5]
in OpenCV coordinates. Boxes here are in pixel-EDGE coordinates, which count from the image's outer
corner: edge coordinate e is OpenCV coordinate e - 0.5, pixel u covers the edge interval [u, u + 1] and
the full image is the box (0, 0, W, H). Two layouts of the same box:

* ``xywh`` = (x, y, w, h), covering [x, x + w] x [y, y + h]: det.json, the estimator's and tracker's boxes;
* ``xyxy`` = (x0, y0, x1, y1), covering [x0, x1] x [y0, y1]: crop boxes (:func:`crop_affine`).

A BOP ``bbox`` [x, y, w, h] counts pixel INDICES instead, ``w = xmax - xmin``: the pixels it holds cover
the edge box (x, y, w + 1, h + 1) (:func:`box_from_bop`), so a one-pixel object has w = 0 and an edge box
one pixel wide.
"""

from __future__ import annotations

from collections.abc import Sequence

Box = tuple[float, float, float, float]


def box_from_bop(bbox: Sequence[float]) -> Box:
    """The pixel-edge box (x, y, w, h) covering the pixels of a BOP ``bbox`` [x, y, w, h]
    (w = xmax - xmin over pixel indices). ValueError for an empty BOP box (w or h < 0, e.g. [-1] * 4)."""
    x, y, w, h = (float(v) for v in bbox)
    if w < 0 or h < 0:
        raise ValueError(f"empty BOP box {list(bbox)}")
    return (x, y, w + 1.0, h + 1.0)


def xyxy_from_xywh(box: Sequence[float]) -> Box:
    """The corners (x0, y0, x1, y1) of a box (x, y, w, h); both in the same (edge) coordinates."""
    x, y, w, h = box
    return (x, y, x + w, y + h)


def xywh_from_xyxy(box: Sequence[float]) -> Box:
    """The box (x, y, w, h) with corners (x0, y0, x1, y1); both in the same (edge) coordinates."""
    x0, y0, x1, y1 = box
    return (x0, y0, x1 - x0, y1 - y0)


def square_crop_box(box: Sequence[float], scale: float,
                    jitter: Sequence[float] = (0.0, 0.0, 0.0)) -> Box:
    """Square pixel-edge crop box (x0, y0, x1, y1) around the pixel-edge box ``box`` = (x, y, w, h): the
    same centre, side ``scale`` x its longer side, at least 1 px. The box is not clipped to the image (a
    crop warp pads with zeros).

    ``jitter`` = (dx, dy, ds) moves the centre by (dx, dy) x the side and then scales the side by
    1 + ds (the training crops' augmentation; zeros leave the box as it is).
    """
    x, y, w, h = (float(v) for v in box)
    dx, dy, ds = (float(v) for v in jitter)
    cx, cy, side = x + w / 2.0, y + h / 2.0, float(scale) * max(w, h)
    cx, cy = cx + dx * side, cy + dy * side
    side = max(side * (1.0 + ds), 1.0)
    return (cx - side / 2.0, cy - side / 2.0, cx + side / 2.0, cy + side / 2.0)


def box_iou(a: Box, b: Box) -> float:
    """Intersection over union of two (x, y, w, h) boxes."""
    ax1, ay1, bx1, by1 = a[0] + a[2], a[1] + a[3], b[0] + b[2], b[1] + b[3]
    iw, ih = max(0.0, min(ax1, bx1) - max(a[0], b[0])), max(0.0, min(ay1, by1) - max(a[1], b[1]))
    inter = iw * ih
    union = a[2] * a[3] + b[2] * b[3] - inter
    return float(inter / union) if union > 0 else 0.0

"""The training crop box: a square box around an instance's BOP box, jittered for augmentation.

The crop geometry itself (boxes, warps, rotated crops and their cameras) is :mod:`surftrack.geometry`'s,
shared with the estimator, which crops a detection box the same way without jitter.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from surftrack.geometry import Box, box_from_bop, square_crop_box


def crop_box(bbox_xywh: Sequence[float], scale: float = 1.2, jitter: float = 0.0,
             rng: np.random.Generator | None = None) -> Box:
    """Square pixel-edge box (x0, y0, x1, y1) around a BOP box [x, y, w, h] (w = xmax - xmin): same
    centre, side = ``scale`` x the longer side of its pixels (:func:`surftrack.geometry.square_crop_box`).

    ``jitter`` > 0 (needs ``rng``) moves the centre by U(-jitter, jitter) x side along each axis and scales
    the side by 1 + U(-jitter, jitter): the box is NOT clipped to the image (the warp pads with zeros).
    ValueError for an empty BOP box.
    """
    box = box_from_bop(bbox_xywh)
    if not jitter > 0:
        return square_crop_box(box, scale)
    if rng is None:
        raise ValueError("crop jitter needs an rng")
    return square_crop_box(box, scale, rng.uniform(-jitter, jitter, size=3))

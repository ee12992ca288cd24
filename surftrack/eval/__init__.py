"""Evaluation metrics: 6-DoF pose errors (bop_toolkit definitions), ADD-10 / VOCap AUC accuracy summaries,
mask Dice and COCO keypoint OKS mAP. Numpy / scipy; of surftrack only the point transform and projection
of :mod:`surftrack.geometry`.

Pose arguments are model-to-camera (R 3x3, t (3,) or (3, 1), mm), model points (N, 3) in mm, K 3x3 pixels.
"""

from surftrack.eval.metrics import (
    add,
    add_threshold_rate,
    adds,
    auc,
    diameter_bbox_diagonal,
    diameter_max_pairwise,
    dice,
    mspd,
    mssd,
    proj,
    re,
    te,
    threshold_rate,
)
from surftrack.eval.oks import (
    OKS_THRESHOLDS,
    RECALL_THRESHOLDS,
    OksMAP,
    keypoint_oks,
    oks_ap_per_threshold,
    oks_map,
)

adi = adds  # bop_toolkit's name for ADD-S

__all__ = [
    "OKS_THRESHOLDS",
    "RECALL_THRESHOLDS",
    "OksMAP",
    "add",
    "add_threshold_rate",
    "adds",
    "adi",
    "auc",
    "diameter_bbox_diagonal",
    "diameter_max_pairwise",
    "dice",
    "keypoint_oks",
    "mspd",
    "mssd",
    "oks_ap_per_threshold",
    "oks_map",
    "proj",
    "re",
    "te",
    "threshold_rate",
]

"""Evaluation metrics: 6-DoF pose errors (bop_toolkit definitions), ADD-10 / VOCap AUC accuracy summaries,
mask Dice and COCO keypoint OKS mAP. Pure numpy / scipy; depends on no other surftrack stage.

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
    project_points,
    re,
    te,
    threshold_rate,
    transform_points,
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
    "project_points",
    "re",
    "te",
    "threshold_rate",
    "transform_points",
]

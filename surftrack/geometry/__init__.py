"""Rigid-body transforms, the pinhole camera and its projection, image boxes and crops.

The one home of the package's geometry: :func:`transform_points` (poses on points),
:func:`project_points` (pinhole projection), box conventions and conversions (:mod:`.boxes`) and crop
warps (:func:`crop_affine`, :func:`crop_warp`, :mod:`.crop`: into a crop and, :func:`unwarp_image`, back).
"""

from surftrack.geometry.boxes import Box, box_from_bop, box_iou, square_crop_box, xywh_from_xyxy, xyxy_from_xywh
from surftrack.geometry.camera import (
    PinholeCamera,
    crop_affine,
    crop_warp,
    project_pose_jacobian,
    project_points,
    projected_box,
)
from surftrack.geometry.crop import crop_with_rotation, pose_in_crop, unwarp_image, warp_image
from surftrack.geometry.transforms import (
    cross3,
    interpolate_pose,
    matrix_from_quat_xyzw,
    quat_xyzw_from_matrix,
    rotation_about,
    rotation_angle_deg,
    se3,
    se3_compose,
    se3_exp,
    se3_inv,
    se3_log,
    se3_split,
    skew,
    slerp,
    so3_exp,
    so3_log,
    so3_right_jacobian,
    transform_points,
)

__all__ = [
    "Box", "PinholeCamera", "box_from_bop", "box_iou", "crop_affine", "crop_warp", "cross3",
    "crop_with_rotation", "interpolate_pose", "matrix_from_quat_xyzw", "pose_in_crop", "project_points",
    "project_pose_jacobian", "projected_box", "quat_xyzw_from_matrix", "rotation_about", "rotation_angle_deg",
    "se3", "se3_compose", "se3_exp", "se3_inv", "se3_log", "se3_split", "skew", "slerp", "so3_exp", "so3_log",
    "so3_right_jacobian", "square_crop_box", "transform_points", "unwarp_image", "warp_image",
    "xywh_from_xyxy", "xyxy_from_xywh",
]

"""Rigid-body transforms and the pinhole camera."""

from surftrack.geometry.camera import PinholeCamera, crop_affine
from surftrack.geometry.transforms import (
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
    slerp,
    so3_exp,
    so3_log,
    transform_points,
)

__all__ = [
    "PinholeCamera", "crop_affine", "interpolate_pose", "matrix_from_quat_xyzw", "quat_xyzw_from_matrix",
    "rotation_about", "rotation_angle_deg", "se3", "se3_compose", "se3_exp", "se3_inv", "se3_log",
    "se3_split", "slerp", "so3_exp", "so3_log", "transform_points",
]

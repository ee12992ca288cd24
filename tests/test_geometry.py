import numpy as np
import pytest

from surftrack.geometry import (
    PinholeCamera,
    crop_affine,
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
    slerp,
    so3_exp,
    so3_log,
    transform_points,
)
from surftrack.instruments import rcm_base_pose

rng = np.random.default_rng(7)


def random_pose():
    return se3(so3_exp(rng.normal(size=3)), rng.normal(scale=50, size=3))


def test_so3_exp_log_round_trip_batched():
    w = rng.normal(size=(20, 3))
    w *= (np.pi - 1e-3) * rng.random((20, 1)) / np.linalg.norm(w, axis=1, keepdims=True)
    R = so3_exp(w)
    assert R.shape == (20, 3, 3)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(so3_log(R), w, atol=1e-9)


def test_rotation_about_matches_right_hand_rule():
    R = rotation_about([0, 0, 2.0], np.pi / 2)
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])
    with pytest.raises(ValueError):
        rotation_about([0, 0, 0], 1.0)


def test_se3_exp_log_round_trip_and_small_angles():
    for scale in (1.0, 1e-8):
        xi = rng.normal(size=(10, 6)) * scale
        T = se3_exp(xi)
        assert np.allclose(se3_log(T), xi, atol=1e-10 * max(scale, 1e-3))
    # Pure translation twist is a pure translation.
    assert np.allclose(se3_exp(np.array([1.0, 2, 3, 0, 0, 0])), se3(np.eye(3), [1, 2, 3]))
    # A full screw: rotating pi/2 about z while moving along the axis.
    T = se3_exp(np.array([0, 0, 1.0, 0, 0, np.pi / 2]))
    assert np.allclose(T[:3, 3], [0, 0, 1.0])


def test_inverse_and_compose():
    A, B = random_pose(), random_pose()
    assert np.allclose(se3_compose(A, se3_inv(A)), np.eye(4), atol=1e-12)
    assert np.allclose(se3_compose(A, B), A @ B)
    p = rng.normal(size=(5, 3))
    assert np.allclose(transform_points(se3_inv(A), transform_points(A, p)), p)


def test_quaternion_is_xyzw_and_round_trips():
    q = quat_xyzw_from_matrix(rotation_about([0, 0, 1], np.pi / 2))
    assert np.allclose(q, [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    R = so3_exp(rng.normal(size=(8, 3)))
    q = quat_xyzw_from_matrix(R)
    assert (q[:, 3] >= 0).all()
    assert np.allclose(matrix_from_quat_xyzw(q), R)


def test_slerp_and_pose_interpolation():
    R0, R1 = np.eye(3), rotation_about([1, 0, 0], 1.0)
    assert np.allclose(slerp(R0, R1, 0.5), rotation_about([1, 0, 0], 0.5))
    T0, T1 = se3(R0, [0, 0, 0]), se3(R1, [10, 0, 0])
    T = interpolate_pose(T0, T1, 0.25)
    assert np.allclose(T[:3, 3], [2.5, 0, 0])
    assert np.isclose(rotation_angle_deg(T[:3, :3], R0), np.degrees(0.25))


def test_rotation_angle_deg_clips_numerical_noise():
    R = so3_exp(rng.normal(size=3))
    assert rotation_angle_deg(R, R) == pytest.approx(0.0, abs=1e-5)
    assert rotation_angle_deg(rotation_about([0, 1, 0], np.pi), np.eye(3)) == pytest.approx(180.0)


def test_camera_project_backproject_round_trip():
    cam = PinholeCamera(np.array([[800.0, 0, 320], [0, 790, 250], [0, 0, 1]]), 640, 512)
    p = np.column_stack([rng.uniform(-20, 20, 50), rng.uniform(-20, 20, 50), rng.uniform(30, 150, 50)])
    uv = cam.project(p)
    assert np.allclose(cam.backproject(uv, p[:, 2]), p)
    assert cam.rays()[250, 320].tolist() == [0.0, 0.0, 1.0]
    with pytest.raises(ValueError):
        PinholeCamera(np.eye(3) * 0, 640, 512)
    assert PinholeCamera.from_dict(cam.to_dict()).K.tolist() == cam.K.tolist()


def test_crop_camera_agrees_with_warp_matrix():
    cam = PinholeCamera(np.array([[800.0, 0, 320], [0, 790, 250], [0, 0, 1]]), 640, 512)
    box = (100.3, 80.7, 300.3, 240.7)
    M, crop = crop_affine(cam, box, (224, 224))
    p = np.column_stack([rng.uniform(-5, 5, 20), rng.uniform(-5, 5, 20), rng.uniform(60, 90, 20)])
    uv = cam.project(p)
    uv_crop = np.c_[uv, np.ones(len(uv))] @ M.T
    assert np.allclose(crop.project(p), uv_crop)
    # Box edges map to the crop's edges: edge x0 is OpenCV coordinate x0 - 0.5, the crop's edge is -0.5.
    assert np.allclose(M @ [box[0] - 0.5, box[1] - 0.5, 1], [-0.5, -0.5])
    assert np.allclose(M @ [box[2] - 0.5, box[3] - 0.5, 1], [224 - 0.5, 224 - 0.5])
    # Resizing the whole image keeps the field of view.
    half = cam.resized(320, 256)
    assert np.allclose(half.project(p), (uv + 0.5) / 2 - 0.5)


def test_crop_pixels_agree_with_cv2_warp():
    import cv2

    cam = PinholeCamera(np.array([[500.0, 0, 100], [0, 500, 80], [0, 0, 1]]), 200, 160)
    img = np.zeros((160, 200), np.float32)
    img[70, 120] = 1.0
    M, crop = crop_affine(cam, (110.0, 60.0, 130.0, 80.0), (40, 40))  # 2x upscale
    warped = cv2.warpAffine(img, M, (40, 40), flags=cv2.INTER_LINEAR)
    v, u = np.unravel_index(np.argmax(warped), warped.shape)
    expect = M @ [120, 70, 1]
    assert abs(u - expect[0]) <= 0.5 and abs(v - expect[1]) <= 0.5


def test_rcm_base_pose_passes_through_trocar():
    trocar, pitch = np.array([-70.0, -50, 10]), np.array([5.0, 3, 70])
    T = rcm_base_pose(trocar, pitch)
    z = T[:3, 2]
    assert np.allclose(T[:3, 3], pitch)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.isclose(np.linalg.det(T[:3, :3]), 1)
    # Distance from the trocar to the shaft axis line.
    d = np.linalg.norm(np.cross(trocar - pitch, z))
    assert d < 1e-9
    assert np.dot(pitch - trocar, z) > 0
    # Degenerate reference (shaft along camera z) still gives a valid frame.
    T2 = rcm_base_pose([0, 0, 0], [0, 0, 50])
    assert np.isclose(np.linalg.det(T2[:3, :3]), 1)

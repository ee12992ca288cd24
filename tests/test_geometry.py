import cv2
import numpy as np
import pytest

from surftrack.geometry import (
    PinholeCamera,
    box_from_bop,
    box_iou,
    crop_affine,
    interpolate_pose,
    matrix_from_quat_xyzw,
    project_points,
    projected_box,
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
    square_crop_box,
    transform_points,
    warp_image,
    xywh_from_xyxy,
    xyxy_from_xywh,
)
from surftrack.instruments import rcm_base_pose
from surftrack.synth.bop_writer import bbox_xywh

rng = np.random.default_rng(7)


def random_pose():
    return se3(so3_exp(rng.normal(size=3)), rng.normal(scale=50, size=3))


@pytest.mark.parametrize("batch", [False, True])
def test_so3_exp_log_match_scipy_near_zero_and_pi(batch):
    """The numpy exponential and logarithm against scipy's, one at a time and batched, over angles from
    0 and 1e-14 rad to pi and pi - 1e-12 (where the axis-angle sign is ambiguous: compared as matrices)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    axes = rng.normal(size=(800, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, 400), np.full(100, np.pi), np.pi - 10.0 ** -rng.uniform(1, 12, 100),
                             10.0 ** -rng.uniform(1, 14, 100), np.zeros(100)])
    w = axes * angles[:, None]
    ref = Rotation.from_rotvec(w).as_matrix()
    R = so3_exp(w) if batch else np.stack([so3_exp(v) for v in w])
    assert np.abs(R - ref).max() < 1e-12
    logs = so3_log(ref) if batch else np.stack([so3_log(m) for m in ref])
    assert np.abs(Rotation.from_rotvec(logs).as_matrix() - ref).max() < 1e-13
    assert np.linalg.norm(logs, axis=1).max() <= np.pi + 1e-12
    away = angles < 3.1
    assert np.abs(logs[away] - Rotation.from_matrix(ref[away]).as_rotvec()).max() < 1e-12


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


# ------------------------------------------------------------------ conventions, pinned against OpenCV and 4x4 matrices
def random_intrinsics(r: np.random.Generator) -> np.ndarray:
    fx = r.uniform(200.0, 2000.0)
    return np.array([[fx, 0.0, r.uniform(100.0, 700.0)], [0.0, fx * r.uniform(0.9, 1.1), r.uniform(100.0, 500.0)],
                     [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("seed", range(5))
def test_projection_matches_cv2_project_points(seed):
    """Model points at a random pose through random intrinsics, no distortion: the same pixels as
    cv2.projectPoints (which takes the model-to-camera rotation vector and translation)."""
    r = np.random.default_rng(seed)
    K = random_intrinsics(r)
    R, t = so3_exp(r.normal(size=3)), np.r_[r.normal(scale=20.0, size=2), r.uniform(80.0, 300.0)]
    X = r.normal(scale=15.0, size=(200, 3))
    expect, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, np.zeros(5))
    uv = project_points(K, transform_points(se3(R, t), X))
    assert uv.shape == (200, 2)
    np.testing.assert_allclose(uv, expect.reshape(-1, 2), rtol=0, atol=1e-8)
    cam = PinholeCamera(K, 800, 600)
    assert np.array_equal(cam.project(transform_points(se3(R, t), X)), uv)
    # a skewed K (a rotated crop's camera) is the full product K @ X, divided by depth
    Ks = K.copy()
    Ks[0, 1] = r.uniform(-5.0, 5.0)
    Xc = transform_points(se3(R, t), X)
    uvw = Xc @ Ks.T
    np.testing.assert_allclose(project_points(Ks, Xc), uvw[:, :2] / uvw[:, 2:3], rtol=0, atol=1e-8)
    # any leading shape; the principal point is where the optical axis lands
    assert project_points(K, X.reshape(10, 20, 3) + [0, 0, 100]).shape == (10, 20, 2)
    assert np.allclose(project_points(K, np.array([0.0, 0.0, 5.0])), K[:2, 2])


def test_projection_of_points_behind_the_camera_is_left_to_the_caller():
    uv = project_points(np.eye(3), np.array([[1.0, 2.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, -2.0]]))
    assert not np.isfinite(uv[:2]).any() and np.allclose(uv[2], [-0.5, -0.5])


@pytest.mark.parametrize("seed", range(5))
def test_transform_points_is_the_homogeneous_product(seed):
    """transform_points(T, x) == (T @ [x, 1])[:3] for a 4x4 pose T; composing poses composes transforms."""
    r = np.random.default_rng(seed)
    A, B = (se3(so3_exp(r.normal(size=3)), r.normal(scale=50.0, size=3)) for _ in range(2))
    X = r.normal(scale=30.0, size=(50, 3))
    homogeneous = np.c_[X, np.ones(len(X))] @ A.T
    assert np.allclose(homogeneous[:, 3], 1.0)
    np.testing.assert_allclose(transform_points(A, X), homogeneous[:, :3], rtol=0, atol=1e-10)
    np.testing.assert_allclose(transform_points(A @ B, X), transform_points(A, transform_points(B, X)),
                               rtol=0, atol=1e-10)
    # the rotation acts on the point, then the translation is added: x' = R x + t
    R, t = se3_split(A)
    np.testing.assert_allclose(transform_points(A, X), X @ R.T + t, rtol=0, atol=1e-12)


def test_bop_box_covers_its_pixels_in_edge_coordinates():
    """Pixel u covers the edge interval [u, u + 1]: a BOP box over pixel indices (w = xmax - xmin) is the
    edge box (x, y, w + 1, h + 1), whose corners in OpenCV (pixel-centre) coordinates are x - 0.5 and
    x + w + 0.5."""
    mask = np.zeros((60, 80), bool)
    mask[30:40, 10:20] = True  # columns 10..19, rows 30..39
    bb = bbox_xywh(mask)
    assert bb == [10, 30, 9, 9]
    assert box_from_bop(bb) == (10.0, 30.0, 10.0, 10.0)
    assert xyxy_from_xywh(box_from_bop(bb)) == (10.0, 30.0, 20.0, 40.0)
    # one pixel: w = 0, one pixel wide; the crop of exactly that box holds only that pixel
    img = np.zeros((20, 30), np.uint8)
    img[7, 12] = 255
    box = xyxy_from_xywh(box_from_bop(bbox_xywh(img > 0)))
    assert box == (12.0, 7.0, 13.0, 8.0)
    cam = PinholeCamera(np.array([[50.0, 0, 14.5], [0, 50.0, 9.5], [0, 0, 1]]), 30, 20)
    M, crop = crop_affine(cam, box, (4, 4))
    assert (warp_image(img, M, 4, nearest=True) == 255).all()
    assert np.allclose(M @ [12.0, 7.0, 1.0], [1.5, 1.5])  # the pixel's centre is the crop's centre
    assert np.allclose(crop.project(cam.backproject(np.array([[12.0, 7.0]]), np.array([40.0]))), [[1.5, 1.5]])
    with pytest.raises(ValueError):
        box_from_bop([-1, -1, -1, -1])  # BOP's empty box


def test_box_conversions_round_trip():
    r = np.random.default_rng(3)
    for _ in range(50):
        xywh = tuple(np.r_[r.uniform(-50, 500, 2), r.uniform(0.5, 200, 2)])
        assert np.allclose(xywh_from_xyxy(xyxy_from_xywh(xywh)), xywh, rtol=0, atol=1e-12)
        xyxy = xyxy_from_xywh(xywh)
        assert np.allclose(xyxy_from_xywh(xywh_from_xyxy(xyxy)), xyxy, rtol=0, atol=1e-12)
        # BOP [x, y, w, h] (integers) -> edge (x0, y0, x1, y1) -> back: w = x1 - x0 - 1
        bop = [int(v) for v in np.r_[r.integers(0, 500, 2), r.integers(0, 100, 2)]]
        x0, y0, x1, y1 = xyxy_from_xywh(box_from_bop(bop))
        assert [x0, y0, x1 - x0 - 1, y1 - y0 - 1] == bop


def test_square_crop_box():
    # centre kept, side = scale x the longer side, pixel-edge corners
    assert square_crop_box((10.0, 20.0, 30.0, 10.0), 1.5) == (2.5, 2.5, 47.5, 47.5)
    assert square_crop_box((10.0, 20.0, 10.0, 30.0), 1.0) == (0.0, 20.0, 30.0, 50.0)
    # never under one pixel
    assert square_crop_box((5.0, 5.0, 0.1, 0.2), 1.2) == (4.55, 4.6, 5.55, 5.6)
    # jitter: the centre moves by (dx, dy) x side, then the side scales by 1 + ds
    x0, y0, x1, y1 = square_crop_box((10.0, 20.0, 30.0, 10.0), 1.5, (0.1, -0.2, 0.5))
    assert np.allclose([(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0], [25 + 4.5, 25 - 9.0, 67.5, 67.5])


def test_project_pose_jacobian_matches_central_differences():
    """The analytic derivative of projected model points with respect to the trackers' pose step
    (t + dt, R exp(dtheta)), against central differences of ``project_points``."""
    from surftrack.geometry import project_pose_jacobian

    r = np.random.default_rng(8)
    K = np.array([[450.0, 0, 320], [0, 455.0, 250], [0, 0, 1]])
    R, t = so3_exp(r.normal(size=3)), np.array([4.0, -6.0, 70.0])
    X = r.normal(scale=8.0, size=(30, 3))
    uv, J = project_pose_jacobian(K, R, t, X)
    np.testing.assert_allclose(uv, project_points(K, X @ R.T + t), atol=1e-12)
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-6
        up = project_points(K, X @ (R @ so3_exp(d[3:])).T + t + d[:3])
        dn = project_points(K, X @ (R @ so3_exp(-d[3:])).T + t - d[:3])
        np.testing.assert_allclose(J[:, :, k], (up - dn) / 2e-6, rtol=1e-5, atol=1e-5)


def test_unwarp_image_carries_a_crop_back_into_the_frame():
    """A smooth image warped into an upscaled crop and carried back with unwarp_image matches itself on
    the pixels the crop saw (bilinear both ways), and only those are marked covered."""
    from surftrack.geometry import crop_warp, unwarp_image

    yy, xx = np.mgrid[0:120, 0:160].astype(np.float32)
    img = np.sin(xx / 9.0) + np.cos(yy / 7.0)
    box = (40.0, 30.0, 100.0, 90.0)
    M = crop_warp(box, (120, 120))  # 2x
    crop = warp_image(img, M, (120, 120))
    back, covered = unwarp_image(crop, M, (160, 120))
    assert back.shape == covered.shape == (120, 160)
    assert covered[30:90, 40:100].all() and not covered[:29].any() and not covered[:, :39].any()
    assert not covered[91:].any() and not covered[:, 101:].any()
    inner = np.zeros_like(covered)
    inner[32:88, 42:98] = True
    assert np.abs(back - img)[inner].max() < 0.02
    assert (back[~covered] == 0).all()
    # where a crop pixel lands: crop pixel centre c comes from image pixel centre (c - M[:, 2]) / scale
    dot = np.zeros((120, 120), np.float32)
    dot[60, 60] = 1.0
    back, _ = unwarp_image(dot, M, (160, 120))
    v, u = np.unravel_index(np.argmax(back), back.shape)
    assert abs(u - (60 - M[0, 2]) / M[0, 0]) <= 0.5 and abs(v - (60 - M[1, 2]) / M[1, 1]) <= 0.5


def test_box_helpers():
    assert box_iou((0, 0, 10, 10), (5, 0, 10, 10)) == pytest.approx(50 / 150)
    assert box_iou((0, 0, 10, 10), (20, 20, 5, 5)) == 0.0
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    box, inside = projected_box(K, np.eye(3), np.array([0, 0, 20.0]), cube, (100, 100))
    assert inside == 1.0 and box[0] == pytest.approx(50 - 100 / 19) and box[2] == pytest.approx(200 / 19 + 1)
    box, inside = projected_box(K, np.eye(3), np.array([-52.0, 0, 20.0]), cube, (100, 100))
    assert box is None and inside == 0.0

"""Overlay drawing (axes, silhouettes, labels), the overlay video writer, and TUM trajectory files."""

import cv2
import numpy as np
import pytest
import trimesh
from scipy.ndimage import binary_dilation, binary_fill_holes
from scipy.spatial.transform import Rotation

from surftrack.geometry import PinholeCamera, rotation_about, rotation_angle_deg, se3
from surftrack.instruments import load_instrument
from surftrack.io import (
    OverlayWriter,
    PartOverlay,
    TumWriter,
    draw_overlay,
    mesh_outline,
    project_axes,
    read_tum,
)
from surftrack.io import overlay
from surftrack.io.overlay import BOX_COLOR, STATUS_COLORS
from surftrack.io.video import read_video_frames

from .raycast import edge_pixels, raycast


def filled(contours, W, H):
    """Boolean mask of the regions enclosed by ``contours`` (their boundary pixels included)."""
    m = np.zeros((H, W), np.uint8)
    cv2.drawContours(m, [c.reshape(-1, 1, 2).astype(np.int32) for c in contours], -1, 1, -1)
    return m.astype(bool)


# --------------------------------------------------------------------------------------------- axes


def test_project_axes_matches_hand_computed_projection():
    K = np.array([[500.0, 0, 320], [0, 400.0, 256], [0, 0, 1]])
    R = rotation_about([0, 0, 1], np.pi / 2)  # part x -> camera y, part y -> camera -x
    uv = project_axes(K, R, [10.0, -20.0, 100.0], 10.0)
    # origin (10, -20, 100); x tip (10, -10, 100); y tip (0, -20, 100); z tip (10, -20, 110)
    expected = [[370.0, 176.0], [370.0, 216.0], [320.0, 176.0], [320 + 5000 / 110, 256 - 8000 / 110]]
    np.testing.assert_allclose(uv, expected, atol=1e-9)


def test_project_axes_behind_the_camera_is_nan():
    R = rotation_about([1, 0, 0], np.pi)  # the part's z axis points back through the camera
    uv = project_axes(np.diag([500.0, 500.0, 1.0]), R, [0.0, 0.0, 5.0], 10.0)
    assert np.all(np.isfinite(uv[:3])) and np.all(np.isnan(uv[3]))
    with pytest.raises(ValueError, match="length_mm"):
        project_axes(np.eye(3), np.eye(3), [0, 0, 5], 0.0)


# --------------------------------------------------------------------------------------------- outlines


def test_box_outline_face_on_is_its_projected_front_face():
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 255.5], [0, 0, 1]])
    box = trimesh.creation.box(extents=(20.0, 10.0, 4.0))
    contours = mesh_outline(K, np.eye(3), [0.0, 0.0, 100.0], box.vertices, box.faces, (640, 512))
    assert len(contours) == 1 and contours[0].shape[1] == 2
    # the front face at z = 98 mm hides the rest: x in +-10 mm, y in +-5 mm
    hx, hy = 500 * 10 / 98, 500 * 5 / 98
    lo, hi = contours[0].min(axis=0), contours[0].max(axis=0)
    np.testing.assert_allclose(lo, [319.5 - hx, 255.5 - hy], atol=1.0)
    np.testing.assert_allclose(hi, [319.5 + hx, 255.5 + hy], atol=1.0)
    area = filled(contours, 640, 512).sum()
    assert abs(area - 4 * hx * hy) < 2 * (hx + hy) * 1.0  # within one pixel along the perimeter


def _lnd_part(name):
    mesh = load_instrument("lnd").parts[name].mesh
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _box(extents, centre):
    b = trimesh.creation.box(extents=extents)
    return np.asarray(b.vertices) + centre, np.asarray(b.faces)


def _scrambled_box():
    """An open box (one triangle of its -x side missing) whose +z side, seen by the camera below, is wound
    the other way: two of its edges are on the silhouette."""
    b = trimesh.creation.box(extents=(10.0, 6.0, 8.0))
    F = np.asarray(b.faces).copy()
    normals = np.asarray(b.face_normals)
    F[normals[:, 2] > 0.5] = F[normals[:, 2] > 0.5, ::-1]
    return np.asarray(b.vertices), np.delete(F, np.flatnonzero(normals[:, 0] < -0.5)[0], axis=0)


CASES = {
    # name: (vertices, faces, R, t)
    "wrist oblique": (*_lnd_part("wrist"), rotation_about([1, 0.4, 0.2], 1.1), [2.0, 1.0, 30.0]),
    "shaft across the border": (*_lnd_part("shaft"), rotation_about([0.2, 1, 0], 1.3), [25.0, 5.0, 40.0]),
    "open, inconsistently wound": (*_scrambled_box(), rotation_about([1, 1, 0], 2.5), [0.0, 0.0, 40.0]),
    "long rod far beyond the view": (*_box((3000.0, 6.0, 6.0), (0, 0, 0)), rotation_about([0, 0, 1], 0.3),
                                     [0.0, 4.0, 80.0]),
    "through the camera plane": (*_box((10.0, 10.0, 200.0), (30.0, 5.0, 50.0)), np.eye(3), [0.0, 0.0, 0.0]),
    # its cross-section with the near plane (z = 1 mm) projects just right of the image
    "rod beside the lens": (*_box((0.8, 1.0, 40.0), (1.2, 0.0, 10.0)), np.eye(3), [0.0, 0.0, 0.0]),
}


@pytest.mark.parametrize("path", ["outline", "triangles"])
@pytest.mark.parametrize("case", list(CASES))
def test_outline_matches_raycast_silhouette(case, path, monkeypatch):
    """Both silhouette algorithms agree with ray casting up to the one-pixel ring along the boundary."""
    if path == "triangles":  # no outline canvas is small enough: fill the clipped triangles one by one
        monkeypatch.setattr(overlay, "_MAX_CANVAS_IMAGES", 0.0)
    V, F, R, t = CASES[case]
    cam = PinholeCamera.from_fov(160, 128, 70)
    mask = filled(mesh_outline(cam.K, R, t, V, F, (160, 128)), 160, 128)
    ids = raycast(cam, {1: (trimesh.Trimesh(V, F, process=False), se3(R, np.asarray(t)))})[0]
    ref = binary_fill_holes(ids == 1)
    assert ref.sum() > 150
    off_edge = (mask ^ ref) & ~binary_dilation(edge_pixels(ref.astype(int)))
    assert off_edge.sum() == 0
    assert (mask & ref).sum() / (mask | ref).sum() > 0.85


def test_outline_of_invisible_mesh_is_empty_and_inputs_are_checked():
    K = PinholeCamera.from_fov(160, 128, 70).K
    V, F = _box((4.0, 4.0, 4.0), (0, 0, 0))
    assert mesh_outline(K, np.eye(3), [0, 0, -50.0], V, F, (160, 128)) == []   # behind the camera
    assert mesh_outline(K, np.eye(3), [500, 0, 50.0], V, F, (160, 128)) == []  # beside the view
    with pytest.raises(ValueError, match="face indices"):
        mesh_outline(K, np.eye(3), [0, 0, 50.0], V, F + 100, (160, 128))
    with pytest.raises(ValueError, match="3x3"):
        mesh_outline(K, np.eye(4), [0, 0, 50.0], V, F, (160, 128))


# --------------------------------------------------------------------------------------------- drawing

W, H = 320, 256
CAM = PinholeCamera.from_fov(W, H, 70)


def _near(img, uv, color, radius=1, tol=70):
    """Whether some pixel within ``radius`` of ``uv`` has (roughly) ``color``."""
    x, y = int(round(uv[0])), int(round(uv[1]))
    patch = img[y - radius:y + radius + 1, x - radius:x + radius + 1].astype(int)
    return bool((np.abs(patch - color).max(axis=-1) < tol).any())


def test_draw_overlay_draws_axes_outline_box_and_labels():
    frame = np.full((H, W, 3), 90, np.uint8)
    V, F = _box((8.0, 8.0, 8.0), (0, 0, 0))
    R, t = rotation_about([1, 1, 0], 0.5), np.array([-15.0, 5.0, 70.0])
    tracked = PartOverlay("jaw", "tracking", 0.87, R, t, box=(150.0, 40.0, 100.0, 60.0), mesh=(V, F),
                          axis_length_mm=12.0)
    lost = PartOverlay("wrist", "lost", 0.1, R, t + [35.0, 0, 0], mesh=(V, F))
    before = frame.copy()
    out = draw_overlay(frame, CAM.K, [tracked, lost], time_s=1.25)
    np.testing.assert_array_equal(frame, before)  # the input is left alone
    assert out.shape == frame.shape and out.dtype == np.uint8

    uv = project_axes(CAM.K, R, t, 12.0)
    for k, color in ((1, (255, 40, 40)), (2, (40, 230, 40))):  # x red, y green, near their tips
        assert _near(out, uv[0] + 0.85 * (uv[k] - uv[0]), color, tol=60), k
    assert not _near(frame, uv[1], (255, 40, 40), tol=60)

    outline = mesh_outline(CAM.K, R, t, V, F, (W, H))[0]
    on_outline = np.mean([_near(out, p, STATUS_COLORS["tracking"]) for p in outline])
    assert on_outline > 0.8
    lost_outline = mesh_outline(CAM.K, R, t + [35.0, 0, 0], V, F, (W, H))[0]
    np.testing.assert_array_equal(out[lost_outline[:, 1], lost_outline[:, 0]],
                                  frame[lost_outline[:, 1], lost_outline[:, 0]])  # lost: nothing drawn

    # pixel-edge box (150, 40, 100, 60): its top edge runs along y = 39.5 in pixel-centre coordinates
    top = out[39:41, 200].astype(int)
    assert (out[42:46, 200] == 90).all()
    assert (np.abs(top - BOX_COLOR).max(axis=-1) < 60).any()
    assert (out[H - 40:, W - 40:] == 90).all()  # untouched far from every part
    legend = out[:60, :160].astype(int)
    reddish = (legend[..., 0] > legend[..., 1] + 60) & (legend[..., 0] > legend[..., 2] + 60)
    assert reddish.sum() > 20  # the lost part's line, in the "lost" colour
    assert (legend < 60).mean() > 0.3  # the dimmed panel


def test_predicted_outline_is_yellow_and_poseless_parts_draw_no_geometry():
    frame = np.full((H, W, 3), 90, np.uint8)
    V, F = _box((8.0, 8.0, 8.0), (0, 0, 0))
    R, t = np.eye(3), np.array([0.0, 0.0, 60.0])
    out = draw_overlay(frame, CAM.K, [PartOverlay("tip", "predicted", 0.5, R, t, mesh=(V, F))])
    outline = mesh_outline(CAM.K, R, t, V, F, (W, H))[0]
    assert np.mean([_near(out, p, STATUS_COLORS["predicted"]) for p in outline]) > 0.8
    bare = draw_overlay(frame, CAM.K, [PartOverlay("tip", "init", 0.0)])
    assert (bare[60:] == 90).all()  # only the legend at the top-left


def test_part_overlay_checks_its_fields():
    with pytest.raises(ValueError, match="status"):
        PartOverlay("a", "tracked", 0.5)
    with pytest.raises(ValueError, match="confidence"):
        PartOverlay("a", "tracking", 1.5)
    with pytest.raises(ValueError, match="both R and t"):
        PartOverlay("a", "tracking", 0.5, R=np.eye(3))
    with pytest.raises(ValueError, match="box"):
        PartOverlay("a", "tracking", 0.5, box=(0, 0, -1, 5))


# --------------------------------------------------------------------------------------------- video

VW, VH = 128, 96
VCAM = PinholeCamera.from_fov(VW, VH, 70)


def _frames(n):
    V, F = _box((6.0, 6.0, 6.0), (0, 0, 0))
    ramp = np.linspace(60, 140, VW)[None, :, None] + np.linspace(0, 30, VH)[:, None, None]
    for i in range(n):
        frame = np.broadcast_to(ramp + (0, 4 * i, 10), (VH, VW, 3)).astype(np.uint8)
        part = PartOverlay("jaw", "tracking", 0.9, rotation_about([0, 1, 0], 0.1 * i), [0.0, 0.0, 50.0 + i],
                           box=(20.0, 20.0, 40.0, 30.0), mesh=(V, F))
        yield frame, [part]


def test_overlay_writer_roundtrip(tmp_path):
    path = tmp_path / "overlay.mp4"
    times = [0.0, 0.04, 0.08, 0.15, 0.19, 0.23]
    raw, drawn = [], []
    with OverlayWriter(path, 25.0, VW, VH, VCAM.K) as writer:
        for t, (frame, parts) in zip(times, _frames(len(times))):
            writer.write(frame, t, parts)
            raw.append(frame)
            drawn.append(draw_overlay(frame, VCAM.K, parts, t))
    assert writer.closed and writer.frames_written == len(times)
    writer.close()  # idempotent
    decoded = list(read_video_frames(path))
    assert len(decoded) == len(times)
    np.testing.assert_allclose([t for t, _ in decoded], times, atol=1e-3)
    for (_, img), frame, expected in zip(decoded, raw, drawn):
        assert img.shape == (VH, VW, 3)
        changed = (frame != expected).any(axis=-1)  # where the overlay drew
        err_drawn = np.abs(img.astype(int) - expected)[changed].mean()
        err_raw = np.abs(img.astype(int) - frame)[changed].mean()
        assert err_drawn < 0.3 * err_raw  # the video shows the overlay, up to H.264 losses
        assert np.abs(img.astype(int) - expected)[~changed].mean() < 3
    with pytest.raises(ValueError, match="closed"):
        writer.write(drawn[0], 1.0)


def test_overlay_writer_interrupted_leaves_a_playable_file(tmp_path):
    path = tmp_path / "crash.mp4"
    with pytest.raises(RuntimeError, match="boom"):
        with OverlayWriter(path, 25.0, VW, VH, VCAM.K) as writer:
            for i, (frame, parts) in enumerate(_frames(3)):
                writer.write(frame, i / 25.0, parts)
            raise RuntimeError("boom")
    assert writer.closed
    assert len(list(read_video_frames(path))) == 3


def test_overlay_writer_rejects_unwritable_paths(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a directory")
    (tmp_path / "dir.mp4").mkdir()
    for bad in (tmp_path / "missing" / "o.mp4", blocker / "o.mp4", tmp_path / "dir.mp4"):
        with pytest.raises(OSError) as e:
            OverlayWriter(bad, 25.0, VW, VH, VCAM.K)
        assert str(bad) in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(ValueError, match="o.avi1"):
        OverlayWriter(tmp_path / "o.avi1", 25.0, VW, VH, VCAM.K)
    OverlayWriter(tmp_path / "empty.mp4", 25.0, VW, VH, VCAM.K).close()
    assert not (tmp_path / "empty.mp4").exists()  # no frames: no (unplayable) file


# --------------------------------------------------------------------------------------------- TUM


def test_tum_roundtrip_in_metres(tmp_path):
    out = tmp_path / "run" / "tum"
    rots = Rotation.random(25, random_state=1).as_matrix()
    ts = np.random.default_rng(1).uniform(-150.0, 150.0, (25, 3))
    times = 3.0 + np.arange(25) * 0.033333333
    with TumWriter(out) as writer:
        assert out.is_dir() and not list(out.iterdir())  # files only for parts that get a pose
        for time_s, R, t in zip(times, rots, ts):
            writer.add("jaw/left", time_s, R, t)
        path = writer.paths["jaw/left"]
        assert path.name == "jaw_left.tum"
        assert len(path.read_text().splitlines()) == 26  # flushed while still open
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# time tx ty tz qx qy qz qw")
    for line, t in zip(lines[1:], ts):
        fields = line.split(" ")  # evo: single spaces, exactly 8 entries, no trailing delimiter
        assert len(fields) == 8
        np.testing.assert_allclose([float(v) for v in fields[1:4]], t / 1000.0, atol=1e-9)
        assert float(fields[7]) >= 0.0
    times_r, R_r, t_r = read_tum(path)
    np.testing.assert_allclose(times_r, times, atol=1e-9)
    np.testing.assert_allclose(t_r, ts, atol=1e-3)  # 1e-6 m
    assert np.radians(rotation_angle_deg(R_r, rots)).max() < 1e-6


def test_tum_writer_names_closing_and_errors(tmp_path):
    writer = TumWriter(tmp_path)
    writer.add("jaw_left", 0.0, np.eye(3), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="both map to"):
        writer.add("jaw/left", 0.1, np.eye(3), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="rotation"):
        writer.add("shaft", 0.1, 2.0 * np.eye(3), [1.0, 2.0, 3.0])
    assert not (tmp_path / "shaft.tum").exists()  # a rejected pose creates no file
    writer.close()
    writer.close()
    with pytest.raises(ValueError, match="closed"):
        writer.add("jaw_left", 0.2, np.eye(3), [1.0, 2.0, 3.0])

    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    with pytest.raises(OSError) as e:
        TumWriter(blocker / "tum")
    assert str(blocker / "tum") in str(e.value)

    bad = tmp_path / "bad.tum"
    bad.write_text("# header\n0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match="bad.tum:3"):
        read_tum(bad)
    with pytest.raises(ValueError, match="missing.tum"):
        read_tum(tmp_path / "missing.tum")


def test_tum_writer_removes_an_earlier_runs_files_only(tmp_path):
    with TumWriter(tmp_path) as w:
        w.add("shaft", 0.0, np.eye(3), [1.0, 2.0, 3.0])
        w.add("wrist", 0.0, np.eye(3), [1.0, 2.0, 3.0])
    mine = tmp_path / "notes.tum"
    mine.write_text("# my own trajectory\n0.0 0 0 0 0 0 0 1\n")
    with TumWriter(tmp_path):  # a run that fails before its first pose leaves the earlier tracks
        pass
    assert (tmp_path / "wrist.tum").exists()
    with TumWriter(tmp_path) as w:  # a second run that never poses the wrist
        w.add("shaft", 0.0, np.eye(3), [4.0, 5.0, 6.0])
    assert not (tmp_path / "wrist.tum").exists()
    assert mine.exists()
    assert np.allclose(read_tum(tmp_path / "shaft.tum")[2][0], [4.0, 5.0, 6.0])

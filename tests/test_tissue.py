"""Tissue sources: a user's mesh (units, orientation, ray-cast height field, vertex colours), photographs
as backdrops, the tissue.source config and its errors, and datasets generated from both."""

import json

import cv2
import numpy as np
import pytest
import trimesh

from surftrack.geometry import PinholeCamera, rotation_about, se3
from surftrack.render import Renderer
from surftrack.synth.config import ConfigError, load_synth_config
from surftrack.synth.generate import generate_dataset
from surftrack.synth.tissue import image_backdrop, load_tissue_mesh, read_image

BLUE, YELLOW = (40, 70, 200), (210, 180, 30)


def _grid(w, h, step, f):
    """A height-field grid mesh (faces wound to face -z) and its vertices' colours: blue at x < 0, else yellow."""
    nx, ny = int(round(w / step)) + 1, int(round(h / step)) + 1
    X, Y = np.meshgrid(np.linspace(-w / 2, w / 2, nx), np.linspace(-h / 2, h / 2, ny))
    V = np.stack([X.ravel(), Y.ravel(), f(X, Y).ravel()], -1)
    i = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    F = np.concatenate([np.stack([i, i + nx, i + 1], -1), np.stack([i + 1, i + nx, i + nx + 1], -1)])
    col = np.where(V[:, :1] < 0, [BLUE + (255,)], [YELLOW + (255,)]).astype(np.uint8)
    return V, F, col


def _bumps(X, Y):  # metres: 3 mm bumps, 50 x 60 mm wavelengths
    return 0.003 * np.sin(X * 2 * np.pi / 0.05) * np.cos(Y * 2 * np.pi / 0.06)


def _rot(axis, deg):
    R = np.asarray(rotation_about(axis, np.radians(deg)))
    return R[:3, :3]


@pytest.fixture(scope="module")
def mesh_file(tmp_path_factory):
    """A bumpy 400 x 340 mm surface in metres, tilted by 20 deg and offset, with vertex colours."""
    V, F, col = _grid(0.40, 0.34, 0.004, _bumps)
    V = V @ _rot([1.0, 0.3, 0.0], 20.0).T + [0.1, -0.05, 0.3]
    path = tmp_path_factory.mktemp("mesh") / "tissue.ply"
    trimesh.Trimesh(V, F, vertex_colors=col, process=False).export(path)
    return path, V


def _first_hits_down(mesh, x, y):
    z0 = mesh.vertices[:, 2].min() - 5.0
    o = np.stack([x, y, np.full_like(x, z0)], -1)
    loc, ray, _ = mesh.ray.intersects_location(o, np.tile([0.0, 0.0, 1.0], (len(x), 1)), multiple_hits=True)
    z = np.full(len(x), np.inf)
    np.minimum.at(z, ray, loc[:, 2])
    return z


def test_mesh_in_metres_gets_a_matching_height_field(mesh_file):
    path, V_m = mesh_file
    t = load_tissue_mesh(path, units="m", spacing=0.5)
    # Units and placement: the file's vertices map onto the tissue's by source_to_tissue (a scaled rotation).
    T = t.source_to_tissue
    assert np.allclose(V_m @ T[:3, :3].T + T[:3, 3], t.mesh.vertices, atol=1e-3)  # PLY stores float32
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, 1e6 * np.eye(3))
    assert t.mesh.area == pytest.approx(1e6 * trimesh.Trimesh(V_m, t.mesh.faces).area, rel=1e-6)
    lo, hi = t.mesh.bounds
    assert np.allclose([lo[0] + hi[0], lo[1] + hi[1]], 0.0, atol=1e-6)
    assert np.allclose(t.extent, hi[:2] - lo[:2])
    # Facing the camera (-z).
    assert (t.mesh.face_normals[:, 2] < 0).all()
    # The height field agrees with ray casting the surface itself.
    rng = np.random.default_rng(0)
    w, h = t.extent
    x, y = rng.uniform(-0.45 * w, 0.45 * w, 400), rng.uniform(-0.45 * h, 0.45 * h, 400)
    z = _first_hits_down(t.mesh, x, y)
    ok = np.isfinite(z)
    assert ok.mean() > 0.95
    assert np.abs(t.height_at(x[ok], y[ok]) - z[ok]).max() < 0.05
    assert abs(np.median(t.height)) < 1e-9


@pytest.mark.parametrize("axis, deg", [([1.0, 0.0, 0.0], 180.0), ([1.0, 0.0, 0.0], 90.0), ([0.0, 1.0, 0.0], -80.0)])
def test_flipped_or_vertical_meshes_are_turned_to_face_minus_z(tmp_path, axis, deg):
    V, F, col = _grid(120.0, 80.0, 4.0, lambda X, Y: 1.5 * np.sin(X / 9.0))
    V = V @ _rot(axis, deg).T
    path = tmp_path / "turned.ply"
    trimesh.Trimesh(V, F, vertex_colors=col, process=False).export(path)
    t = load_tissue_mesh(path, spacing=1.0)
    assert (t.mesh.face_normals[:, 2] < 0).mean() > 0.99
    assert np.allclose(sorted(t.extent), [80.0, 120.0], atol=0.5)
    assert np.ptp(t.height) < 4.0  # the 3 mm waves, not a surface on its side


def test_vertex_coloured_mesh_renders_with_its_colours(mesh_file):
    t = load_tissue_mesh(mesh_file[0], units="m", spacing=1.0)
    assert t.texture is None and t.colors is not None
    W, H = 160, 128
    r = Renderer(W, H)
    tid = t.add_to(r)
    cam = PinholeCamera.from_fov(W, H, 60.0)
    res = r.render(cam, {tid: se3(np.eye(3), [0.0, 0.0, 130.0])}, modalities={"rgb", "instance"})
    assert (res.instance == tid).mean() > 0.99
    rgb = res.rgb.astype(float)
    left, right = rgb[:, : W // 2 - 8].reshape(-1, 3).mean(0), rgb[:, W // 2 + 8:].reshape(-1, 3).mean(0)
    assert left[2] > 1.5 * left[0] and left[2] > left[1]       # blue where x < 0
    assert right[0] > 1.5 * right[2] and right[1] > right[2]    # yellow where x > 0


def test_textured_obj_keeps_its_texture(tmp_path):
    V, F, _ = _grid(60.0, 40.0, 5.0, lambda X, Y: 0.0 * X)
    uv = np.stack([(V[:, 0] + 30) / 60, (V[:, 1] + 20) / 40], -1)
    img = np.zeros((16, 16, 3), np.uint8)
    img[..., 1] = 200
    from PIL import Image

    m = trimesh.Trimesh(V, F, process=False)
    m.visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(img))
    m.export(tmp_path / "tex.obj")
    t = load_tissue_mesh(tmp_path / "tex.obj")
    assert t.texture is not None and t.uv.shape == (len(t.mesh.vertices), 2)
    assert t.texture[..., 1].mean() > 100 and t.texture[..., 0].max() == 0


def test_image_backdrop_is_upright_and_curves_gently():
    photo = np.zeros((120, 200, 3), np.uint8)
    photo[:60] = (220, 40, 40)     # top half red
    photo[60:] = (40, 40, 220)     # bottom half blue
    flat = image_backdrop(photo, (200.0, 120.0))
    assert np.allclose(flat.height, 0.0) and flat.extent == (200.0, 120.0)
    bowl = image_backdrop(photo, (200.0, 120.0), bowl_mm=10.0)
    assert bowl.height_at(np.zeros(1), np.zeros(1))[0] == pytest.approx(0.0)
    assert bowl.height_at(np.array([100.0]), np.array([60.0]))[0] == pytest.approx(-10.0)
    W, H = 120, 96
    r = Renderer(W, H)
    tid = flat.add_to(r)
    res = r.render(PinholeCamera.from_fov(W, H, 50.0), {tid: se3(np.eye(3), [0.0, 0.0, 100.0])}, modalities={"rgb"})
    top, bottom = res.rgb[: H // 2 - 4].reshape(-1, 3).mean(0), res.rgb[H // 2 + 4:].reshape(-1, 3).mean(0)
    assert top[0] > 2 * top[2] and bottom[2] > 2 * bottom[0]


def _small(tissue: dict) -> dict:
    return {
        "image": {"width": 160, "height": 128},
        "camera": {"hfov_deg": [55, 65]},
        "tissue": {"images_per_tissue": 1, "spacing_mm": 5.0, "texel_mm": 1.0, "tilt_deg": [0, 15],
                   "distance_mm": [100, 130], **tissue},
        "output": {"images_per_scene": 2, "rgb_format": "png"},
    }


def _check_dataset(root, report, n):
    assert report.made == n and report.failed == 0
    count = 0
    for scene in sorted((root / "train").iterdir()):
        gts = json.loads((scene / "scene_gt.json").read_text())
        for k in gts:
            rgb = cv2.imread(str(scene / "rgb" / f"{int(k):06d}.png"))
            depth = cv2.imread(str(scene / "depth" / f"{int(k):06d}.png"), cv2.IMREAD_UNCHANGED)
            assert rgb.shape == (128, 160, 3) and rgb.std() > 5
            assert (depth > 0).mean() > 0.95 and len(gts[k]) > 0
            count += 1
    assert count == n


def test_dataset_from_a_tissue_mesh(mesh_file, tmp_path):
    cfg = load_synth_config(overrides=_small({"source": "mesh", "mesh": str(mesh_file[0]), "mesh_units": "m"}))
    report = generate_dataset(tmp_path / "ds", cfg, 2, seed=3, workers=1, progress=False)
    _check_dataset(tmp_path / "ds", report, 2)


def test_dataset_from_background_images(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    yy, xx = np.mgrid[0:150, 0:200]
    for k in range(2):
        im = np.stack([60 + 0.5 * xx, 40 + 0.6 * yy + 40 * k, 120 + 0 * xx], -1).clip(0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"frame{k}.png"), im)
    (folder / "notes.txt").write_text("not an image")
    cfg = load_synth_config(overrides=_small({"source": "images", "images": str(folder)}))
    report = generate_dataset(tmp_path / "ds", cfg, 2, seed=1, workers=1, progress=False)
    _check_dataset(tmp_path / "ds", report, 2)


def test_bad_tissue_sources_name_the_file(tmp_path, mesh_file):
    bad = tmp_path / "bad.yaml"
    bad.write_text("tissue: {source: mesh, mesh: missing_tissue.ply}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*missing_tissue\.ply"):
        load_synth_config(bad)
    bad.write_text("tissue: {source: mesh}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*tissue\.mesh"):
        load_synth_config(bad)
    bad.write_text("tissue: {source: photos}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*tissue\.source"):
        load_synth_config(bad)
    (tmp_path / "empty").mkdir()
    bad.write_text("tissue: {source: images, images: empty}\n")  # relative to the config's folder
    with pytest.raises(ConfigError, match=r"bad\.yaml.*empty.*no images"):
        load_synth_config(bad)
    with pytest.raises(ConfigError, match=r"default\.yaml.*nowhere\.obj"):
        load_synth_config(overrides={"tissue": {"source": "mesh", "mesh": str(tmp_path / "nowhere.obj")}})
    # A path relative to the config file's folder is found.
    (tmp_path / "t.ply").write_bytes(mesh_file[0].read_bytes())
    bad.write_text("tissue: {source: mesh, mesh: t.ply, mesh_units: m}\n")
    assert load_synth_config(bad).tissue.mesh == str(tmp_path / "t.ply")
    # Files that are not tissue surfaces.
    (tmp_path / "junk.ply").write_text("not a mesh\n")
    trimesh.PointCloud(np.random.default_rng(0).random((30, 3))).export(tmp_path / "cloud.ply")
    trimesh.creation.icosphere().export(tmp_path / "ball.ply")
    for name, why in [("junk.ply", "cannot read"), ("cloud.ply", "no triangles"), ("ball.ply", "not a surface"),
                      ("absent.ply", "tissue mesh file not found")]:
        with pytest.raises(ValueError, match=rf"{name}: {why}"):
            load_tissue_mesh(tmp_path / name)
    with pytest.raises(ValueError, match="junk.ply: cannot read the image"):
        read_image(tmp_path / "junk.ply")


def test_a_bad_tissue_file_stops_synthesis_before_its_first_image(tmp_path):
    from surftrack.synth.generate import generate_dataset

    (tmp_path / "junk.ply").write_text("not a mesh\n")
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"not a jpeg")
    for tissue, name in (({"source": "mesh", "mesh": str(tmp_path / "junk.ply")}, "junk.ply"),
                         ({"source": "images", "images": str(tmp_path / "photos")}, "a.jpg")):
        cfg = load_synth_config(overrides=_small(tissue))
        with pytest.raises(ConfigError, match=rf"tissue: .*{name}"):
            generate_dataset(tmp_path / "out", cfg, 2, seed=0, workers=1, progress=False)
        assert not list((tmp_path / "out").rglob("*.png")) and not list((tmp_path / "out").rglob("*.jpg"))

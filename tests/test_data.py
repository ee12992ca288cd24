"""Training data: BOP loading and its errors, SurgRIPE import, crop geometry, rendered targets,
augmentation, the crop dataset and syn:real mixing."""

import json
import os
import pickle
import shutil

import cv2
import numpy as np
import pytest
import torch

from surftrack.data import (
    AugmentConfig,
    BopDataset,
    CropDataset,
    DatasetError,
    MixedSampler,
    TargetRenderer,
    augment,
    crop_box,
    denormalise_image,
    import_surgripe,
    mixed_dataset,
    mixed_indices,
)
from surftrack.data.join import join_datasets
from surftrack.geometry import (
    PinholeCamera,
    box_from_bop,
    crop_with_rotation,
    pose_in_crop,
    rotation_about,
    se3,
    transform_points,
    warp_image,
    xyxy_from_xywh,
)
from surftrack.render import Renderer, worker_context
from surftrack.synth.bop_writer import bbox_xywh
from surftrack.synth.config import load_synth_config
from surftrack.synth.generate import generate_dataset

W, H, N = 320, 256, 4
SMALL = {"image": {"width": W, "height": H},
         "tissue": {"images_per_tissue": 2, "spacing_mm": 4.0, "texel_mm": 1.0},
         "output": {"images_per_scene": 4, "rgb_format": "png"}}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    out = tmp_path_factory.mktemp("bop")
    # the paper's ranges: the crop checks below were written for them (a tool mostly inside its crop)
    report = generate_dataset(out, load_synth_config("paper", overrides=SMALL), N, seed=3, workers=1, progress=False)
    assert report.made == N
    return out


@pytest.fixture(scope="module")
def bop(root):
    return BopDataset(root, "train", min_visib_fract=0.1, min_px_visib=64)


def copy_dataset(root, dst):
    shutil.copytree(root, dst, ignore=shutil.ignore_patterns("depth", "normal", "mask", "records", "*.png.tmp"))
    return dst


# ---------------------------------------------------------------------- BOP loading
def test_instances_match_scene_gt_after_filtering(root, bop):
    expected = []
    for scene in sorted((root / "train").iterdir()):
        gts = json.loads((scene / "scene_gt.json").read_text())
        infos = json.loads((scene / "scene_gt_info.json").read_text())
        for im in sorted(gts, key=int):
            for k, (gt, info) in enumerate(zip(gts[im], infos[im])):
                if info["visib_fract"] >= 0.1 and info["px_count_visib"] >= 64:
                    expected.append((int(scene.name), int(im), k, gt["obj_id"]))
    got = [(i.scene_id, i.im_id, i.gt_index, i.obj_id) for i in bop.instances]
    total = sum(len(v) for scene in (root / "train").iterdir()
                for v in json.loads((scene / "scene_gt.json").read_text()).values())
    assert got == expected and 0 < len(got) <= total
    assert bop.filter_counts[0][1] == total
    assert sorted(bop.models) == [1, 2, 3, 4]
    inst = bop.instances[0]
    gt = json.loads((root / "train" / f"{inst.scene_id:06d}" / "scene_gt.json").read_text())[str(inst.im_id)][inst.gt_index]
    assert np.allclose(inst.R.ravel(), gt["cam_R_m2c"]) and np.allclose(inst.t, gt["cam_t_m2c"])
    assert inst.extra["instrument"] == "large_needle_driver" and "joints_deg" in inst.extra and "part" in inst.extra
    assert bop.image_path(inst.scene_id, inst.im_id).suffix == ".png"
    rgb = bop.load_rgb(inst.scene_id, inst.im_id)
    m = bop.load_mask_visib(inst.scene_id, inst.im_id, inst.gt_index)
    assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8 and m.shape == (H, W) and m.dtype == bool
    assert m.sum() == inst.px_count_visib and tuple(bbox_xywh(m)) == inst.bbox_visib
    assert bop.load_depth(inst.scene_id, inst.im_id).shape == (H, W)
    # obj id filter
    only = BopDataset(root, obj_ids=[1])
    assert [i.obj_id for i in only.instances] == [1] * sum(1 for e in expected if e[3] == 1)


def _break(kind, d):
    scene = d / "train" / "000000"
    if kind == "root":
        shutil.rmtree(d)
        return str(d), {}
    if kind == "models_dir":
        shutil.rmtree(d / "models")
        return "models", {}
    if kind == "models_info":
        (d / "models" / "models_info.json").unlink()
        return "models_info.json", {}
    if kind == "no_models":
        for p in (d / "models").iterdir():
            p.unlink()
        return "no models", {}
    if kind == "no_scenes":
        shutil.rmtree(d / "train")
        (d / "train").mkdir()
        return "no scene folders", {}
    if kind == "scene_gt":
        (scene / "scene_gt.json").unlink()
        return "000000/scene_gt.json", {}
    if kind == "image":
        (scene / "rgb" / "000002.png").unlink()
        return "rgb/000002", {}
    if kind == "json":
        (scene / "scene_camera.json").write_text('{"0": {"cam_K": [1, 2,')
        return "scene_camera.json: malformed JSON", {}
    if kind == "ply":
        ply = next((d / "models").glob("obj_*.ply"))
        ply.write_bytes(ply.read_bytes()[:200])  # cut off mid-write
        return f"{ply.name}: cannot read the model", {}
    if kind == "visib_null":
        infos = json.loads((scene / "scene_gt_info.json").read_text())
        infos["0"][0]["visib_fract"] = None
        (scene / "scene_gt_info.json").write_text(json.dumps(infos))
        return "image 0 entry 0: bad value", {}
    if kind == "image_key":
        gts = json.loads((scene / "scene_gt.json").read_text())
        gts["first"] = gts.pop("0")
        (scene / "scene_gt.json").write_text(json.dumps(gts))
        return "image keys must be image numbers", {}
    if kind == "filter_visib":
        return "removed by min_visib_fract=1.5", {"min_visib_fract": 1.5}
    if kind == "filter_px":
        return "removed by min_px_visib=1000000", {"min_px_visib": 10**6}
    if kind == "obj_ids":
        return "obj_ids [9] have no model", {"obj_ids": [9]}
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["root", "models_dir", "models_info", "no_models", "no_scenes", "scene_gt", "image",
                                  "json", "ply", "visib_null", "image_key", "filter_visib", "filter_px", "obj_ids"])
def test_broken_dataset_fails_with_one_clear_message(root, tmp_path, kind):
    d = copy_dataset(root, tmp_path / "ds")
    needle, kwargs = _break(kind, d)
    with pytest.raises(DatasetError) as e:
        BopDataset(d, "train", **kwargs)
    assert needle in str(e.value), str(e.value)


def test_flat_zero_based_model_layout_loads(root, bop, tmp_path):
    d = copy_dataset(root, tmp_path / "flat")
    models = d / "models"
    for p in sorted(models.glob("obj_*.ply")):
        p.rename(models / f"{int(p.stem[4:]) - 1:06d}.ply")
    (models / "models_info.json").unlink()
    flat = BopDataset(d)
    assert sorted(flat.models) == sorted(bop.models)
    for oid, part in bop.models.items():
        assert np.allclose(flat.models[oid].mesh.vertices, part.mesh.vertices)
    assert [(i.scene_id, i.im_id, i.gt_index) for i in flat.instances] == \
           [(i.scene_id, i.im_id, i.gt_index) for i in bop.instances]
    (models / "000001.ply").unlink()  # a hole in the numbering
    with pytest.raises(DatasetError, match="000001.ply"):
        BopDataset(d)


# ---------------------------------------------------------------------- SurgRIPE import
def _fake_surgripe(src, part_mesh, K, n=3, with_masks=True):
    """Frames of noise with the object at known poses; masks are the rendered silhouette with a
    rectangle cut out (an occluder)."""
    (src / "image").mkdir(parents=True)
    (src / "pose").mkdir()
    if with_masks:
        (src / "mask").mkdir()
    r = Renderer(W, H)
    iid = r.add_mesh(part_mesh)
    cam = PinholeCamera(K, W, H)
    rng = np.random.default_rng(0)
    poses = {}
    for k in range(n):
        stem = f"frame_{k * 7:04d}"
        T = se3(rotation_about(rng.normal(size=3), rng.uniform(0, np.pi)), [rng.uniform(-5, 5), rng.uniform(-5, 5), 70.0])
        np.save(src / "pose" / f"{stem}.npy", T[:3])
        cv2.imwrite(str(src / "image" / f"{stem}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        if with_masks:
            m = r.render(cam, {iid: T}, modalities={"instance"}).instance == iid
            ys, xs = np.nonzero(m)
            m[: int(np.median(ys))] = False  # the upper half is occluded
            cv2.imwrite(str(src / "mask" / f"{stem}.png"), m.astype(np.uint8) * 255)
        poses[stem] = T
    r.release()
    return poses


def test_surgripe_folder_imports_as_bop(bop, tmp_path):
    part = bop.models[1]
    mesh_path = tmp_path / "lnd_shaft.stl"
    part.mesh.export(mesh_path)
    K = np.array([[300.0, 0, 158.3], [0, 298.0, 129.1], [0, 0, 1]])
    src = tmp_path / "surgripe"
    poses = _fake_surgripe(src, part.mesh, K)
    n = import_surgripe(src, tmp_path / "out", "lnd_shaft", mesh_path, K, split="test")
    assert n == 3
    ds = BopDataset(tmp_path / "out", "test", min_visib_fract=0.0, min_px_visib=1)
    assert len(ds) == 3 and list(ds.models) == [1]
    info = json.loads((tmp_path / "out" / "models" / "models_info.json").read_text())["1"]
    assert info["diameter_bbox_diagonal"] == pytest.approx(np.linalg.norm(part.mesh.extents), rel=1e-6)
    assert info["diameter"] == pytest.approx(part.diameter_max_pairwise, rel=1e-6)
    for inst, (stem, T) in zip(ds.instances, sorted(poses.items())):
        assert inst.extra["source_stem"] == stem
        assert np.allclose(inst.pose, T) and np.allclose(inst.K, K)
        given = cv2.imread(str(src / "mask" / f"{stem}.png"), cv2.IMREAD_GRAYSCALE) > 0
        assert np.array_equal(ds.load_mask_visib(inst.scene_id, inst.im_id, 0), given)
        assert inst.bbox_visib == tuple(bbox_xywh(given)) and 0.2 < inst.visib_fract < 0.8
        assert np.array_equal(ds.load_rgb(inst.scene_id, inst.im_id),
                              cv2.imread(str(src / "image" / f"{stem}.png"))[..., ::-1])
    # the imported data feeds the crop dataset: rendered targets agree with the given masks
    item = CropDataset(ds, crop_size=64)[0]
    modal, valid = item["mask_modal"].bool(), item["coord_valid"]
    assert modal.sum() > 50 and (modal & ~valid).sum() <= 0.03 * modal.sum()
    # without masks the object counts as fully visible; a missing pose is named
    src2 = tmp_path / "surgripe2"
    _fake_surgripe(src2, part.mesh, K, n=2, with_masks=False)
    import_surgripe(src2, tmp_path / "out2", "lnd_shaft", mesh_path, K)
    ds2 = BopDataset(tmp_path / "out2", "test", min_visib_fract=0.0, min_px_visib=1)
    for i in ds2.instances:  # unoccluded: visible = the silhouette within the image
        full = cv2.imread(str(ds2.scene_dir(i.scene_id) / "mask" / f"{i.im_id:06d}_000000.png"), cv2.IMREAD_GRAYSCALE) > 0
        assert np.array_equal(ds2.load_mask_visib(i.scene_id, i.im_id, 0), full) and i.visib_fract > 0.3
        assert i.visib_fract == 1.0 or i.bbox_obj[0] < 0 or i.bbox_obj[1] < 0 or \
            i.bbox_obj[0] + i.bbox_obj[2] >= W or i.bbox_obj[1] + i.bbox_obj[3] >= H
    next((src2 / "pose").iterdir()).unlink()
    with pytest.raises(DatasetError, match=r"\.npy: pose for image"):
        import_surgripe(src2, tmp_path / "out3", "lnd_shaft", mesh_path, K)


# ---------------------------------------------------------------------- crop geometry
def test_bop_box_edges_and_crop_box_cover_the_mask_pixels_exactly():
    mask = np.zeros((60, 80), bool)
    mask[30:40, 10:20] = True  # pixels 10..19 x 30..39
    bb = bbox_xywh(mask)
    assert bb == [10, 30, 9, 9] and xyxy_from_xywh(box_from_bop(bb)) == (10, 30, 20, 40)
    assert crop_box(bb, scale=1.0) == (10, 30, 20, 40)
    cam = PinholeCamera(np.array([[50.0, 0, 39.5], [0, 50.0, 29.5], [0, 0, 1]]), 80, 60)
    M, _, _ = crop_with_rotation(cam, crop_box(bb, scale=1.0), 10)
    assert warp_image(mask, M, 10, nearest=True).all()
    M, _, _ = crop_with_rotation(cam, crop_box(bb, scale=2.0), 20)
    expect = np.zeros((20, 20), bool)
    expect[5:15, 5:15] = True
    assert np.array_equal(warp_image(mask, M, 20, nearest=True), expect)
    # a rectangular box becomes a square with the same centre; jitter moves it within bounds
    x0, y0, x1, y1 = crop_box([10, 20, 29, 9], scale=1.5)
    assert (x1 - x0, y1 - y0) == (45, 45) and ((x0 + x1) / 2, (y0 + y1) / 2) == (25, 25)
    rng = np.random.default_rng(0)
    for _ in range(20):
        x0, y0, x1, y1 = crop_box([10, 20, 29, 9], scale=1.5, jitter=0.1, rng=rng)
        assert abs(x1 - x0 - 45) <= 4.5 + 1e-9 and abs((x0 + x1) / 2 - 25) <= 4.5 + 1e-9
    with pytest.raises(ValueError):
        crop_box([-1, -1, -1, -1])


@pytest.mark.parametrize("fy", [600.0, 640.0])
@pytest.mark.parametrize("angle_deg", [0.0, 17.0, -120.0])
def test_rotated_crop_camera_reprojects_like_the_warp(fy, angle_deg):
    cam = PinholeCamera(np.array([[600.0, 0, 330.2], [0, fy, 251.7], [0, 0, 1]]), 640, 512)
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-20, 20, 200), rng.uniform(-20, 20, 200), rng.uniform(40, 90, 200)])
    box = (250.3, 180.1, 410.9, 340.7)
    M, crop_cam, R_crop = crop_with_rotation(cam, box, 224, np.radians(angle_deg))
    assert np.allclose(R_crop @ R_crop.T, np.eye(3)) and np.isclose(np.linalg.det(R_crop), 1.0)
    assert np.allclose(R_crop[2], [0, 0, 1])  # a rotation about the optical axis
    warped = cam.project(X) @ M[:, :2].T + M[:, 2]
    assert np.abs(crop_cam.project(X @ R_crop.T) - warped).max() < 1e-9
    # the crop centre stays the box centre; square pixels give an ordinary K and R_crop by the angle
    c = np.array([(box[0] + box[2]) / 2 - 0.5, (box[1] + box[3]) / 2 - 0.5])
    assert np.allclose(M[:, :2] @ c + M[:, 2], [111.5, 111.5])
    if fy == 600.0:
        assert abs(crop_cam.K[0, 1]) < 1e-9
        assert np.isclose(np.degrees(np.arctan2(R_crop[1, 0], R_crop[0, 0])), angle_deg)
    # poses: projecting model points with the crop pose equals the warp of their projection
    T = se3(rotation_about([1, 2, 3], 0.7), [3.0, -2.0, 60.0])
    P = rng.normal(size=(50, 3)) * 5
    proj = crop_cam.project(transform_points(pose_in_crop(R_crop, T), P))
    assert np.abs(proj - (cam.project(transform_points(T, P)) @ M[:, :2].T + M[:, 2])).max() < 1e-9


# ---------------------------------------------------------------------- targets through the dataset
def dilate(mask, r):
    m = mask.numpy() if isinstance(mask, torch.Tensor) else mask
    out = cv2.dilate(m.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
    return torch.from_numpy(out) if isinstance(mask, torch.Tensor) else out


@pytest.fixture(scope="module")
def crops(bop):
    ds = CropDataset(bop, crop_size=96, jitter=0.1, max_rotation_deg=45.0, seed=2)
    return ds, [ds[i] for i in range(len(ds))]


def test_coord_map_reprojects_onto_its_own_pixels(bop, crops):
    ds, items = crops
    worst = 0.0
    for item in items:
        part = bop.models[int(item["obj_id"])]
        valid = item["coord_valid"].numpy()
        K, R, t = (item[k].double().numpy() for k in ("K", "R", "t"))
        cam = PinholeCamera(K, 96, 96)
        vs, us = np.nonzero(valid)
        pts = part.denormalise(item["coord_norm"].numpy()[valid])
        uv = cam.project(pts @ R.T + t)
        worst = max(worst, np.abs(uv - np.column_stack([us, vs])).max())
        # model surface points projected with the crop K and pose land on coord_valid pixels
        samples, _ = part.sample_surface(3000, seed=1)
        uv = np.round(cam.project(samples @ R.T + t)).astype(int)
        inside = (uv >= 0).all(1) & (uv < 96).all(1)
        hit = valid[uv[inside, 1], uv[inside, 0]]
        near = dilate(valid, 1)[uv[inside, 1], uv[inside, 0]]
        assert inside.sum() > 1000 and hit.mean() > 0.85 and near.all()  # misses only by rounding at the outline
    assert worst < 0.5, worst


def test_amodal_coords_cover_the_amodal_mask_and_the_visible_mask(crops):
    ds, items = crops
    for item in items:
        amodal, valid, modal = item["mask_amodal"].bool(), item["coord_valid"], item["mask_modal"].bool()
        assert torch.equal(amodal, valid) and valid.sum() > 20
        c = item["coord_norm"]
        assert (c[valid].norm(dim=-1) > 1e-6).all() and (c[valid].norm(dim=-1) <= 1.0 + 1e-4).all()
        assert (c[~valid] == 0).all()
        # the dataset's visible mask, warped into the (rotated, upsampled) crop, lies inside the rendered
        # silhouette up to the blockiness of nearest-neighbour upsampling at the outline
        up = 96 / float(item["bbox"][2] - item["bbox"][0])
        assert not (modal & ~dilate(valid, int(np.ceil(up / 2)) + 1)).any()
        assert (modal & ~valid).sum() <= 0.1 * modal.sum()
        assert torch.equal(item["mask_train"], item["mask_amodal"])  # default mask_mode = amodal


def test_unscaled_crop_targets_equal_the_datasets_full_silhouette(bop):
    """A crop at scale 1 with integer edges is a pure shift: the rendered crop silhouette must equal the
    dataset's ``mask/`` (the full silhouette rendered by the generator) pixel for pixel."""
    tr = TargetRenderer(bop.models, 64)
    for inst in bop.instances:
        x, y, w, h = inst.bbox_visib
        box = (x - 10, y - 10, x + 54, y + 54)
        M, cam, R_crop = crop_with_rotation(inst.camera(W, H), box, 64)
        assert np.array_equal(R_crop, np.eye(3)) and np.allclose(M, [[1, 0, -x + 10], [0, 1, -y + 10]])
        full = cv2.imread(str(bop.scene_dir(inst.scene_id) / "mask" / f"{inst.im_id:06d}_{inst.gt_index:06d}.png"), 0) > 0
        expect = warp_image(full, M, 64, nearest=True)
        got = tr.render(inst.obj_id, cam, inst.pose).valid
        inside = np.zeros_like(got)  # compare only where the crop lies inside the image
        inside[max(0, 10 - y):64 - max(0, y + 54 - H), max(0, 10 - x):64 - max(0, x + 54 - W)] = True
        assert (got != expect)[inside].sum() <= 2, (inst.scene_id, inst.im_id, inst.gt_index)
    tr.release()


def test_target_renderer_is_picklable_and_renders_lazily(bop):
    tr = TargetRenderer(bop.models, 32)
    tr2 = pickle.loads(pickle.dumps(tr))
    assert tr2._renderer is None
    inst = bop.instances[0]
    box = crop_box(inst.bbox_visib)
    _, cam, _ = crop_with_rotation(inst.camera(W, H), box, 32)
    tg = tr2.render(inst.obj_id, cam, inst.pose)
    assert tg.valid.any() and tg.xyz.dtype == np.float32
    assert pickle.loads(pickle.dumps(tr2))._renderer is None
    # non-square pixels and a rotated crop: the crop K has a skew, which the renderer must honour
    K = inst.K.copy()
    K[1, 1] *= 1.15
    M, cam, R_crop = crop_with_rotation(PinholeCamera(K, W, H), crop_box(inst.bbox_visib), 32, np.radians(35))
    assert abs(cam.K[0, 1]) > 1e-3
    tg = tr2.render(inst.obj_id, cam, pose_in_crop(R_crop, inst.pose))
    vs, us = np.nonzero(tg.valid)
    uv = cam.project(transform_points(pose_in_crop(R_crop, inst.pose), tg.xyz[tg.valid].astype(np.float64)))
    assert len(us) > 20 and np.abs(uv - np.column_stack([us, vs])).max() < 0.05
    tr2.release()


# ---------------------------------------------------------------------- augmentation
def test_augmentations_keep_shapes_and_occluders_shrink_the_modal_mask():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
    mask = np.zeros((64, 64), bool)
    mask[16:48, 16:48] = True
    cfg = AugmentConfig.from_dict({"p_color": 1, "p_blur": 1, "p_noise": 1, "p_dropout": 1, "p_specular": 1,
                                   "p_occluder": 0})
    out, m = augment(img, mask, cfg, rng)
    assert out.shape == img.shape and out.dtype == np.uint8 and np.array_equal(m, mask)
    assert not np.array_equal(out, img)
    occ_cfg = AugmentConfig.from_dict({**AugmentConfig.none().to_dict(), "p_occluder": 1.0})
    shrunk = 0
    for k in range(10):
        out, m = augment(img, mask, occ_cfg, np.random.default_rng(k))
        assert m.dtype == bool and not (m & ~mask).any()
        changed = (out != img).any(-1)
        assert not (m & changed).any()  # painted pixels are gone from the mask
        shrunk += m.sum() < mask.sum()
    assert shrunk >= 7
    out, m = augment(img, mask, AugmentConfig.none(), rng)
    assert np.array_equal(out, img) and np.array_equal(m, mask)
    with pytest.raises(ValueError, match="unknown augment keys"):
        AugmentConfig.from_dict({"p_colour": 1})
    with pytest.raises(ValueError, match="probability"):
        AugmentConfig(p_blur=2.0)


# ---------------------------------------------------------------------- crop dataset
def test_crop_dataset_items_shapes_dtypes_and_determinism(bop):
    aug = {"p_occluder": 1.0, "p_specular": 0.5}
    ds = CropDataset(bop, crop_size=64, jitter=0.1, max_rotation_deg=30, augment=aug, seed=7)
    item = ds[1]
    S = 64
    shapes = {"image": ((3, S, S), torch.float32), "mask_modal": ((S, S), torch.float32),
              "mask_amodal": ((S, S), torch.float32), "mask_train": ((S, S), torch.float32),
              "coord_norm": ((S, S, 3), torch.float32), "coord_valid": ((S, S), torch.bool),
              "part_index": ((), torch.int64), "obj_id": ((), torch.int64), "K": ((3, 3), torch.float32),
              "R": ((3, 3), torch.float32), "t": ((3,), torch.float32), "bbox": ((4,), torch.float32)}
    for k, (shape, dtype) in shapes.items():
        assert tuple(item[k].shape) == shape and item[k].dtype == dtype, k
    assert int(item["part_index"]) == ds.obj_ids.index(int(item["obj_id"]))
    assert abs(float(item["image"].mean())) < 3  # normalised
    again = ds[1]
    assert all(torch.equal(item[k], again[k]) for k in item)
    ds.set_epoch(1)
    other = ds[1]
    assert not torch.equal(item["image"], other["image"])
    ds.set_epoch(0)
    assert torch.equal(ds[1]["image"], item["image"])
    copy = pickle.loads(pickle.dumps(ds))
    assert copy.targets._renderer is None and torch.equal(copy[1]["coord_norm"], item["coord_norm"])
    assert len(denormalise_image(item["image"]).shape) == 3
    modal = CropDataset(bop, crop_size=64, mask_mode="modal", obj_ids=[2, 1])
    it = modal[0]
    assert torch.equal(it["mask_train"], it["mask_modal"]) and all(int(modal[i]["obj_id"]) in (1, 2) for i in range(len(modal)))
    assert int(it["part_index"]) == [2, 1].index(int(it["obj_id"]))
    with pytest.raises(ValueError, match="mask_mode"):
        CropDataset(bop, mask_mode="visible")


def test_dataloader_workers_render(bop):
    ds = CropDataset(bop, crop_size=32)
    ds[0]  # this process now holds a GL context; workers from worker_context() must still render
    loader = torch.utils.data.DataLoader(torch.utils.data.Subset(ds, [0, 1]), batch_size=2, num_workers=1,
                                         multiprocessing_context=worker_context())
    batch = next(iter(loader))
    assert batch["coord_norm"].shape == (2, 32, 32, 3)
    assert torch.equal(batch["coord_norm"][0], ds[0]["coord_norm"])


# ---------------------------------------------------------------------- mixing
@pytest.mark.parametrize("ratio,bs", [((1, 1), 20), ((1, 3), 8), ((2, 1), 6)])
def test_mixed_sampler_hits_the_ratio_in_every_batch(ratio, bs):
    la, lb = 37, 11
    sampler = MixedSampler(la, lb, bs, ratio, num_samples=bs * 30, seed=1)
    idx = list(sampler)
    assert len(idx) == len(sampler) == bs * 30
    want_a = round(bs * ratio[0] / sum(ratio))
    for b in range(0, len(idx), bs):
        batch = np.array(idx[b:b + bs])
        assert (batch < la).sum() == want_a
    a = [i for i in idx if i < la]
    assert set(a) == set(range(la)) and set(i for i in idx if i >= la) == set(range(la, la + lb))
    for draws, n in ((a, la), ([i - la for i in idx if i >= la], lb)):  # walked in permutations: even use
        counts = np.bincount(draws, minlength=n)
        assert counts.max() - counts.min() <= 1
    assert list(MixedSampler(la, lb, bs, ratio, num_samples=bs * 30, seed=1)) == idx
    sampler.set_epoch(1)
    assert list(sampler) != idx
    concat = mixed_dataset(list(range(la)), [100 + k for k in range(lb)])
    assert [concat[i] for i in (0, la - 1, la, la + lb - 1)] == [0, la - 1, 100, 100 + lb - 1]
    raw = mixed_indices(la, lb, 10, ratio, np.random.default_rng(0))
    assert len(raw) == 10 and raw.max() < la + lb
    with pytest.raises(ValueError, match="empty"):
        mixed_indices(0, 5, 10)


def test_join_links_the_scenes_of_several_datasets(root, tmp_path):
    """`surftrack join`: the joined folder reads as one dataset with every source's images; sources with
    other models, and an existing folder joining something else, are refused naming the folder."""
    from surftrack.cli import main

    other = copy_dataset(root, tmp_path / "other")
    n_one = len(BopDataset(root, "train", min_visib_fract=0.1).instances)
    assert main(["join", "--out", str(tmp_path / "both"), str(root), str(other)]) == 0
    joined = BopDataset(tmp_path / "both", "train", min_visib_fract=0.1)
    assert len(joined.instances) == 2 * n_one
    links = [tmp_path / "both" / "models", *(tmp_path / "both" / "train").iterdir()]
    assert links and all(p.is_symlink() and not os.path.isabs(os.readlink(p)) for p in links)  # the tree can move
    card = json.loads((tmp_path / "both" / "dataset_card.json").read_text())
    assert card["objects"] == json.loads((root / "dataset_card.json").read_text())["objects"]
    assert main(["join", "--out", str(tmp_path / "both"), str(root), str(other)]) == 0  # the same join again
    with pytest.raises(DatasetError, match="does not join exactly these"):
        join_datasets(tmp_path / "both", [root])
    # a card of an earlier version (no mesh hashes, other extra fields) joins; one naming other parts does not
    card_path = other / "dataset_card.json"
    old_card = json.loads(card_path.read_text())
    for rec in old_card["objects"].values():
        del rec["mesh_sha256"]
        rec["extra"] = 1
    card_path.write_text(json.dumps(old_card))
    assert join_datasets(tmp_path / "older", [root, other]) == 2 * len(list((root / "train").iterdir()))
    renamed = json.loads(card_path.read_text())
    next(iter(renamed["objects"].values()))["part"] = "elsewhere"
    card_path.write_text(json.dumps(renamed))
    with pytest.raises(DatasetError, match="other: its models differ"):
        join_datasets(tmp_path / "renamed", [root, other])
    card_path.write_text(json.dumps(old_card))
    ply = next((other / "models").glob("*.ply"))
    ply.write_bytes(ply.read_bytes() + b"\n")
    with pytest.raises(DatasetError, match="other: its models differ"):
        join_datasets(tmp_path / "again", [root, other])
    assert not (tmp_path / "again").exists()


def test_twin_labels_make_the_targets_a_function_of_the_image(root, bop):
    """The same images annotated as the LND's roll twin (half a turn about the shaft, the jaws exchanged:
    the same pixels) are labelled back as the twin whose shaft x axis points away from the camera: with
    twin labels the crops carry the same obj ids, poses and targets as the original annotation (the
    paper's ranges lie there), and exactly one of the two twins counts as turned."""
    import copy
    import dataclasses

    from surftrack.data.twin_labels import twin_labels
    from surftrack.instruments import HALF_TURN

    objects = json.loads((root / "dataset_card.json").read_text())["objects"]
    twins = twin_labels({int(o): (v["instrument"], v["part"]) for o, v in objects.items()})
    names = {int(o): v["part"] for o, v in objects.items()}
    ids = {v: k for k, v in names.items()}
    assert twins.partner == {ids["shaft"]: ids["shaft"], ids["wrist"]: ids["wrist"],
                             ids["jaw_left"]: ids["jaw_right"], ids["jaw_right"]: ids["jaw_left"]}
    assert twins.axis_parts == {ids["shaft"], ids["wrist"]}
    turned = copy.copy(bop)
    turned.instances = [dataclasses.replace(i, obj_id=twins.partner[i.obj_id], R=i.R @ HALF_TURN)
                        for i in bop.instances]
    plain, back = twins.flips(bop.instances), twins.flips(turned.instances)
    assert not any(plain) and all(back)  # the paper's ranges: roll within +-30 deg of that zero; the twin +-180
    original = CropDataset(bop, crop_size=64, seed=1)
    relabelled = CropDataset(turned, crop_size=64, seed=1, twins=twins)
    as_given = CropDataset(turned, crop_size=64, seed=1)
    jaws = 0
    for k in range(len(original)):
        a, b, c = original[k], relabelled[k], as_given[k]
        assert int(a["obj_id"]) == int(b["obj_id"]) and torch.allclose(a["R"], b["R"], atol=1e-6)
        assert torch.allclose(a["coord_norm"], b["coord_norm"], atol=1e-5)
        assert torch.equal(a["mask_amodal"], b["mask_amodal"]) and torch.equal(a["mask_modal"], b["mask_modal"])
        if names[int(a["obj_id"])].startswith("jaw"):
            jaws += 1
            assert int(c["obj_id"]) != int(a["obj_id"])  # as given, the other jaw's label on these pixels
    assert jaws > 0
    from surftrack.model.config import TrainConfig
    from surftrack.model.train import training_crops

    made = training_crops(TrainConfig.from_dict({"data": {"crop": 64}}), bop, sorted(bop.models), 0)
    assert made.twins == twins  # by default; the objects read from the dataset card
    off = TrainConfig.from_dict({"data": {"crop": 64, "canonical_twin": False}})
    assert training_crops(off, bop, sorted(bop.models), 0).twins is None

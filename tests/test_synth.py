"""Generated BOP data, each property checked independently of the generator."""

import hashlib
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from surftrack.geometry import PinholeCamera
from surftrack.instruments import JOINT_NAMES, load_bop_models, load_instrument
from surftrack.render import Renderer
from surftrack.synth.bop_writer import decode_normals
from surftrack.synth.config import ConfigError, load_synth_config
from surftrack.synth.generate import generate_dataset
from surftrack.synth.sampling import sample_joints

W, H, N = 320, 256, 8
SMALL = {
    "image": {"width": W, "height": H},
    "instruments": ["large_needle_driver", "scissors"],
    "two_instruments_prob": 0.6,
    "tissue": {"images_per_tissue": 4, "spacing_mm": 4.0, "texel_mm": 1.0},
    "output": {"images_per_scene": 4, "rgb_format": "png"},
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    cfg = load_synth_config(overrides=SMALL)
    report = generate_dataset(root, cfg, N, seed=5, workers=1, progress=False)
    return root, cfg, report


def images(root):
    for scene in sorted((root / "train").iterdir()):
        cams = json.loads((scene / "scene_camera.json").read_text())
        gts = json.loads((scene / "scene_gt.json").read_text())
        infos = json.loads((scene / "scene_gt_info.json").read_text())
        for k in sorted(gts, key=int):
            yield scene, int(k), cams[k], gts[k], infos[k]


def test_layout_names_and_units_follow_bop(dataset):
    root, cfg, report = dataset
    assert report.made == N and report.failed == 0
    scenes = sorted(p.name for p in (root / "train").iterdir())
    assert scenes == ["000000", "000001"]
    info = json.loads((root / "models" / "models_info.json").read_text())
    for key in ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"):
        assert all(key in v for v in info.values())
    assert all((root / "models" / f"obj_{int(k):06d}.ply").is_file() for k in info)
    count = 0
    for scene, im, cam, gts, infos in images(root):
        count += 1
        assert len(cam["cam_K"]) == 9 and cam["depth_scale"] == 0.1
        assert (scene / "rgb" / f"{im:06d}.png").is_file()
        depth = cv2.imread(str(scene / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == (H, W)
        assert len(gts) == len(infos) > 0
        for k, (gt, gi) in enumerate(zip(gts, infos)):
            assert set(gt) >= {"obj_id", "cam_R_m2c", "cam_t_m2c", "instrument", "part", "joints_deg"}
            assert len(gt["cam_R_m2c"]) == 9 and len(gt["cam_t_m2c"]) == 3
            assert 20 < np.linalg.norm(gt["cam_t_m2c"]) < 400  # millimetres, not metres
            assert set(gi) >= {"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract"}
            for sub in ("mask", "mask_visib"):
                m = cv2.imread(str(scene / sub / f"{im:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
                assert m.shape == (H, W) and set(np.unique(m)) <= {0, 255}
    assert count == N
    card = json.loads((root / "dataset_card.json").read_text())
    assert card["images"] == N and card["acceptance"]["accepted"] == N
    assert (root / "contact_sheet.png").is_file()


def test_rerendered_masks_and_depth_match(dataset):
    """Re-render every GT part from the exported BOP models at its GT pose with a fresh renderer: the full
    silhouette must match ``mask``; where the re-rendered depth agrees with the stored depth (within
    0.08 mm: the png stores 0.1 mm steps) the part is visible, and that set must match ``mask_visib`` (IoU >= 0.99)."""
    root, cfg, _ = dataset
    models = load_bop_models(root / "models")
    r = Renderer(W, H)
    ids = {oid: r.add_mesh(p.mesh) for oid, p in models.items()}
    checked = 0
    for scene, im, cam, gts, infos in images(root):
        camera = PinholeCamera(np.array(cam["cam_K"]).reshape(3, 3), W, H)
        depth = cv2.imread(str(scene / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED) * cam["depth_scale"]
        for k, (gt, gi) in enumerate(zip(gts, infos)):
            T = np.eye(4)
            T[:3, :3] = np.array(gt["cam_R_m2c"]).reshape(3, 3)
            T[:3, 3] = gt["cam_t_m2c"]
            res = r.render(camera, {ids[gt["obj_id"]]: T}, modalities={"depth", "instance"})
            full = res.instance > 0
            mask = cv2.imread(str(scene / "mask" / f"{im:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            visib = cv2.imread(str(scene / "mask_visib" / f"{im:06d}_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            mine_visib = full & (np.abs(res.depth - depth) < 0.08)  # png quantises to 0.1 mm
            if full.sum() >= 50:
                assert (full & mask).sum() / (full | mask).sum() >= 0.99
            if visib.sum() >= 50:
                assert (mine_visib & visib).sum() / (mine_visib | visib).sum() >= 0.99
                checked += 1
            assert gi["px_count_visib"] == visib.sum()
            assert gi["px_count_all"] >= mask.sum()
    assert checked >= N


def test_visibility_threshold_holds(dataset):
    root, cfg, _ = dataset
    thr = cfg.rejection.min_visib_fract
    for _, _, _, gts, infos in images(root):
        per_inst = {}
        for gt, gi in zip(gts, infos):
            a = per_inst.setdefault(gt["instrument_index"], [0, 0])
            a[0] += gi["px_count_visib"]
            a[1] += gi["px_count_all"]
            if gt["part"] == "wrist":
                assert gi["visib_fract"] >= thr
            assert gi["visib_fract"] == pytest.approx(gi["px_count_visib"] / gi["px_count_all"])
        for vis, full in per_inst.values():
            assert vis >= thr * full


def test_no_collisions_and_rcm(dataset):
    """Fresh fcl check of every image's parts at their GT poses, and the RCM: the shaft axis passes
    through the trocar."""
    root, cfg, _ = dataset
    models = load_bop_models(root / "models")
    two = 0
    for _, _, _, gts, _ in images(root):
        manager = trimesh.collision.CollisionManager()
        for k, gt in enumerate(gts):
            T = np.eye(4)
            T[:3, :3] = np.array(gt["cam_R_m2c"]).reshape(3, 3)
            T[:3, 3] = gt["cam_t_m2c"]
            manager.add_object(f"{k}", models[gt["obj_id"]].mesh, transform=T)
            if gt["part"] == "shaft":
                trocar = np.array(gt["trocar_mm"])
                axis = T[:3, 2]
                d = np.linalg.norm(np.cross(trocar - T[:3, 3], axis))
                assert d < 0.1
        assert not manager.in_collision_internal()
        two += len({gt["instrument_index"] for gt in gts}) == 2
    assert two > 0, "no image with two instruments: the occlusion path went untested"


def test_joint_angles_within_ranges(dataset):
    root, cfg, _ = dataset
    p = cfg.pose
    assert p.joint_source == "limits"  # the default: each instrument's own reach
    for _, _, _, gts, _ in images(root):
        for gt in gts:
            j = gt["joints_deg"]
            for name, (lo, hi) in load_instrument(gt["instrument"]).reach().items():
                assert np.degrees(lo) - 1e-6 <= j[name] <= np.degrees(hi) + 1e-6, name
            assert p.tip_to_tissue_mm[0] <= gt["tip_to_tissue_mm"] <= p.tip_to_tissue_mm[1]


@pytest.mark.parametrize("name", ["lnd", "scissors", "permanent_cautery_spatula"])
def test_joint_sampling_follows_the_instruments_limits_or_the_papers_ranges(name):
    """The default samples each joint over the instrument's YAML limits and covers them; the paper preset
    stays in its ranges (within the limits)."""
    inst = load_instrument(name)
    rng = np.random.default_rng(0)
    reach = load_synth_config().pose
    qs = np.array([[getattr(sample_joints(inst, reach, rng), n) for n in JOINT_NAMES] for _ in range(2000)])
    for k, n in enumerate(JOINT_NAMES):
        lo, hi = inst.limits.ranges.get(n, (0.0, 0.0))  # a joint without a limit (a spatula's opening) stays 0
        assert lo - 1e-9 <= qs[:, k].min() and qs[:, k].max() <= hi + 1e-9, n
        want = inst.reach()[n]
        if want[1] > want[0]:  # the samples cover the range they are drawn from
            assert qs[:, k].min() < want[0] + 0.02 * (want[1] - want[0]) and qs[:, k].max() > want[1] - 0.02 * (want[1] - want[0])
    assert np.ptp(qs[:, 0]) > np.radians(350)  # roll: the full circle
    paper = load_synth_config("paper").pose
    assert paper.joint_source == "ranges"
    qs = np.array([[getattr(sample_joints(inst, paper, rng), n) for n in JOINT_NAMES] for _ in range(500)])
    assert np.degrees(np.abs(qs[:, 0])).max() <= 30 + 1e-6 and np.degrees(np.abs(qs[:, 1])).max() <= 60 + 1e-6
    for k, n in enumerate(JOINT_NAMES):  # within the limits, and 0 without one, here too
        lo, hi = inst.limits.ranges.get(n, (0.0, 0.0))
        assert lo - 1e-9 <= qs[:, k].min() and qs[:, k].max() <= hi + 1e-9, n


def test_normals_face_the_camera(dataset):
    root, _, _ = dataset
    scene, im, cam, _, _ = next(images(root))
    n = decode_normals(cv2.cvtColor(cv2.imread(str(scene / "normal" / f"{im:06d}.png")), cv2.COLOR_BGR2RGB))
    camera = PinholeCamera(np.array(cam["cam_K"]).reshape(3, 3), W, H)
    rays = camera.rays()
    valid = np.linalg.norm(n, axis=-1) > 0.5
    assert valid.mean() > 0.9
    assert (np.einsum("hwc,hwc->hw", n, rays)[valid] < 0.05).mean() > 0.99


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted((root / "train").rglob("*")):
        if p.is_file() and "records" not in p.parts:
            h.update(p.relative_to(root).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_deterministic_across_workers_and_resumable(dataset, tmp_path):
    root, cfg, _ = dataset
    other = tmp_path / "two_workers"
    generate_dataset(other, cfg, N, seed=5, workers=2, progress=False)
    assert _digest(other) == _digest(root)
    # Interrupt: drop the last scene's finalised files and two records, then resume.
    resumed = tmp_path / "resumed"
    generate_dataset(resumed, cfg, N - 3, seed=5, workers=1, progress=False)
    report = generate_dataset(resumed, cfg, N, seed=5, workers=1, progress=False)
    assert report.skipped == N - 3 and report.made == 3
    assert _digest(resumed) == _digest(root)


def test_bad_config_is_reported_with_its_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("pose: {roll_deg: [30, -30]}\n")
    with pytest.raises(ConfigError, match="bad.yaml.*roll_deg"):
        load_synth_config(bad)
    bad.write_text("posse: {}\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_synth_config(bad)
    # values a worker or a comparison would only trip over later: one line naming the file
    for text, why in (("effects: {noise: [0, 2]}", "effects: unknown camera effect"),
                      ("effects: {blur_prob: 2}", "effects: blur_prob must be a probability"),
                      ("tissue: {tilt_deg: 30}", r"tissue.tilt_deg: expected a \[lo, hi\] range"),
                      ("image: {width: 0}", "even positive integers"),
                      ("image: {width: '640'}", "even positive integers"),
                      ("two_instruments_prob: '0.3'", "bad.yaml")):
        bad.write_text(text + "\n")
        with pytest.raises(ConfigError, match=f"bad.yaml.*{why}" if why != "bad.yaml" else why):
            load_synth_config(bad)


def test_roll_zero_sets_which_way_the_jaws_open():
    """At zero roll the jaws open along the base x axis: towards the camera's viewing direction with
    ``roll_zero: view``, across the view (both jaws at one depth) with ``across``; the shaft stays put."""
    from surftrack.instruments import rcm_base_pose
    from surftrack.synth.sampling import roll_reference

    view, across = (load_synth_config(overrides={"pose": {"roll_zero": z}}).pose for z in ("view", "across"))
    rng = np.random.default_rng(0)
    for _ in range(20):
        theta, phi = np.radians(rng.uniform(35, 75)), rng.uniform(0, 2 * np.pi)
        shaft = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        pitch_point = rng.normal(size=3) * 10 + [0, 0, 100]
        Bv = rcm_base_pose(pitch_point - 80 * shaft, pitch_point, roll_reference(view, shaft))
        Ba = rcm_base_pose(pitch_point - 80 * shaft, pitch_point, roll_reference(across, shaft))
        assert np.allclose(Bv[:3, 2], shaft) and np.allclose(Ba[:3, 2], shaft)
        assert Bv[2, 0] == pytest.approx(np.sin(theta))  # x as far towards +z as a vector normal to the shaft gets
        assert Ba[2, 0] == pytest.approx(0.0, abs=1e-12)
    # and the sampler uses it
    from surftrack.instruments import load_instrument
    from surftrack.synth.config import TissueCfg
    from surftrack.synth.sampling import sample_camera, sample_instrument, sample_tissue_pose
    from surftrack.synth.tissue import procedural_tissue

    cfg = load_synth_config()
    lnd, tissue = load_instrument("lnd"), procedural_tissue(rng)
    for pose_cfg, expect_zero in ((view, False), (across, True)):
        got = 0
        for _ in range(40):
            cam = sample_camera(cfg.image, cfg.camera, rng)
            s = sample_instrument(lnd, pose_cfg, rng, cam, tissue, sample_tissue_pose(TissueCfg(), rng))
            if s is not None:
                got += 1
                assert (abs(s.base[2, 0]) < 1e-9) == expect_zero
        assert got >= 5
    bad = {"pose": {"roll_zero": "sideways"}}
    with pytest.raises(ConfigError, match="roll_zero must be one of view, across"):
        load_synth_config(overrides=bad)


def test_resume_refuses_another_seed_or_config(dataset):
    root, cfg, _ = dataset
    before = _digest(root)
    with pytest.raises(ConfigError, match="another seed or configuration"):
        generate_dataset(root, cfg, N + 2, seed=6, workers=1, progress=False)
    other = load_synth_config(overrides={**SMALL, "two_instruments_prob": 0.1})
    with pytest.raises(ConfigError, match="another seed or configuration"):
        generate_dataset(root, other, N + 2, seed=5, workers=1, progress=False)
    assert _digest(root) == before


def test_resume_accepts_a_card_from_before_a_config_key_existed(dataset, tmp_path):
    """A dataset made before a key was added (its card lacks it) resumes under that key's default,
    which is the behaviour it was made with; a non-default value is still refused."""
    from surftrack.synth.generate import _check_resume

    root, cfg, _ = dataset
    card = json.loads((root / "dataset_card.json").read_text())
    del card["config"]["pose"]["roll_zero"]
    (tmp_path / "dataset_card.json").write_text(json.dumps(card))
    _check_resume(tmp_path, cfg, 5)
    across = load_synth_config(overrides={**SMALL, "pose": {**cfg.to_dict()["pose"], "roll_zero": "across"}})
    with pytest.raises(ConfigError, match="another seed or configuration"):
        _check_resume(tmp_path, across, 5)


def test_resume_takes_an_alias_for_its_instrument(dataset):
    """``--instruments lnd`` resumes a dataset made with ``large_needle_driver``; another tool does not."""
    from surftrack.synth.generate import _check_resume

    root, cfg, _ = dataset
    _check_resume(root, load_synth_config(overrides={**SMALL, "instruments": ["lnd", "scissors"]}), 5)
    with pytest.raises(ConfigError, match="another seed or configuration"):
        _check_resume(root, load_synth_config(overrides={**SMALL, "instruments": ["lnd", "cadiere_forceps"]}), 5)


def test_resume_refuses_an_instrument_whose_geometry_changed(dataset, tmp_path):
    from surftrack.synth.generate import _check_resume

    root, cfg, _ = dataset
    card = json.loads((root / "dataset_card.json").read_text())
    assert all(len(o["mesh_sha256"]) == 64 for o in card["objects"].values())
    _check_resume(root, cfg, 5)
    first = sorted(card["objects"], key=int)[0]
    card["objects"][first]["mesh_sha256"] = "0" * 64  # the recorded hash differs from today's ...
    (tmp_path / "dataset_card.json").write_text(json.dumps(card))
    shutil.copytree(root / "models", tmp_path / "models")
    _check_resume(tmp_path, cfg, 5)  # ... but the dataset's model is today's mesh: a hash that moved alone
    ply = tmp_path / "models" / f"obj_{int(first):06d}.ply"
    mesh = trimesh.load(ply, force="mesh", process=False)
    mesh.apply_scale(1.05)  # the part's mesh edited since the images were made
    mesh.export(ply)
    with pytest.raises(ConfigError, match=f"geometry of {card['objects'][first]['instrument']}/"):
        _check_resume(tmp_path, cfg, 5)


def test_resume_refuses_a_damaged_card_in_one_line(tmp_path):
    from surftrack.synth.generate import _check_resume

    (tmp_path / "dataset_card.json").write_text('{"config": {"image"')  # cut off mid-write
    with pytest.raises(ConfigError, match="dataset_card.json: not a dataset card"):
        _check_resume(tmp_path, load_synth_config(overrides=SMALL), 5)


def test_instrument_aliases_and_duplicates(tmp_path):
    cfg = load_synth_config(overrides={**SMALL, "instruments": ["lnd", "mcs"]})
    from surftrack.synth.generate import load_instruments

    assert [i.name for i in load_instruments(cfg)] == ["large_needle_driver", "scissors"]
    dup = load_synth_config(overrides={**SMALL, "instruments": ["lnd", "large_needle_driver"]})
    with pytest.raises(ConfigError, match="twice"):
        load_instruments(dup)

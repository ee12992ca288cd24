"""Evaluation on a BOP split: the output files, the metric aggregation against hand computations (with
injected poses), and the CLI's one-line errors."""

import csv
import json

import numpy as np
import pytest
import torch

from surftrack.data import BopDataset
from surftrack.eval import auc
from surftrack.geometry import box_from_bop
from surftrack.model.checkpoint import save_checkpoint
from surftrack.model.config import TrainConfig
from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D
from surftrack.pose.estimator import PartPose, PoseEstimator
from surftrack.pose.evaluate import (evaluate, evaluate_seeds, group_stats, markdown_table, pose_errors, seed_table,
                                     summarize, write_eval_outputs)
from surftrack.pose.preset import get_preset
from surftrack.synth.config import load_synth_config
from surftrack.synth.generate import generate_dataset

TINY = {
    "model": {"emb_dim": 12, "decoder_widths": [32, 32, 16, 16, 16], "single_decoder": False, "siren_hidden": 64},
    "data": {"crop": 64, "scale": 1.2, "jitter": 0.0, "max_rotation_deg": 0, "mask_mode": "amodal",
             "min_visib_fract": 0.1},
}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(dataset root, checkpoint): 3 images 320x256 (split "train") and an untrained tiny model."""
    root = tmp_path_factory.mktemp("eval_data")
    cfg = load_synth_config(overrides={
        "image": {"width": 320, "height": 256}, "two_instruments_prob": 0.0,
        "tissue": {"images_per_tissue": 3, "spacing_mm": 4.0, "texel_mm": 1.0},
        "output": {"images_per_scene": 3, "rgb_format": "png"}})
    generate_dataset(root, cfg, 3, seed=3, workers=1, progress=False)
    bop = BopDataset(root, "train")
    card = json.loads((root / "dataset_card.json").read_text())["objects"]
    parts = [PartInfo.from_part(o, card[str(o)]["instrument"], bop.models[o]) for o in sorted(bop.models)]
    torch.manual_seed(0)
    ckpt = save_checkpoint(root / "m.pt", SurfSurg6D(parts, TrainConfig.from_dict(TINY).model),
                           TrainConfig.from_dict(TINY), 0)
    return root, ckpt


REQUIRED = {"count", "failures", "re_mean", "re_median", "te_mean", "te_median", "add_mean", "add_median",
            "adds_mean", "add10_bop", "add10_surgripe", "auc_add_0_5mm", "auc_adds_0_5mm"}


def test_evaluate_writes_json_table_csv_png(tiny, tmp_path):
    root, ckpt = tiny
    r = evaluate(ckpt, root, split="train", preset="fast", max_images=2, device="cpu")
    bop = BopDataset(root, "train")
    images = sorted({(i.scene_id, i.im_id) for i in bop.instances})[:2]
    gt = {(i.scene_id, i.im_id, i.obj_id): i for i in bop.instances if (i.scene_id, i.im_id) in images}
    assert r["n_images"] == 2 and r["n_instances"] == len(gt) == len(r["instances"])
    assert r["preset"] == "fast" and r["occlusion"]["threshold"] == 0.9
    assert set(r["diameters"]) == {"bop", "surgripe"}
    for p in list(r["parts"].values()) + [r["overall"]]:
        for g in ("non_occ", "occ", "all"):
            assert set(p[g]) >= REQUIRED
        assert p["all"]["count"] == p["non_occ"]["count"] + p["occ"]["count"]
    assert r["overall"]["all"]["count"] == len(gt)
    for p in r["parts"].values():
        assert p["diameter_surgripe_mm"] >= p["diameter_bop_mm"] > 0
    assert r["timings"]["per_image_s_mean"] > 0 and "forward" in r["timings"]["per_instance_ms_mean"]

    paths = write_eval_outputs(r, tmp_path / "out" / "ev.json")
    data = json.loads(paths["json"].read_text())
    assert data["n_instances"] == len(gt) and set(data["overall"]) == {"non_occ", "occ", "all"}
    md = paths["markdown"].read_text()
    assert md == markdown_table(r)
    rows = [l for l in md.splitlines() if l.startswith("| ")]
    assert "Non-occ RE" in rows[0] and "occ ADD-10" in rows[0] and "Avg Avg ACC 0-5 mm" in rows[0]
    assert len(rows[0].split("|")) - 2 == 1 + 3 * 4
    assert any(l.startswith("| **Avg** |") for l in rows)
    assert all(label in md for label in r["parts"])
    assert "SurgRIPE diameter" in md and "BOP diameter" in md and "visib_fract < 0.9" in md
    with paths["bop_csv"].open() as f:
        recs = list(csv.DictReader(f))
    assert list(recs[0]) == ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
    assert len(recs) == len(gt)
    for row in recs:
        inst = gt[(int(row["scene_id"]), int(row["im_id"]), int(row["obj_id"]))]
        R = np.array([float(v) for v in row["R"].split(" ")]).reshape(3, 3)
        t = np.array([float(v) for v in row["t"].split(" ")])
        assert R.shape == (3, 3) and t.shape == (3,) and float(row["time"]) > 0
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6)
        # t in mm: the CSV's pose reproduces the recorded TE against the ground truth (mm).
        rec = next(x for x in r["instances"] if (x["scene_id"], x["im_id"], x["obj_id"]) ==
                   (inst.scene_id, inst.im_id, inst.obj_id))
        assert np.linalg.norm(t - inst.t) == pytest.approx(rec["te"], abs=1e-4)
        assert 5.0 < inst.t[2] < 1000.0  # ground-truth depths are tens of mm
    assert paths["plot"].is_file() and paths["plot"].stat().st_size > 1000


class _Oracle(PoseEstimator):
    """Returns the ground truth changed by ``perturb(obj_id, part name, R, t) -> (R, t)``."""

    def __init__(self, ckpt, gt, perturb):
        super().__init__(ckpt, "fast", device="cpu")
        self.gt, self.perturb = gt, perturb
        self.names = {p.obj_id: (p.name, p.instrument) for p in self.model.parts}

    def estimate_batch(self, images, boxes_per_image, Ks, priors=None, groups=None):
        out = []
        for i, boxes in enumerate(boxes_per_image):
            poses = []
            for obj_id, box in boxes:
                inst = self.gt[(obj_id, tuple(box))]
                name, instrument = self.names[obj_id]
                R, t = self.perturb(obj_id, name, inst.R.copy(), inst.t.copy())
                poses.append(PartPose(obj_id, name, instrument, R, t, 1.0, 10, True,
                                      {"forward": 1.0, "total": 1.0}, (0, 0, 1, 1), np.eye(3), i))
            out.append(poses)
        return out


def test_aggregation_with_injected_poses(tiny):
    root, ckpt = tiny
    bop = BopDataset(root, "train")
    gt = {(i.obj_id, box_from_bop(i.bbox_visib)): i for i in bop.instances}
    assert len(gt) == len(bop.instances)
    # Shift each part by the mean of its two diameters' 10 %: ADD-10 passes under SurgRIPE's (larger)
    # diameter and fails under BOP's.
    d = {o: (m.diameter_max_pairwise, m.diameter_bbox_diagonal) for o, m in bop.models.items()}
    shift = {o: 0.05 * (a + b) for o, (a, b) in d.items()}
    # RE 0, TE = ADD = shift
    oracle = _Oracle(ckpt, gt, lambda o, name, R, t: (R, t + np.array([0.0, 0.0, shift[o]])))
    r = evaluate(oracle, root, split="train", occlusion_threshold=0.9)
    assert r["n_images"] == 3 and r["n_instances"] == len(bop.instances)
    for label, p in r["parts"].items():
        o = p["obj_id"]
        assert p["diameter_bop_mm"] == pytest.approx(d[o][0], rel=1e-9)
        assert p["diameter_surgripe_mm"] == pytest.approx(d[o][1], rel=1e-9)
        a = p["all"]
        n = sum(1 for i in bop.instances if i.obj_id == o)
        assert a["count"] == n
        assert a["re_mean"] == pytest.approx(0.0, abs=1e-3)
        assert a["te_mean"] == pytest.approx(shift[o]) and a["add_mean"] == pytest.approx(shift[o])
        assert a["add10_surgripe"] == 1.0 and a["add10_bop"] == 0.0
        # VOCap by hand (n equal errors e; the toolbox credits 1/n on [0, e]): (5 - e) / 5 + e / (5 n), 0 if e > 5.
        e = shift[o]
        assert a["auc_add_0_5mm"] == pytest.approx((5 - e) / 5 + e / (5 * n) if e <= 5.0 else 0.0)
        n_occ = sum(1 for i in bop.instances if i.obj_id == o and i.visib_fract < 0.9)
        assert p["occ"]["count"] == n_occ and p["non_occ"]["count"] == n - n_occ
    allv = r["overall"]["all"]
    shifts = [shift[i.obj_id] for i in bop.instances]
    assert allv["te_mean"] == pytest.approx(np.mean(shifts)) and allv["te_median"] == pytest.approx(np.median(shifts))
    assert allv["add10_surgripe"] == 1.0 and allv["add10_bop"] == 0.0


def test_each_instance_records_its_signed_depth_error(tiny):
    """``depth_err_rel``: the estimate's excess along the true line of sight over the true distance
    (negative: too close); a pose moved sideways has none; a non-finite estimate has None."""
    from surftrack.pose.evaluate import depth_error_rel

    root, ckpt = tiny
    bop = BopDataset(root, "train")
    gt = {(i.obj_id, box_from_bop(i.bbox_visib)): i for i in bop.instances}
    r = evaluate(_Oracle(ckpt, gt, lambda o, name, R, t: (R, t * 0.97)), root, split="train")
    assert [i["depth_err_rel"] for i in r["instances"]] == pytest.approx([-0.03] * len(bop.instances))
    for p in r["parts"].values():
        assert p["all"]["depth_bias"] == pytest.approx(-0.03) and p["all"]["depth_bias_count"] == p["all"]["count"]
    assert "Depth bias (% of the distance" in markdown_table(r) and "-3.00 (" in markdown_table(r)
    # a wrong rotation, or a depth 20 % off, says nothing about the bias
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    r = evaluate(_Oracle(ckpt, gt, lambda o, name, R, t: (R @ turn, t * 0.97) if name == "shaft" else (R, t * 0.8)),
                 root, split="train")
    assert {p["all"]["depth_bias_count"] for p in r["parts"].values()} == {0}
    assert all(p["all"]["depth_bias"] is None for p in r["parts"].values())
    assert "Depth bias" not in markdown_table(r)
    t = np.array([3.0, -4.0, 80.0])
    side = np.cross(t, [0.0, 1.0, 0.0])
    assert depth_error_rel(t + 2.0 * side / np.linalg.norm(side), t) == pytest.approx(0.0, abs=1e-12)
    assert depth_error_rel([np.nan, 0.0, 1.0], t) is None


def test_the_roll_twin_is_scored_as_a_symmetry(tiny):
    """Estimates that are the LND's roll twin of the truth (half a turn about the shaft, the jaws exchanged:
    the same image) fail ADD-10 as scored and pass it with the twin counted as a symmetry of the
    instrument; the truth passes both."""
    from surftrack.instruments import HALF_TURN

    root, ckpt = tiny
    bop = BopDataset(root, "train")
    gt = {(i.obj_id, box_from_bop(i.bbox_visib)): i for i in bop.instances}
    partner = {"shaft": "shaft", "wrist": "wrist", "jaw_left": "jaw_right", "jaw_right": "jaw_left"}

    class Twin(_Oracle):
        def estimate_batch(self, images, boxes_per_image, Ks, priors=None, groups=None):
            out = []
            for i, boxes in enumerate(boxes_per_image):
                insts = [self.gt[(o, tuple(b))] for o, b in boxes]
                by_name = {self.names[x.obj_id][0]: x for x in insts}
                poses = []
                for x in insts:
                    name, instrument = self.names[x.obj_id]
                    src = by_name.get(partner[name])  # a part whose partner is hidden keeps the truth
                    R, t = (src.R @ HALF_TURN, src.t.copy()) if src is not None else (x.R.copy(), x.t.copy())
                    poses.append(PartPose(x.obj_id, name, instrument, R, t, 1.0, 10, True,
                                          {"forward": 1.0, "total": 1.0}, (0, 0, 1, 1), np.eye(3), i))
                out.append(poses)
            return out

    twin = evaluate(Twin(ckpt, gt, None), root, split="train")
    scored = [r for r in twin["instances"] if "add10_twin_surgripe" in r]
    assert len({(r["scene_id"], r["im_id"]) for r in scored}) >= 1  # an image showing the whole instrument
    assert all(r["add10_twin_surgripe"] for r in scored)
    assert not any(r["add10_surgripe"] for r in scored if r["part"].endswith(("shaft", "wrist")))
    assert twin["overall"]["all"]["twin_count"] == len(scored) < len(twin["instances"])
    assert "roll twin counted as a symmetry" in markdown_table(twin)
    truth = evaluate(_Oracle(ckpt, gt, lambda o, name, R, t: (R, t)), root, split="train")
    assert truth["overall"]["all"]["add10_surgripe"] == truth["overall"]["all"]["add10_twin_surgripe"] == 1.0


def test_summarize_hand_computed():
    parts = {1: {"label": "shaft", "diameter_bop_mm": 20.0, "diameter_surgripe_mm": 30.0},
             2: {"label": "jaw", "diameter_bop_mm": 10.0, "diameter_surgripe_mm": 12.0}}
    rec = [  # obj, visib, re, te, add
        (1, 1.00, 2.0, 1.0, 1.0), (1, 0.95, 4.0, 3.0, 2.5), (1, 0.50, 10.0, 6.0, 8.0),
        (2, 0.80, 6.0, 0.5, 1.1), (2, 0.30, 30.0, 9.0, 20.0), (2, 0.92, 1.0, 0.2, 0.4, False),
    ]
    records = [{"obj_id": o, "visib_fract": v, "re": a, "te": b, "add": c, "adds": c / 2, "ok": (x[0] if x else True)}
               for o, v, a, b, c, *x in rec]
    s = summarize(records, parts, occlusion_threshold=0.9)
    assert list(s["parts"]) == ["shaft", "jaw"]
    sh = s["parts"]["shaft"]
    assert sh["non_occ"]["count"] == 2 and sh["occ"]["count"] == 1
    assert sh["non_occ"]["re_mean"] == pytest.approx(3.0) and sh["non_occ"]["te_median"] == pytest.approx(2.0)
    # ADD < 2.0 (BOP 10 %) vs < 3.0 (SurgRIPE): adds 1.0, 2.5, 8.0
    assert sh["all"]["add10_bop"] == pytest.approx(1 / 3) and sh["all"]["add10_surgripe"] == pytest.approx(2 / 3)
    # VOCap closed form: mean(max(0, 5 - e) / 5) + e_(m) / (n * 5)
    e = np.array([1.0, 2.5, 8.0])
    hand = np.mean(np.maximum(0, 5 - e) / 5) + 2.5 / (3 * 5)
    assert sh["all"]["auc_add_0_5mm"] == pytest.approx(hand)
    jaw = s["parts"]["jaw"]
    assert jaw["occ"]["count"] == 2 and jaw["non_occ"]["count"] == 1 and jaw["all"]["failures"] == 1
    assert jaw["all"]["add10_bop"] == pytest.approx(1 / 3) and jaw["all"]["add10_surgripe"] == pytest.approx(2 / 3)
    ov = s["overall"]
    assert ov["all"]["count"] == 6 and ov["occ"]["count"] == 3 and ov["non_occ"]["count"] == 3
    assert ov["all"]["re_mean"] == pytest.approx(np.mean([2, 4, 10, 6, 30, 1]))
    assert ov["occ"]["te_median"] == pytest.approx(6.0)  # occ: 6.0, 0.5, 9.0
    assert ov["all"]["add10_bop"] == pytest.approx(2 / 6)  # 1.0 < 2 and 0.4 < 1; 1.1 >= 1.0
    assert ov["all"]["add10_surgripe"] == pytest.approx(4 / 6)  # + 2.5 < 3 and 1.1 < 1.2
    assert ov["all"]["failures"] == 1
    empty = group_stats([], {})
    assert empty["count"] == 0 and empty["re_mean"] is None
    result = {"parts": s["parts"], "overall": ov, "occlusion": {"definition": "occluded = visib_fract < 0.9"}}
    md = markdown_table(result)
    avg = next(l for l in md.splitlines() if l.startswith("| **Avg**"))
    cells = [c.strip() for c in avg.strip("|").split("|")]
    assert cells[1] == f"{np.mean([2, 4, 1]):.2f}" and cells[3] == "100.00"  # Non-occ RE, ADD-10 SurgRIPE
    assert cells[4] == f"{100 * auc([1.0, 2.5, 0.4]):.2f}"


def test_pose_errors_known_pose():
    pts = np.array([[10.0, 0, 0], [0, 10.0, 0], [0, 0, 10.0], [-10.0, 0, 0]])
    c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    t_g = np.array([0.0, 0.0, 100.0])
    e = pose_errors(Rz, t_g + [3.0, 4.0, 0.0], np.eye(3), t_g, pts)
    assert e["re"] == pytest.approx(10.0) and e["te"] == pytest.approx(5.0)
    hand = np.mean([np.linalg.norm(Rz @ p + [3, 4, 0] - p) for p in pts])
    assert e["add"] == pytest.approx(hand) and e["adds"] <= e["add"]
    assert pose_errors(np.full((3, 3), np.nan), t_g, np.eye(3), t_g, pts)["add"] == np.inf


def test_cli_eval_bad_inputs_and_run(tiny, tmp_path, capsys):
    from surftrack.cli import main

    root, ckpt = tiny
    cases = [
        (["--model", str(tmp_path / "missing.pt"), "--data", str(root)], "checkpoint not found"),
        (["--model", str(ckpt), "--data", str(tmp_path / "nodata")], "dataset root is missing"),
        (["--model", str(ckpt), "--data", str(root), "--split", "test"], "split folder is missing"),
        (["--model", str(ckpt), "--data", str(root), "--max-images", "0"], "--max-images"),
        (["--model", str(ckpt), "--data", str(root), "--seed", "-1"], "--seed"),
        (["--model", str(ckpt), "--data", str(root), "--seed", "1", "1"], "--seed takes distinct"),
        (["--model", str(ckpt), "--data", str(root), "--views", "10"], "--views must be between 1 and 9"),
        (["--model", str(ckpt), "--data", str(root), "--anchor-views", "3"], "it needs --kinematic"),
        (["--model", str(ckpt), "--data", str(root), "--kinematic", "--anchor-views", "0"],
         "--anchor-views must be between 1 and 9"),
    ]
    for args, msg in cases:
        assert main(["eval", *args, "--out", str(tmp_path / "e.json"), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("surftrack: error:") and msg in err and err.count("\n") == 1, err
    out = tmp_path / "ok" / "e.json"
    assert main(["eval", "--model", str(ckpt), "--data", str(root), "--split", "train", "--preset", "fast",
                 "--max-images", "1", "--seed", "5", "--out", str(out), "--device", "cpu", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "| **Avg** |" in printed and str(out.with_suffix(".bop.csv")) in printed and "(seed 5)" in printed
    assert json.loads(out.read_text())["seed"] == 5 and json.loads(out.read_text())["views"] == 1
    assert all(p.is_file() for p in (out, out.with_suffix(".md"), out.with_suffix(".png")))
    # several seeds: one set of outputs each and a table of ADD-10 per seed with the mean
    many = tmp_path / "many" / "e.json"
    assert main(["eval", "--model", str(ckpt), "--data", str(root), "--split", "train", "--preset", "fast",
                 "--max-images", "1", "--seed", "0", "3", "--out", str(many), "--device", "cpu", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "| Part | seed 0 | seed 3 | mean | range |" in printed and "| **Avg** |" in printed
    for s in (0, 3):
        assert json.loads((many.parent / f"e.seed{s}.json").read_text())["seed"] == s
    assert not many.exists() and (many.parent / "e.seeds.md").read_text() in printed
    # crop views
    views = tmp_path / "views" / "e.json"
    assert main(["eval", "--model", str(ckpt), "--data", str(root), "--split", "train", "--preset", "fast",
                 "--max-images", "1", "--views", "2", "--out", str(views), "--device", "cpu", "--quiet"]) == 0
    assert "2 crop views per box" in capsys.readouterr().out
    assert json.loads(views.read_text())["views"] == 2
    assert {i["timings_ms"]["total"] > 0 for i in json.loads(views.read_text())["instances"]} == {True}
    # more crop views for the instrument fit's anchor only
    anchor = tmp_path / "anchor" / "e.json"
    assert main(["eval", "--model", str(ckpt), "--data", str(root), "--split", "train", "--preset", "fast",
                 "--max-images", "1", "--kinematic", "--anchor-views", "3", "--out", str(anchor), "--device", "cpu",
                 "--quiet"]) == 0
    assert ", 3 crop views on wrist)" in capsys.readouterr().out
    assert json.loads(anchor.read_text())["views"] == 1 and json.loads(anchor.read_text())["part_views"] == {"wrist": 3}


def test_cli_preset_names_are_the_presets():
    from surftrack.cli import PRESET_NAMES
    from surftrack.pose.preset import PRESETS

    assert sorted(PRESET_NAMES) == sorted(PRESETS)


def test_seed_table_averages_the_seeds():
    def result(seed, wrist, avg):
        parts = {"lnd wrist": {"all": {"add10_surgripe": wrist}}, "lnd shaft": {"all": {"add10_surgripe": None}}}
        return {"seed": seed, "preset": "fast", "n_images": 3, "parts": parts,
                "overall": {"all": {"add10_surgripe": avg}}}

    table = seed_table([result(0, 0.5, 0.4), result(1, 0.6, 0.5), result(2, 0.7, 0.3)])
    assert "| Part | seed 0 | seed 1 | seed 2 | mean | range |" in table
    assert "| lnd wrist | 50.00 | 60.00 | 70.00 | 60.00 | 50.00-70.00 |" in table
    assert "| lnd shaft | – | – | – | – | – |" in table  # no instance of the part: no figure
    assert "| **Avg** | 40.00 | 50.00 | 30.00 | 40.00 | 30.00-50.00 |" in table
    with pytest.raises(ValueError):
        seed_table([])


def test_evaluate_seeds_shares_the_forward_and_matches_single_seed_runs(tiny):
    root, ckpt = tiny
    est = PoseEstimator(ckpt, "fast", device="cpu")
    calls = []
    forward = est._forward
    est._forward = lambda crops, keep_masks=False: calls.append(len(crops)) or forward(crops, keep_masks)
    many = evaluate_seeds(est, root, [0, 5], split="train", max_images=2, kinematic=True)
    assert len(calls) == 1  # one batch of 2 images: one forward for both seeds
    poses = {}
    for r in many:
        one = evaluate(PoseEstimator(ckpt, get_preset("fast").replace(seed=r["seed"]), device="cpu"), root,
                       split="train", max_images=2, kinematic=True)
        assert one["seed"] == r["seed"] and r["n_instances"] == one["n_instances"]
        for a, b in zip(r["instances"], one["instances"]):
            assert (a["scene_id"], a["im_id"], a["obj_id"]) == (b["scene_id"], b["im_id"], b["obj_id"])
            np.testing.assert_allclose(a["R"], b["R"], atol=1e-9)
            np.testing.assert_allclose(a["t"], b["t"], atol=1e-9)
            assert a["add"] == pytest.approx(b["add"])
        assert r["timings"]["per_image_s_mean"] > 0
        poses[r["seed"]] = np.array([x["t"] for x in r["instances"]])
    assert not np.allclose(poses[0], poses[5])  # the seed reaches the solver
    with pytest.raises(ValueError, match="distinct"):
        evaluate_seeds(ckpt, root, [1, 1], split="train")


def test_kinematic_evaluation_fixes_the_shaft_roll(tiny):
    root, ckpt = tiny
    bop = BopDataset(root, "train")
    gt = {(i.obj_id, box_from_bop(i.bbox_visib)): i for i in bop.instances}
    from scipy.spatial.transform import Rotation

    roll = Rotation.from_euler("z", 50, degrees=True).as_matrix()  # the shaft's near-symmetry
    est = _Oracle(ckpt, gt, lambda o, name, R, t: (R @ roll if name == "shaft" else R, t))
    raw = evaluate(est, root, split="train")
    kin = evaluate(est, root, split="train", kinematic=True)
    assert raw["kinematic"] is None and kin["kinematic"]["anchor"] == "wrist"
    assert raw["parts"]["large_needle_driver shaft"]["all"]["re_median"] == pytest.approx(50.0, abs=0.01)
    for label, p in kin["parts"].items():  # every part consistent with the (correct) wrist again
        assert p["all"]["re_mean"] < 1.0 and p["all"]["te_mean"] < 0.5, label
    assert "kinematic fit" in markdown_table(kin) and kin["kinematic_instruments"] == ["large_needle_driver"]
    for info in est.model.parts:  # a model of meshes no description has: said once, per-part poses kept
        info.mesh_sha256, info.vertices = "0" * 64, info.vertices * 1.01
    other = evaluate(est, root, split="train", kinematic=True)
    assert other["kinematic_instruments"] == [] and "kinematic fit" not in markdown_table(other)
    assert any("differ from those of" in w and "per-part poses" in w for w in other["warnings"])
    assert other["parts"]["large_needle_driver shaft"]["all"]["re_median"] == pytest.approx(50.0, abs=0.01)


def test_the_held_out_suite_is_made_once_and_evaluated_as_one_table(tiny_ckpt, tmp_path, capsys):
    """`surftrack eval --suite`: each set made with its seed and overrides, one row per set with a column per
    part, the mean over solver seeds; a second run reuses the sets; a bad suite file is one line, exit 2."""
    from surftrack.cli import main
    from surftrack.pose.suite import load_suite, set_config

    small = "{image: {width: 320, height: 256}, tissue: {images_per_tissue: 3, spacing_mm: 4.0, texel_mm: 1.0}, " \
            "output: {images_per_scene: 3, rgb_format: png}"
    (tmp_path / "suite.yaml").write_text(f"""images: 3
sets:
  paper: {{config: paper, seed: 13, overrides: {small}}}, about: narrow}}
  occluded: {{config: default, seed: 4, overrides: {small}, two_instruments_prob: 1.0}}}}
""")
    sets = load_suite(tmp_path / "suite.yaml")
    assert [s.name for s in sets] == ["paper", "occluded"]
    assert set_config(sets[0]).pose.joint_source == "ranges" and set_config(sets[1]).pose.joint_source == "limits"
    assert set_config(sets[1]).two_instruments_prob == 1.0 and set_config(sets[1]).image.width == 320
    args = ["eval", "--suite", str(tmp_path / "suite.yaml"), "--suite-dir", str(tmp_path / "sets"),
            "--model", str(tiny_ckpt), "--preset", "fast", "--seed", "0", "1", "--out", str(tmp_path / "e.json"),
            "--quiet"]
    assert main(args) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| paper") or line.startswith("| occluded")]
    assert len(rows) == 2 and "| shaft | wrist | jaw_left | jaw_right | all parts |" in out
    assert (tmp_path / "e.suite.md").is_file()
    rgb = sorted((tmp_path / "sets" / "paper").rglob("rgb/*.png"))
    made = [p.stat().st_mtime_ns for p in rgb]
    assert len(rgb) == 3 and main(args) == 0  # the set is there: its images are not made again
    assert [p.stat().st_mtime_ns for p in rgb] == made
    capsys.readouterr()
    (tmp_path / "bad.yaml").write_text("sets: {a: {seed: 1, sed: 2}}\n")
    assert main(["eval", "--suite", str(tmp_path / "bad.yaml"), "--model", str(tiny_ckpt)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "bad.yaml" in err and "sed" in err


@pytest.mark.parametrize("text, problem", [
    ("images: many\nsets: {a: {seed: 1}}\n", "'images' must be a positive integer"),
    ("sets: {a: [1, 2]}\n", "set 'a' must be a mapping"),
    ("sets: {a: {seed: 1, overrides: x}}\n", "'overrides' must be a mapping"),
    ("sets: {a: {seed: 1}}\nclips: {c: 5}\n", "clip 'c' must be a mapping"),
])
def test_a_malformed_suite_file_is_one_named_problem(tmp_path, text, problem):
    from surftrack.pose.suite import SuiteError, load_suite, load_suite_clips

    (tmp_path / "suite.yaml").write_text(text)
    with pytest.raises(SuiteError) as e:
        load_suite(tmp_path / "suite.yaml")
        load_suite_clips(tmp_path / "suite.yaml")
    assert str(tmp_path / "suite.yaml") in str(e.value) and problem in str(e.value)


def test_a_suite_clip_with_an_unreadable_record_is_refused(tmp_path):
    from surftrack.pose.suite import SuiteClip, SuiteError, make_suite_clips

    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "suite_clip.json").write_text("{not json")
    with pytest.raises(SuiteError, match="suite_clip.json: not a JSON record"):
        make_suite_clips([SuiteClip("a", 1, 2.0, 15.0)], tmp_path)


def test_eval_by_cause_bins_every_instance(tiny, tmp_path, capsys):
    """`eval --by-cause`: per condition one row for all parts and one per part, the instance counts of a
    row adding up to the instances evaluated; a plain BOP set gets the tables that need no joint angles."""
    import re
    import shutil

    from surftrack.cli import main

    root, ckpt = tiny
    out = tmp_path / "e.json"
    assert main(["eval", "--data", str(root), "--split", "train", "--model", str(ckpt), "--preset", "fast",
                 "--max-images", "2", "--by-cause", "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    n = json.loads(out.read_text())["n_instances"]
    tables = out.with_suffix(".causes.md").read_text()
    assert tables.strip() in text
    for title in ("depth z (mm)", "visible box side (px)", "visible fraction", "|roll| (deg)", "|pitch| (deg)"):
        row = next(line for line in tables.splitlines() if line.startswith("| all parts") and
                   tables.splitlines()[tables.splitlines().index(line) - 2].startswith(f"| {title} |"))
        assert sum(int(c) for c in re.findall(r"\((\d+)\)", row)) == n, (title, row)
    # a BOP set without joint angles (not made by synth): the other conditions, no joint tables
    bare = tmp_path / "bare"
    shutil.copytree(root, bare)
    for f in (bare / "train").rglob("scene_gt.json"):
        doc = json.loads(f.read_text())
        f.write_text(json.dumps({k: [{x: g[x] for x in ("obj_id", "cam_R_m2c", "cam_t_m2c")} for g in v]
                                 for k, v in doc.items()}))
    assert main(["eval", "--data", str(bare), "--split", "train", "--model", str(ckpt), "--preset", "fast",
                 "--max-images", "1", "--by-cause", "--out", str(tmp_path / "b.json"), "--quiet"]) == 0
    text = (tmp_path / "b.causes.md").read_text()
    assert "| depth z (mm) |" in text and "roll" not in text



def test_the_suite_clips_are_made_once_and_scored_per_frame(tiny_ckpt, tmp_path, capsys):
    """The suite's tracking clips: made with their seed, length and rate, scored by per-frame estimation
    (one row per clip, a column per part, mean over solver seeds), reused by a second run, and refused
    when the folder holds a clip made with other settings."""
    import json

    from surftrack.cli import main
    from surftrack.pose.suite import SuiteError, load_suite_clips, make_suite_clips

    small = "{image: {width: 320, height: 256}, tissue: {images_per_tissue: 2, spacing_mm: 4.0, texel_mm: 1.0}, " \
            "output: {images_per_scene: 2, rgb_format: png}}"
    (tmp_path / "suite.yaml").write_text(f"""images: 2
sets:
  paper: {{config: paper, seed: 13, overrides: {small}}}
clips:
  c1: {{seed: 411, seconds: 2.0, fps: 3, about: a short full-range clip}}
  c2: {{seed: 411, seconds: 2.0, fps: 3, roll_deg: [150, 170], roll_swing_deg: [0, 0]}}
""")
    clips = load_suite_clips(tmp_path / "suite.yaml")
    assert [(c.name, c.seed, c.seconds, c.fps) for c in clips] == [("c1", 411, 2.0, 3.0), ("c2", 411, 2.0, 3.0)]
    args = ["eval", "--suite", str(tmp_path / "suite.yaml"), "--suite-dir", str(tmp_path / "s"),
            "--model", str(tiny_ckpt), "--preset", "fast", "--seed", "0", "1", "--out", str(tmp_path / "e.json"),
            "--quiet", "--kinematic"]
    assert main(args) == 0
    out = capsys.readouterr().out
    row = [line for line in out.splitlines() if line.startswith("| c1 |")]
    assert len(row) == 1 and row[0].startswith("| c1 | 411 | 6 |") and "| shaft | wrist |" in out
    assert row[0].count("|") == 11 and "each frame's instrument scored as its estimate or" in out  # the LND's twin
    assert "c1: a short full-range clip" in (tmp_path / "e.suite.md").read_text()
    frames = json.loads((tmp_path / "s" / "c2" / "gt.json").read_text())["frames"].values()
    rolls = {rec["joints_deg"]["roll"] for f in frames for rec in f["gt"] if rec["instrument_index"] == 0}
    assert all(150 <= r <= 170 for r in rolls)  # a tool rolled away from the camera, as asked
    assert json.loads((tmp_path / "s" / "c2" / "suite_clip.json").read_text())["roll_deg"] == [150, 170]
    assert "roll_deg" not in json.loads((tmp_path / "s" / "c1" / "suite_clip.json").read_text())
    video = tmp_path / "s" / "c1" / "video.mp4"
    made = video.stat().st_mtime_ns
    assert make_suite_clips(clips, tmp_path / "s")["c1"] == tmp_path / "s" / "c1"
    assert video.stat().st_mtime_ns == made
    stamp = tmp_path / "s" / "c1" / "suite_clip.json"
    stamp.write_text(json.dumps({**json.loads(stamp.read_text()), "seed": 5}))
    with pytest.raises(SuiteError, match="other settings"):
        make_suite_clips(clips, tmp_path / "s")
    for clip, word in (("{seed: 1, fps: 0}", "fps"), ("{seed: 1, roll_deg: [10, -10]}", "roll_deg")):
        (tmp_path / "bad.yaml").write_text(f"sets: {{a: {{seed: 1}}}}\nclips: {{c: {clip}}}\n")
        assert main(["eval", "--suite", str(tmp_path / "bad.yaml"), "--model", str(tiny_ckpt)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "bad.yaml" in err and word in err, err

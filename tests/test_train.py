"""Real training steps on a tiny generated dataset: the loss falls, checkpoints round-trip, resume works."""

import json

import numpy as np
import pytest
import torch

from surftrack.model import load_checkpoint, load_train_config
from surftrack.model.train import train
from surftrack.synth.config import load_synth_config
from surftrack.synth.generate import generate_dataset

TINY = {
    "model": {"emb_dim": 12, "decoder_widths": [32, 32, 16, 16, 16], "single_decoder": False, "siren_hidden": 64},
    "data": {"crop": 64, "scale": 1.2, "jitter": 0.0, "max_rotation_deg": 0, "mask_mode": "amodal",
             "min_visib_fract": 0.1},
    "loss": {"alpha": 0.5, "beta": 1.0, "lam": 10.0, "m": 0.01, "pen_floor": 0.0, "n_pos": 128, "n_neg": 128,
             "key_noise": 0.001},
    "optim": {"lr_net": 1e-3, "lr_field": 3e-4, "batch": 6, "steps": 80, "warmup": 0},
    "run": {"val_every": 40, "val_images": 2, "ckpt_every": 40, "log_every": 1, "workers": 0, "seed": 0,
            "amp": False},
}


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("train_data")
    # the paper's narrower ranges: the loss-falls threshold below was set on them
    cfg = load_synth_config("paper", overrides={
        "image": {"width": 320, "height": 256}, "two_instruments_prob": 0.0,
        "tissue": {"images_per_tissue": 3, "spacing_mm": 4.0, "texel_mm": 1.0},
        "output": {"images_per_scene": 6, "rgb_format": "png"}})
    generate_dataset(root, cfg, 6, seed=3, workers=1, progress=False)
    return root


def test_overfit_loss_falls(tiny_data, tmp_path):
    from surftrack.model.config import TrainConfig

    cfg = TrainConfig.from_dict(TINY)
    out = tmp_path / "m.pt"
    s = train(cfg, tiny_data, out, progress=False)
    rows = [json.loads(l) for l in (tmp_path / "m.metrics.jsonl").read_text().splitlines()]
    tr = [r for r in rows if r["kind"] == "train"]
    first = {k: np.mean([r[k] for r in tr[:5]]) for k in ("nce", "mask")}
    last = {k: np.mean([r[k] for r in tr[-10:]]) for k in ("nce", "mask")}
    assert all(np.isfinite(r["total"]) and np.isfinite(r["grad_norm"]) for r in tr)
    # 80 steps on 6 images: InfoNCE (log 129 = 4.86 at chance) falls by at least 1.2x, mask BCE by 2x.
    assert last["nce"] < first["nce"] / 1.2, f"InfoNCE fell only from {first['nce']:.3f} to {last['nce']:.3f}"
    assert last["mask"] < first["mask"] / 2.0, f"mask BCE fell only from {first['mask']:.3f} to {last['mask']:.3f}"
    assert any(r["kind"] == "val" for r in rows) and "re_median" in s["val"]
    assert (tmp_path / "m.curves.png").is_file()
    assert s["steps"] == 80


def test_checkpoint_round_trip_and_resume(tiny_data, tmp_path):
    from surftrack.model.config import TrainConfig

    cfg = TrainConfig.from_dict(TINY).replace(optim={"steps": 4}, run={"val_every": 100, "ckpt_every": 2})
    out = tmp_path / "m.pt"
    train(cfg, tiny_data, out, progress=False)
    model, cfg2, blob = load_checkpoint(out)
    assert cfg2 == cfg and blob["step"] == 4
    assert [p.obj_id for p in model.parts] == [1, 2, 3, 4]
    assert len(model.parts[0].mesh_sha256) == 64
    # The parts carry their meshes and normalisation: inference needs nothing else.
    part = model.parts[2].to_part()
    assert np.allclose(part.bounding_sphere[1], model.parts[2].radius)
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        a = model(x, torch.tensor([1]))
    model_b, _, _ = load_checkpoint(out)
    with torch.no_grad():
        b = model_b(x, torch.tensor([1]))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    half, _, hblob = load_checkpoint(tmp_path / "m.fp16.pt")
    assert hblob["fp16"] and (tmp_path / "m.fp16.pt").stat().st_size < 0.6 * out.stat().st_size
    with torch.no_grad():
        c = half(x, torch.tensor([1]))
    assert torch.allclose(a[1], c[1], atol=5e-2, rtol=5e-2)
    # Resume continues from the saved step to the new target.
    s = train(cfg.replace(optim={"steps": 6}), tiny_data, out, resume=True, progress=False)
    assert s["steps"] == 6 and load_checkpoint(out)[2]["step"] == 6
    steps = [json.loads(line)["step"] for line in (tmp_path / "m.metrics.jsonl").read_text().splitlines()
             if json.loads(line)["kind"] == "train"]
    assert steps == sorted(set(steps)) and steps[-1] == 6  # no step logged twice across the resume


def test_training_mixes_a_second_dataset(tiny_data, tmp_path):
    """``data.real_data`` (the paper's syn:real 1:1 batches) trains end to end; here the second dataset is
    the same small set, which has the same models."""
    from surftrack.model.config import TrainConfig

    cfg = TrainConfig.from_dict(TINY).replace(data={"real_data": str(tiny_data), "syn_real_ratio": (1, 1)},
                                              optim={"steps": 3}, run={"val_every": 100})
    s = train(cfg, tiny_data, tmp_path / "m.pt", progress=False)
    assert s["steps"] == 3 and load_checkpoint(tmp_path / "m.pt")[2]["step"] == 3


def test_two_process_ddp_training(tiny_data, tmp_path):
    """``torchrun --nproc_per_node 2`` (gloo on CPU): per-part decoders and SIREN fields absent from a
    batch do not stall DDP, the processes end with the same weights (checked inside ``train``), and only
    rank 0 logs, saves and prints."""
    import os
    import subprocess
    import sys

    import yaml

    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(TINY))
    out = tmp_path / "m.pt"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                        "-m", "surftrack.cli", "train", "--config", str(tmp_path / "tiny.yaml"), "--data",
                        str(tiny_data), "--out", str(out), "--steps", "5", "--quiet"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.count("surftrack train: 5 steps") == 1, r.stdout
    assert load_checkpoint(out)[2]["step"] == 5
    rows = [json.loads(l) for l in (tmp_path / "m.metrics.jsonl").read_text().splitlines()]
    assert [row["step"] for row in rows if row["kind"] == "train"] == [1, 2, 3, 4, 5]


def test_bad_checkpoint_and_config_errors(tmp_path):
    from surftrack.model import CheckpointError, TrainConfigError

    bad = tmp_path / "x.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="x.pt"):
        load_checkpoint(bad)
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("optim: {stepz: 3}\n")
    with pytest.raises(TrainConfigError, match="stepz"):
        load_train_config(cfg)


def test_lr_schedule_warmup_and_cosine():
    from surftrack.model.config import OptimCfg, lr_factor

    const = OptimCfg(warmup=0, schedule="constant")
    assert lr_factor(const, 0, 100) == 1.0 and lr_factor(const, 99, 100) == 1.0
    cos = OptimCfg(warmup=10, schedule="cosine")
    assert lr_factor(cos, 0, 110) == pytest.approx(0.1) and lr_factor(cos, 9, 110) == pytest.approx(1.0)
    assert lr_factor(cos, 10, 110) == pytest.approx(1.0)
    assert lr_factor(cos, 60, 110) == pytest.approx(0.55)
    assert lr_factor(cos, 110, 110) == pytest.approx(0.1)
    vals = [lr_factor(cos, s, 110) for s in range(10, 111)]
    assert all(a >= b for a, b in zip(vals, vals[1:]))


def test_init_from_checkpoint(tiny_data, tmp_path):
    from surftrack.model import CheckpointError
    from surftrack.model.config import TrainConfig

    cfg = TrainConfig.from_dict(TINY).replace(optim={"steps": 2, "lr_net": 0.0, "lr_field": 0.0},
                                              run={"val_every": 100, "ckpt_every": 100})
    first = tmp_path / "a.pt"
    train(cfg, tiny_data, first, progress=False)
    # With zero learning rates, a run started from `first` keeps its weights (BN statistics aside).
    second = tmp_path / "b.pt"
    train(cfg, tiny_data, second, progress=False, init=first)
    a, b = load_checkpoint(first)[0].state_dict(), load_checkpoint(second)[0].state_dict()
    conv = [k for k in a if k.endswith("weight") and "bn" not in k]
    assert conv and all(torch.equal(a[k], b[k]) for k in conv)
    other = cfg.replace(model={"decoder_widths": [16, 16, 16, 16, 16]})
    with pytest.raises(CheckpointError, match="architecture"):
        train(other, tiny_data, tmp_path / "c.pt", progress=False, init=first)
    with pytest.raises(CheckpointError, match="differs from the config's"):  # resuming it would write bad checkpoints
        train(other.replace(optim={"steps": 4}), tiny_data, first, progress=False, resume=True)


def test_imagenet_weights_initialise_the_encoder(tiny_data, tmp_path):
    """``--imagenet FILE``: a torchvision resnet18 state dict (names kept, ``fc.*`` ignored) sets the
    encoder of a new run; anything else is refused naming the file."""
    from surftrack.cli import main
    from surftrack.model import CheckpointError
    from surftrack.model.config import TrainConfig
    from surftrack.model.resnet_unet import ResNet18Encoder

    torch.manual_seed(5)
    enc = ResNet18Encoder()
    state = {**enc.state_dict(), "fc.weight": torch.zeros(1000, 512), "fc.bias": torch.zeros(1000)}
    torch.save(state, tmp_path / "resnet18.pth")
    cfg = TrainConfig.from_dict(TINY).replace(optim={"steps": 1, "lr_net": 0.0, "lr_field": 0.0},
                                              run={"val_every": 100, "ckpt_every": 100})
    train(cfg, tiny_data, tmp_path / "m.pt", progress=False, imagenet=tmp_path / "resnet18.pth")
    got = load_checkpoint(tmp_path / "m.pt")[0].net.encoder.state_dict()
    assert all(torch.equal(got[k], v) for k, v in enc.state_dict().items() if not k.endswith(("running_mean",
                                                                                               "running_var",
                                                                                               "num_batches_tracked")))
    torch.save({"conv1.weight": torch.zeros(3)}, tmp_path / "bad.pth")
    with pytest.raises(CheckpointError, match="bad.pth"):
        train(cfg, tiny_data, tmp_path / "n.pt", progress=False, imagenet=tmp_path / "bad.pth")
    assert main(["train", "--data", str(tiny_data), "--init", "x.pt", "--imagenet", "y.pth"]) == 2


def test_int8_export_is_small_and_close(tmp_path):
    from surftrack.instruments import load_instrument
    from surftrack.model import save_checkpoint
    from surftrack.model.config import ModelCfg, TrainConfig
    from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D

    lnd = load_instrument("lnd")
    parts = [PartInfo.from_part(i + 1, lnd.name, lnd.parts[n]) for i, n in enumerate(lnd.part_names)]
    torch.manual_seed(0)
    model = SurfSurg6D(parts, ModelCfg(decoder_widths=(32, 32, 16, 16, 16), siren_hidden=32)).eval()
    cfg = TrainConfig.from_dict({"model": {"decoder_widths": [32, 32, 16, 16, 16], "siren_hidden": 32}})
    full = save_checkpoint(tmp_path / "full.pt", model, cfg, step=1)
    q8 = save_checkpoint(tmp_path / "q8.pt", model, cfg, step=1, int8=True)
    assert q8.stat().st_size < 0.3 * full.stat().st_size
    loaded, _, blob = load_checkpoint(q8)
    assert blob["int8"] and all(k.startswith("net.") for k in blob["int8"])
    x, idx = torch.rand(2, 3, 64, 64), torch.tensor([0, 3])
    with torch.no_grad():
        (_, qa), (_, qb) = model(x, idx), loaded(x, idx)
    assert float((qa - qb).norm() / qa.norm()) < 0.02
    pts = torch.rand(50, 3) - 0.5  # the SIREN fields are kept in fp16, not quantised
    with torch.no_grad():
        assert torch.allclose(model.keys(1, pts), loaded.keys(1, pts), atol=2e-2)


def test_validation_holds_out_whole_tissue_groups(tiny_data):
    from types import SimpleNamespace

    from surftrack.data.join import join_datasets
    from surftrack.model.train import _split_instances, tissue_group_size

    card = json.loads((tiny_data / "dataset_card.json").read_text())
    assert tissue_group_size(card) == 3
    joined = tiny_data.parent / "joined"
    join_datasets(joined, [tiny_data, tiny_data])
    assert tissue_group_size(json.loads((joined / "dataset_card.json").read_text())) == 3
    assert tissue_group_size({"objects": {}}) == 1  # not ours: no grouping known
    # sources that disagree: groups of their least common multiple (whole groups of each); nested joins
    ours = [{"config": {"tissue": {"images_per_tissue": n}}} for n in (10, 4)]
    assert tissue_group_size({"joined": [], "sources": ours}) == 20
    assert tissue_group_size({"joined": [], "sources": [{"joined": [], "sources": ours}, ours[0]]}) == 20
    # 3 scenes of 100 images, 2 instances each, tissue groups of 10
    bop = SimpleNamespace(instances=[SimpleNamespace(scene_id=s, im_id=i) for s in range(3) for i in range(100)
                                     for _ in range(2)])
    train_idx, val_idx = _split_instances(bop, 24, seed=0, group_size=10)
    val = {(bop.instances[i].scene_id, bop.instances[i].im_id) for i in val_idx}
    train = {(bop.instances[i].scene_id, bop.instances[i].im_id) for i in train_idx}
    assert len(val) == 30 and not val & train and len(train_idx) + len(val_idx) == 600
    assert {(s, i // 10) for s, i in val}.isdisjoint({(s, i // 10) for s, i in train})
    # fewer than 10 groups: single images
    _, val_idx = _split_instances(bop, 24, seed=0, group_size=50)
    assert len({(bop.instances[i].scene_id, bop.instances[i].im_id) for i in val_idx}) == 24


def test_loader_workers_give_the_in_process_batches(tiny_data):
    """The training loader's workers (their own GL context, OpenCV on one thread) produce exactly
    the crops and rendered targets of the in-process loader: items depend on (seed, epoch, index) only."""
    from surftrack.data import BopDataset, CropDataset
    from surftrack.model.train import _loader

    ds = CropDataset(BopDataset(tiny_data, min_visib_fract=0.1), crop_size=64, jitter=0.1, seed=5)
    first = [next(iter(_loader(ds, 4, w, 0, True))) for w in (0, 1)]
    for key in ("image", "coord_norm", "mask_amodal", "index"):
        assert torch.equal(first[0][key], first[1][key]), key


def test_cli_train_workers(tiny_data, tmp_path):
    """`surftrack train --workers N` overrides the config's loader processes (checked; one worker
    trains here), so a GPU user sets them without copying the config."""
    import yaml

    from surftrack.cli import main

    cfg = {**TINY, "optim": {**TINY["optim"], "steps": 2}, "run": {**TINY["run"], "val_every": 100}}
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    args = ["train", "--config", str(tmp_path / "tiny.yaml"), "--data", str(tiny_data), "--quiet", "--device", "cpu"]
    assert main(args + ["--out", str(tmp_path / "w.pt"), "--workers", "-1"]) == 2
    assert main(args + ["--out", str(tmp_path / "w.pt"), "--workers", "1"]) == 0
    assert load_checkpoint(tmp_path / "w.pt")[2]["step"] == 2

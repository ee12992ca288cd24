"""Training throughput: images/s of real training steps (data loading, target rendering, forward,
losses, backward, Adam), of the network alone on random tensors and of the data loader alone, so that
the slower of the two halves shows.

    python pipelines/bench_train.py [--config lite] [--data DIR] [--steps 20] [--device cpu|cuda]
                                    [--workers N]

Without --data it first generates a small dataset (24 images, LND) into a temporary folder; give a
dataset of a few hundred images or more with many workers, else the loader's start-up dominates. The
training step is reported over the whole run and after its first logged steps (the workers' start-up,
which starts them, sends each the dataset and makes a GL context in each, left out).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import torch

from surftrack.model import load_train_config
from surftrack.model.train import train


def network_only(cfg, device: torch.device, steps: int) -> float:
    """Images/s of forward + backward + Adam of the U-Net alone (random inputs, 4 parts)."""
    from surftrack.model.resnet_unet import ResNetUNet

    net = ResNetUNet(4, cfg.model.emb_dim, tuple(cfg.model.decoder_widths)).to(device)
    opt = torch.optim.Adam(net.parameters(), 3e-4)
    B, S = cfg.optim.batch, cfg.data.crop
    x = torch.randn(B, 3, S, S, device=device)
    part = torch.arange(B, device=device) % 4
    amp = device.type == "cuda" and cfg.run.amp  # as the full training step does
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    if device.type == "cuda":
        net = net.to(memory_format=torch.channels_last)
        x = x.contiguous(memory_format=torch.channels_last)
    for i in range(steps + 3):
        if i == 3:
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t0 = time.perf_counter()
        with torch.autocast(device.type, enabled=amp):
            m, q = net(x, part)
            loss = m.float().mean() + q.float().square().mean()
        opt.zero_grad()
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return steps * B / (time.perf_counter() - t0)


def crop_dataset(cfg, data: Path):
    """The training crops of ``data`` as :func:`~surftrack.model.train.train` makes them."""
    from surftrack.data import BopDataset
    from surftrack.model.train import training_crops

    bop = BopDataset(data, min_visib_fract=cfg.data.min_visib_fract)
    return training_crops(cfg, bop, sorted(bop.models), cfg.run.seed)


#: The stages of one training crop, by the function that does each (cumulative profile times).
ITEM_STAGES = {"read rgb": "load_rgb", "read mask": "load_mask_visib", "render targets": "render",
               "augment": "augment", "normalise": "normalise_image"}


def item_breakdown(cfg, data: Path, n: int) -> tuple[float, dict[str, float]]:
    """(ms per crop, ms per crop of each of :data:`ITEM_STAGES`) in this process, one core: compared with
    the loader's rate over its workers, it shows whether the workers slow each other down."""
    import cProfile
    import pstats

    ds = crop_dataset(cfg, data)
    ds[0]  # the GL context and the meshes' upload stay out of the figures
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    for i in range(1, n + 1):
        ds[i % len(ds)]
    prof.disable()
    total = (time.perf_counter() - t0) * 1e3 / n
    stats = pstats.Stats(prof).stats  # (file, line, name) -> (calls, prim, tottime, cumtime, callers)
    files = {"render": "targets.py", "augment": "augment.py"}
    stages = {}
    for label, fn in ITEM_STAGES.items():
        cum = [v[3] for (f, _, name), v in stats.items() if name == fn and f.endswith(files.get(fn, ".py"))]
        stages[label] = (max(cum) if cum else 0.0) * 1e3 / n
    return total, stages


def loader_only(cfg, data: Path, batches: int) -> tuple[float, float]:
    """(start-up s, images/s after the first batch) of the training data loader alone: the crops, targets
    and augmentation :func:`~surftrack.model.train.train` feeds the network, with its workers."""
    from surftrack.model.train import _loader

    ds = crop_dataset(cfg, data)
    t0 = time.perf_counter()
    n, t1 = 0, None
    for i, b in enumerate(_loader(ds, cfg.optim.batch, cfg.run.workers, cfg.run.seed, True)):
        if t1 is None:
            t1 = time.perf_counter()
        else:
            n += b["image"].shape[0]
        if i == batches:
            break
    return t1 - t0, n / max(time.perf_counter() - t1, 1e-9)


def steady_rate(rows: list[dict], batch: int) -> float | None:
    """Images/s between the first and the last logged training rows (their images/s are cumulative)."""
    tr = [r for r in rows if r["kind"] == "train"]
    if len(tr) < 2:
        return None
    t = [r["step"] * batch / r["images_per_s"] for r in (tr[0], tr[-1])]
    return (tr[-1]["step"] - tr[0]["step"]) * batch / max(t[1] - t[0], 1e-9)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="lite")
    ap.add_argument("--data")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--workers", type=int, help="data loader workers (default: from the config)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = ap.parse_args()
    cfg = load_train_config(args.config)
    if args.workers is not None:
        cfg = cfg.replace(run={"workers": args.workers})
    # no validation images: validation runs the pose solver on the CPU, which is not what is timed here
    cfg = cfg.replace(run={"val_every": 10**9, "val_images": 0, "ckpt_every": 10**9, "log_every": 5})
    device = torch.device(args.device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {os.cpu_count()} cores"
    print(f"config {args.config}: crop {cfg.data.crop}, batch {cfg.optim.batch}, decoders "
          f"{list(cfg.model.decoder_widths)} | device {name} | torch {torch.__version__}")
    print(f"network alone: {network_only(cfg, device, max(5, args.steps // 2)):.1f} images/s")
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            from surftrack.synth.config import load_synth_config
            from surftrack.synth.generate import generate_dataset

            data = Path(tmp) / "data"
            generate_dataset(data, load_synth_config(), 24, seed=0, workers=1, progress=False)
        per, stages = item_breakdown(cfg, Path(data), 40)
        print(f"one crop in this process: {per:.1f} ms (" + ", ".join(f"{k} {v:.1f}" for k, v in stages.items())
              + f" ms): {1e3 / per:.1f} images/s per worker")
        start, rate = loader_only(cfg, Path(data), max(5, args.steps // 2))
        print(f"data loader alone ({cfg.run.workers} workers): {rate:.1f} images/s after a {start:.1f} s start")
        out = Path(tmp) / "bench.pt"
        s = train(cfg.replace(optim={"steps": args.steps}), data, out, device=args.device, progress=False)
        rows = [json.loads(line) for line in (Path(tmp) / "bench.metrics.jsonl").read_text().splitlines()]
        steady = steady_rate(rows, cfg.optim.batch)
    print(f"full training step: {s['images_per_s']:.1f} images/s over {s['steps']} steps"
          + (f", {steady:.1f} after the first {cfg.run.log_every}" if steady else ""))


if __name__ == "__main__":
    main()

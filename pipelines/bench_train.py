"""Training throughput: images/s of real training steps (data loading, target rendering, forward,
losses, backward, Adam) and of the network alone on random tensors.

    python pipelines/bench_train.py [--config lite] [--data DIR] [--steps 20] [--device cpu|cuda]

Without --data it first generates a small dataset (24 images, LND) into a temporary folder.
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
    cfg = cfg.replace(run={"val_every": 10**9, "ckpt_every": 10**9, "log_every": 5})
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
        out = Path(tmp) / "bench.pt"
        s = train(cfg.replace(optim={"steps": args.steps}), data, out, device=args.device, progress=False)
        rows = [json.loads(line) for line in (Path(tmp) / "bench.metrics.jsonl").read_text().splitlines()]
        rates = [r["images_per_s"] for r in rows if r["kind"] == "train"]
    print(f"full training step: {s['images_per_s']:.1f} images/s over {s['steps']} steps "
          f"(last logged {rates[-1]:.1f} images/s)")


if __name__ == "__main__":
    main()

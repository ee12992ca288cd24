"""Training SurfSurg6D: data, the step (mask BCE + penNCE + consistency), validation, checkpoints.

``surftrack train --config lite --data DIR --out model.pt [--steps N] [--resume]``. Multi-GPU: launch
with ``torchrun --nproc_per_node G -m surftrack.cli train ...`` (DDP; rank 0 logs and saves).
"""

from __future__ import annotations

import json
import math
import os
import pickle
import random
import time
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import torch

from surftrack.geometry import rotation_angle_deg
from surftrack.model import losses
from surftrack.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from surftrack.model.config import TrainConfig, TrainConfigError, lr_factor
from surftrack.model.resnet_unet import load_imagenet_weights
from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D, surface_bank

BANK_SIZE = 20000


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _dist(device: str | None) -> tuple[int, int, torch.device]:
    """(rank, world size, this process's device), initialising torch.distributed when launched by
    torchrun: NCCL on CUDA (one GPU per process, ``LOCAL_RANK``), gloo on the CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if world == 1:
        return 0, 1, dev
    if dev.type == "cuda":
        dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(dev)
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    return torch.distributed.get_rank(), world, dev


class LossForward(torch.nn.Module):
    """Everything a training step asks of the model in one ``forward``: mask logits and queries of the
    crops, and keys of 3D points (``pts[b]`` on the surface of part ``part[b]``). DDP all-reduces the
    gradients of the parameters a forward used, so the SIREN fields must be called inside it too; the
    decoders and fields of parts absent from a batch are unused (``find_unused_parameters``)."""

    def __init__(self, model: SurfSurg6D, amp: bool = False):
        super().__init__()
        self.model, self.amp = model, amp

    def forward(self, img: torch.Tensor, part: torch.Tensor, pts: torch.Tensor):
        with torch.autocast(img.device.type, enabled=self.amp):
            mask_logit, query = self.model(img, part)
        keys = torch.empty((*pts.shape[:2], query.shape[1]), device=pts.device)
        for p in torch.unique(part).tolist():
            sel = (part == p).nonzero(as_tuple=True)[0]
            keys[sel] = self.model.keys(p, pts[sel].reshape(-1, 3)).view(len(sel), pts.shape[1], -1)
        return mask_logit.float(), query.float(), keys


class Trainer:
    """Holds the model, the surface banks and the optimiser; :meth:`step` runs one training step
    (through ``module``, a DDP wrapper of :attr:`forward`, when given)."""

    def __init__(self, model: SurfSurg6D, cfg: TrainConfig, device: torch.device):
        if device.type == "cuda":  # the crops are channels-last too (fresh, initialised or resumed alike)
            model = model.to(memory_format=torch.channels_last)
        self.model, self.cfg, self.device = model, cfg, device
        banks = [surface_bank(p, BANK_SIZE, seed=i) for i, p in enumerate(model.parts)]
        self.bank = torch.stack([torch.from_numpy(b[0]) for b in banks]).to(device)  # (P, BANK, 3)
        o = cfg.optim
        self.optimizer = torch.optim.Adam([
            {"params": model.net.parameters(), "lr": o.lr_net},
            {"params": model.fields.parameters(), "lr": o.lr_field},
        ])
        self.amp = cfg.run.amp and device.type == "cuda"
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp)
        self.forward = LossForward(model, self.amp)

    def losses(self, batch: dict, gen: torch.Generator | None = None, module: torch.nn.Module | None = None) -> dict:
        """Loss components for a batch (see :func:`surftrack.model.losses.surfsurg6d_loss`)."""
        cfg = self.cfg.loss
        img = batch["image"].to(self.device, non_blocking=True)
        if self.device.type == "cuda":
            img = img.contiguous(memory_format=torch.channels_last)
        part = batch["part_index"].to(self.device)
        mask_t = batch["mask_train"].to(self.device)
        valid = batch["coord_valid"].to(self.device) & (mask_t > 0.5)
        coord = batch["coord_norm"].to(self.device)
        B = img.shape[0]
        # Queries: n_pos pixels per crop from the training mask (with replacement when it is small).
        w = valid.view(B, -1).float()
        empty = w.sum(1) == 0  # e.g. an occluder over all of a thin part's visible pixels (modal masks)
        w[empty] = 1.0  # keeps multinomial defined; these crops' queries are left out of the NCE below
        idx = torch.multinomial(w, cfg.n_pos, replacement=True, generator=gen)        # (B, N)
        c_q = coord.view(B, -1, 3).gather(1, idx[..., None].expand(-1, -1, 3))
        neg_idx = torch.randint(0, self.bank.shape[1], (B, cfg.n_neg), device=self.device, generator=gen)
        c_neg = self.bank[part[:, None], neg_idx]                                       # (B, M, 3)
        noise = torch.randn((B, cfg.n_pos + cfg.n_neg, 3), device=self.device, generator=gen) * cfg.key_noise
        pts = torch.cat([c_q, c_neg], dim=1) + noise
        mask_logit, query, keys = (module if module is not None else self.forward)(img, part, pts)
        q = query.flatten(2).transpose(1, 2).gather(1, idx[..., None].expand(-1, -1, query.shape[1]))
        k_pos, k_neg = keys[:, : cfg.n_pos], keys[:, cfg.n_pos:]
        keep = ~empty if bool((~empty).any()) else torch.ones_like(empty)  # all empty: keep the batch defined
        q, k_pos, k_neg, c_q, c_neg = (x[keep] for x in (q, k_pos, k_neg, c_q, c_neg))
        out = losses.surfsurg6d_loss(
            mask_logit, mask_t, q, k_pos, k_neg, c_q, c_neg, key_coords=c_neg, key_emb=k_neg,
            alpha=cfg.alpha, beta=cfg.beta, lam=cfg.lam, m=cfg.m, pen_floor=cfg.pen_floor)
        out["empty_masks"] = empty.sum().float()
        return out

    def set_lr(self, factor: float) -> None:
        """Scale the configured learning rates (network, fields) by ``factor``."""
        o = self.cfg.optim
        for group, base in zip(self.optimizer.param_groups, (o.lr_net, o.lr_field)):
            group["lr"] = base * factor

    def step(self, batch: dict, module: torch.nn.Module | None = None) -> dict[str, float]:
        self.model.train()
        self.optimizer.zero_grad(set_to_none=True)
        out = self.losses(batch, module=module)
        self.scaler.scale(out["total"]).backward()
        self.scaler.unscale_(self.optimizer)
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), 10.0)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        logs = {k: float(v.detach()) for k, v in out.items()}
        logs["grad_norm"] = float(grad_norm)
        return logs


@torch.no_grad()
def quick_pose_eval(model: SurfSurg6D, batch: dict, bank: torch.Tensor, device: torch.device,
                    max_queries: int = 600, n_keys: int = 4000) -> list[dict]:
    """A fast pose check for validation: per crop, argmax correspondences of predicted-mask pixels
    against surface keys, then RANSAC-PnP; returns RE (deg), TE (mm) and ADD (mm) per crop."""
    model.eval()
    img, part = batch["image"].to(device), batch["part_index"].to(device)
    mask_logit, query = model(img, part)
    out = []
    for b in range(img.shape[0]):
        p = int(part[b])
        info = model.parts[p]
        m = torch.sigmoid(mask_logit[b]) > 0.5
        ys, xs = torch.nonzero(m, as_tuple=True)
        res = {"re": 180.0, "te": 1e3, "add": 1e3, "part": p}
        if len(xs) >= 6:
            gen = torch.Generator(device=device).manual_seed(b)  # leaves the training random stream alone
            sel = torch.randperm(len(xs), device=device, generator=gen)[:max_queries]
            ys, xs = ys[sel], xs[sel]
            qv = query[b][:, ys, xs].T                                   # (Q, E)
            kc = bank[p, :n_keys]
            keys = model.keys(p, kc)
            best = (qv @ keys.T).argmax(1)
            obj = (kc[best].cpu().numpy() * info.radius + info.center).astype(np.float64)
            uv = torch.stack([xs, ys], 1).cpu().numpy().astype(np.float64)
            K = batch["K"][b].numpy().astype(np.float64)
            ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, uv, K, None, reprojectionError=3.0, iterationsCount=200,
                                                     flags=cv2.SOLVEPNP_EPNP)
            if ok and np.isfinite(rvec).all() and np.isfinite(tvec).all():
                R = cv2.Rodrigues(rvec)[0]
                t = tvec.ravel()
                Rg, tg = batch["R"][b].numpy().astype(np.float64), batch["t"][b].numpy().astype(np.float64)
                pts = info.vertices
                add = np.linalg.norm((pts @ R.T + t) - (pts @ Rg.T + tg), axis=1).mean()
                res = {"re": float(rotation_angle_deg(R, Rg)), "te": float(np.linalg.norm(t - tg)),
                       "add": float(add), "part": p}
        diam = float(np.linalg.norm(info.vertices.max(0) - info.vertices.min(0)))
        res["add10"] = res["add"] < 0.1 * diam
        out.append(res)
    return out


def plot_curves(metrics_path: Path, png_path: Path) -> None:
    """Training and validation curves from the JSON-lines log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [json.loads(line) for line in metrics_path.read_text().splitlines() if line.strip()]
    train = [r for r in rows if r["kind"] == "train"]
    val = [r for r in rows if r["kind"] == "val"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for key in ("total", "nce", "mask", "con"):
        if train and key in train[0]:
            axes[0].plot([r["step"] for r in train], [r[key] for r in train], label=key)
    axes[0].set_yscale("log"); axes[0].set_xlabel("step"); axes[0].set_title("training loss"); axes[0].legend()
    if val:
        axes[1].plot([r["step"] for r in val], [r["total"] for r in val], "o-", label="val total")
        axes[1].set_xlabel("step"); axes[1].set_title("validation loss"); axes[1].legend()
        axes[2].plot([r["step"] for r in val], [r["re_median"] for r in val], "o-", label="RE median (deg)")
        axes[2].plot([r["step"] for r in val], [100 * r["add10"] for r in val], "s-", label="ADD-10 (%)")
        axes[2].set_xlabel("step"); axes[2].set_title("quick pose check"); axes[2].legend()
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)


def tissue_group_size(card: Mapping) -> int:
    """How many consecutive images (by im_id within a scene) share one tissue group (the same patch and
    base pose) in the dataset of this ``dataset_card.json``: ``surftrack synth``'s
    ``tissue.images_per_tissue``; for a joined dataset, the least common multiple of its sources' (a group
    of that size is a union of whole groups of every source); 1 when unknown (other BOP data)."""
    if "joined" in card:
        sizes = [tissue_group_size(c) for c in card.get("sources") or []]
        return math.lcm(*sizes) if sizes else 1
    try:
        return max(int(card["config"]["tissue"]["images_per_tissue"]), 1)
    except (KeyError, TypeError, ValueError):
        return 1


def validation_split(bop, data_dir: str | Path, cfg: TrainConfig) -> tuple[list[int], list[int]]:
    """(training, validation) instance indices of ``bop`` (the dataset at ``data_dir``) as :func:`train`
    splits them: about ``cfg.run.val_images`` images drawn with ``cfg.run.seed``, whole tissue groups of
    our generated data (:func:`tissue_group_size`)."""
    card_path = Path(data_dir) / "dataset_card.json"
    card = json.loads(card_path.read_text()) if card_path.is_file() else {}
    return _split_instances(bop, cfg.run.val_images, cfg.run.seed, tissue_group_size(card))


def _split_instances(bop, val_images: int, seed: int, group_size: int = 1) -> tuple[list[int], list[int]]:
    """Hold out whole images (every instance of them): about ``val_images`` images, drawn with ``seed``.
    With ``group_size`` > 1 (images ``k * group_size ...`` of a scene share a tissue patch: our generated
    data), whole groups are held out, so that no held-out image shares its tissue with a training image;
    when there are fewer than 10 groups, single images are (holding out one group would take too much)."""
    images = sorted({(r.scene_id, r.im_id) for r in bop.instances})
    rng = np.random.default_rng(seed)
    n_val = min(val_images, max(1, len(images) // 10)) if len(images) > 1 else 0
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for s, im in images:
        groups.setdefault((s, im // max(int(group_size), 1)), []).append((s, im))
    units = list(groups.values()) if len(groups) >= 10 else [[k] for k in images]
    val_set: set[tuple[int, int]] = set()
    for u in rng.permutation(len(units)) if n_val else []:
        if len(val_set) >= n_val:
            break
        val_set.update(units[u])
    train_idx = [i for i, r in enumerate(bop.instances) if (r.scene_id, r.im_id) not in val_set]
    val_idx = [i for i, r in enumerate(bop.instances) if (r.scene_id, r.im_id) in val_set]
    return train_idx, val_idx


def training_crops(cfg: TrainConfig, bop, obj_ids: list[int], seed: int, validation: bool = False):
    """The :class:`~surftrack.data.CropDataset` of ``bop`` (a BopDataset) that :func:`train` feeds the
    network: crops of ``cfg.data``, jittered, rotated and augmented; with ``validation``, centred and plain.
    With ``cfg.data.canonical_twin``, near-symmetric instruments are labelled as one of their roll twins
    (:mod:`surftrack.data.twin_labels`; the objects' instruments and parts from ``dataset_card.json``)."""
    from surftrack.data import CropDataset
    from surftrack.data.twin_labels import twin_labels

    twins = None
    if cfg.data.canonical_twin:
        card = bop.root / "dataset_card.json"
        objects = json.loads(card.read_text()).get("objects", {}) if card.is_file() else {}
        twins = twin_labels({o: (objects.get(str(o), {}).get("instrument", ""), bop.models[o].name) for o in obj_ids})
    common = dict(obj_ids=obj_ids, crop_size=cfg.data.crop, scale=cfg.data.scale, mask_mode=cfg.data.mask_mode,
                  seed=seed, twins=twins)
    if validation:
        return CropDataset(bop, jitter=0.0, augment=None, **common)
    return CropDataset(bop, jitter=cfg.data.jitter, max_rotation_deg=cfg.data.max_rotation_deg,
                       augment=cfg.data.augment, **common)


def _init_loader_worker(_worker_id: int) -> None:
    # One worker per core already: OpenCV's own thread pool in each of them (torch's is set to one thread
    # by the DataLoader) would oversubscribe the machine N-fold.
    cv2.setNumThreads(1)


#: What the loader's workers import (surftrack.data: the crops, targets, augmentation), imported once by the
#: fork server they are forked from.
LOADER_PRELOAD = ("torch", "cv2", "surftrack.data", "surftrack.model.train")


def _loader(ds, batch: int, workers: int, seed: int, shuffle: bool, rank: int = 0, world: int = 1, sampler=None,
            pin_memory: bool = False):
    from surftrack.render import worker_context

    if sampler is None and world > 1:
        sampler = torch.utils.data.distributed.DistributedSampler(ds, world, rank, shuffle=shuffle, seed=seed)
    g = torch.Generator().manual_seed(seed)
    # Target rendering needs GL, which needs workers not forked from this process (worker_context: forked
    # from a fork server that imported what they need); workers are not persistent so that each epoch's
    # CropDataset.set_epoch reaches them.
    return torch.utils.data.DataLoader(
        ds, batch_size=batch, shuffle=shuffle and sampler is None, sampler=sampler, drop_last=shuffle,
        num_workers=workers, generator=g, persistent_workers=False, pin_memory=pin_memory,
        worker_init_fn=_init_loader_worker if workers > 0 else None,
        multiprocessing_context=worker_context(LOADER_PRELOAD) if workers > 0 else None)


def _subset(ds, bop_indices: list[int]):
    keep = set(bop_indices)
    return torch.utils.data.Subset(ds, [pos for pos, k in enumerate(ds.items) if k in keep])


def train(cfg: TrainConfig, data_dir: str | Path, out: str | Path, steps: int | None = None, resume: bool = False,
          device: str | None = None, progress: bool = True, log_dir: str | Path | None = None,
          init: str | Path | None = None, imagenet: str | Path | None = None) -> dict:
    """Train on the BOP dataset ``data_dir``; writes ``out`` (checkpoint), and next to it
    ``<out stem>.metrics.jsonl``, ``<out stem>.curves.png`` and ``<out stem>.fp16.pt``. Returns a summary.
    ``init`` starts a new run from another checkpoint's weights (same parts and architecture; fresh optimiser,
    step 0), e.g. to fine-tune a model on more data. ``imagenet``: a torchvision ``resnet18`` state-dict
    file whose weights initialise the encoder of a new run (as in the paper; nothing is downloaded)."""
    from tqdm import tqdm

    from surftrack.data import BopDataset, MixedSampler, mixed_dataset

    rank, world, dev = _dist(device)
    out = Path(out)
    log_dir = Path(log_dir) if log_dir else out.parent
    metrics_path = log_dir / f"{out.stem}.metrics.jsonl"
    total_steps = steps if steps is not None else cfg.optim.steps
    seed_everything(cfg.run.seed + rank)

    bop = BopDataset(data_dir, min_visib_fract=cfg.data.min_visib_fract)
    obj_ids = sorted(bop.models)
    card = Path(data_dir) / "dataset_card.json"
    names = json.loads(card.read_text()).get("objects", {}) if card.is_file() else {}
    parts = [PartInfo.from_part(o, names.get(str(o), {}).get("instrument", "unknown"), bop.models[o]) for o in obj_ids]
    train_idx, val_idx = validation_split(bop, data_dir, cfg)
    syn_ds = training_crops(cfg, bop, obj_ids, cfg.run.seed)
    epoch_datasets = [syn_ds]
    train_ds = _subset(syn_ds, train_idx)
    sampler = None
    if cfg.data.real_data:
        if world > 1:
            raise TrainConfigError("mixing data.real_data into batches is not supported with several processes yet "
                                   "(the mixed sampler is not split by rank)")
        real_bop = BopDataset(cfg.data.real_data, min_visib_fract=cfg.data.min_visib_fract)
        if not real_bop.models or any(o not in bop.models or not bop.models[o].same_geometry(m.mesh.vertices, m.mesh.faces)
                                      for o, m in real_bop.models.items()):
            raise TrainConfigError(f"{cfg.data.real_data}: its models differ from those of {data_dir}")
        real_ds = training_crops(cfg, real_bop, obj_ids, cfg.run.seed + 1)
        epoch_datasets.append(real_ds)
        sampler = MixedSampler(len(train_ds), len(real_ds), cfg.optim.batch, tuple(cfg.data.syn_real_ratio),
                               seed=cfg.run.seed)
        train_ds = mixed_dataset(train_ds, real_ds)
    val_ds = _subset(training_crops(cfg, bop, obj_ids, cfg.run.seed, validation=True), val_idx) if val_idx else None

    start, start_epoch = 0, 0
    if resume and out.is_file():
        model, _, blob = load_checkpoint(out, dev)
        if [p.mesh_sha256 for p in model.parts] != [p.mesh_sha256 for p in parts]:
            raise CheckpointError(f"{out}: checkpoint parts do not match the dataset's models; cannot resume")
        if model.cfg != cfg.model:
            raise CheckpointError(f"{out}: its model ({model.cfg}) differs from the config's ({cfg.model}); resume "
                                  f"with the config it was trained with, or start afresh with --init")
        trainer = Trainer(model, cfg, dev)
        if blob.get("optimizer"):
            trainer.optimizer.load_state_dict(blob["optimizer"])
            _match_state_layout(trainer.optimizer)
        start = int(blob["step"])
        extra = blob.get("extra", {})
        if world == 1 and "torch_rng" in extra:  # the stream continues where the checkpoint left it
            torch.set_rng_state(extra["torch_rng"])
            if dev.type == "cuda" and "cuda_rng" in extra:
                torch.cuda.set_rng_state(extra["cuda_rng"], dev)
        else:  # only rank 0's state is saved: a fresh stream per rank, not step 0's again
            seed_everything(cfg.run.seed + rank + 100_003 * start)
        if extra.get("scaler"):
            trainer.scaler.load_state_dict(extra["scaler"])
        start_epoch = int(extra.get("epoch", 0))
        if rank == 0 and metrics_path.exists():  # rows logged after the checkpoint would repeat steps
            rows = [line for line in metrics_path.read_text().splitlines()
                    if line.strip() and json.loads(line)["step"] <= start]
            metrics_path.write_text("".join(r + "\n" for r in rows))
    else:
        model = SurfSurg6D(parts, cfg.model).to(dev)
        if imagenet is not None:
            try:
                missing = load_imagenet_weights(model.net.encoder, imagenet)
            except (OSError, RuntimeError, pickle.UnpicklingError) as e:
                raise CheckpointError(f"{imagenet}: cannot load ImageNet weights: {str(e).splitlines()[0]}") from None
            except ValueError as e:
                raise CheckpointError(str(e)) from None
            if missing:
                raise CheckpointError(f"{imagenet}: not a resnet18 state dict (missing {missing[:3]})")
        if init is not None:
            src, _, _ = load_checkpoint(init, dev)
            if [p.mesh_sha256 for p in src.parts] != [p.mesh_sha256 for p in parts]:
                raise CheckpointError(f"{init}: its parts do not match the dataset's models; cannot start from it")
            try:
                model.load_state_dict(src.state_dict())
            except RuntimeError as e:
                raise CheckpointError(f"{init}: its architecture differs from the config's model: "
                                      f"{str(e).splitlines()[0]}") from None
            del src
        trainer = Trainer(model, cfg, dev)
        if rank == 0 and metrics_path.exists():
            metrics_path.unlink()
    module = None
    if world > 1:
        module = torch.nn.parallel.DistributedDataParallel(
            trainer.forward, device_ids=[dev.index] if dev.type == "cuda" else None, find_unused_parameters=True)

    loader = _loader(train_ds, cfg.optim.batch, cfg.run.workers, cfg.run.seed + start, True, rank, world, sampler,
                     pin_memory=dev.type == "cuda")
    val_loader = _loader(val_ds, cfg.optim.batch, 0, cfg.run.seed, False) if val_ds is not None else None

    def log(row: dict) -> None:
        if rank == 0:
            metrics_path.parent.mkdir(parents=True, exist_ok=True)
            with metrics_path.open("a") as f:
                f.write(json.dumps(row) + "\n")

    def save(step: int) -> None:
        if rank == 0:
            rng = {"torch_rng": torch.get_rng_state()}
            if dev.type == "cuda":
                rng["cuda_rng"] = torch.cuda.get_rng_state(dev)
            save_checkpoint(out, model, cfg, step, trainer.optimizer, extra={
                **rng, "epoch": epoch, "scaler": trainer.scaler.state_dict()})

    step, t0, seen = start, time.perf_counter(), 0
    bar = tqdm(total=total_steps, initial=start, desc="train", unit="step", disable=not progress or rank > 0)
    epoch = start_epoch
    last_val: dict = {}
    try:
        while step < total_steps:
            if hasattr(loader.sampler, "set_epoch"):
                loader.sampler.set_epoch(epoch)
            for d in epoch_datasets:
                d.set_epoch(epoch)
            for batch in loader:
                if step >= total_steps:
                    break
                trainer.set_lr(lr_factor(cfg.optim, step, total_steps))
                logs = trainer.step(batch, module)
                step += 1
                seen += batch["image"].shape[0] * world
                bar.update(1)
                if step % cfg.run.log_every == 0 or step == total_steps:
                    rate = seen / (time.perf_counter() - t0)
                    log({"kind": "train", "step": step, "images_per_s": rate, **logs})
                    bar.set_postfix(loss=f"{logs['total']:.3f}", img_s=f"{rate:.1f}")
                if val_loader is not None and (step % cfg.run.val_every == 0 or step == total_steps):
                    if rank == 0:  # the others wait in the barrier (or the next step's all-reduce)
                        last_val = validate(trainer, val_loader)
                        log({"kind": "val", "step": step, **last_val})
                        plot_curves(metrics_path, log_dir / f"{out.stem}.curves.png")
                    if world > 1:
                        torch.distributed.barrier()
                if step % cfg.run.ckpt_every == 0:
                    save(step)
            epoch += 1
    finally:
        bar.close()
        if step > start:
            save(step)
    if rank == 0:
        save_checkpoint(out.with_suffix(".fp16.pt"), model, cfg, step, half=True)
    if world > 1:
        _check_ranks_agree(model, rank)
    return {"steps": step, "images_per_s": seen / max(time.perf_counter() - t0, 1e-9), "val": last_val,
            "checkpoint": str(out), "metrics": str(metrics_path), "rank": rank}


def _match_state_layout(optimizer: torch.optim.Optimizer) -> None:
    """Give the loaded Adam moments the memory layout of their parameters (channels-last on CUDA), which
    ``load_state_dict`` does not keep; mixed layouts push the fused update onto a slower path."""
    for group in optimizer.param_groups:
        for p in group["params"]:
            for k, v in optimizer.state.get(p, {}).items():
                if torch.is_tensor(v) and v.shape == p.shape and v.stride() != p.stride():
                    optimizer.state[p][k] = torch.empty_like(p).copy_(v)


def _check_ranks_agree(model: torch.nn.Module, rank: int) -> None:
    """Raise when the DDP processes ended with different weights: some gradient was not all-reduced
    (a parameter used outside :class:`LossForward`), and the checkpoint of rank 0 is not the run's model."""
    vec = torch.cat([p.detach().reshape(-1).double() for p in model.parameters()])
    ramp = torch.linspace(0.0, 1.0, len(vec), dtype=torch.float64, device=vec.device)
    sig = torch.stack([vec.sum(), vec.square().sum(), (vec * ramp).sum()])
    every = [torch.empty_like(sig) for _ in range(torch.distributed.get_world_size())]
    torch.distributed.all_gather(every, sig)
    if not all(torch.allclose(s, every[0], rtol=1e-9, atol=0.0) for s in every):
        raise RuntimeError(f"rank {rank}: the training processes ended with different weights")


@torch.no_grad()
def validate(trainer: Trainer, loader) -> dict:
    """Mean losses and the quick pose check over the held-out crops."""
    model = trainer.model
    model.eval()
    gen = torch.Generator(device=trainer.device).manual_seed(0)
    sums: dict[str, float] = {}
    n = 0
    poses: list[dict] = []
    for batch in loader:
        out = trainer.losses(batch, gen=gen)
        for k, v in out.items():
            sums[k] = sums.get(k, 0.0) + float(v) * batch["image"].shape[0]
        n += batch["image"].shape[0]
        poses += quick_pose_eval(model, batch, trainer.bank, trainer.device)
    res = {k: v / max(n, 1) for k, v in sums.items()}
    if poses:
        res["re_median"] = float(np.median([p["re"] for p in poses]))
        res["te_median"] = float(np.median([p["te"] for p in poses]))
        res["add10"] = float(np.mean([p["add10"] for p in poses]))
        res["val_crops"] = len(poses)
    return res

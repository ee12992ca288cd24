"""One checkpoint file holds everything inference needs: weights, the training config, the part
identities (ids, names, meshes, mesh hashes, normalisation) and, for resuming, the optimiser state."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from surftrack import __version__
from surftrack.model.config import TrainConfig
from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D

FORMAT = "surftrack-surfsurg6d"


class CheckpointError(ValueError):
    """An unreadable or foreign checkpoint; the message names the file."""


def save_checkpoint(path: str | Path, model: SurfSurg6D, cfg: TrainConfig, step: int,
                    optimizer: torch.optim.Optimizer | None = None, extra: dict[str, Any] | None = None,
                    half: bool = False) -> Path:
    """Write atomically. ``half`` stores floating-point weights as fp16 (inference export)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: (v.half() if half and v.is_floating_point() else v).cpu() for k, v in model.state_dict().items()}
    blob = {
        "format": FORMAT, "version": __version__, "step": step, "config": cfg.to_dict(),
        "parts": [p.to_dict() for p in model.parts], "state_dict": state, "fp16": half,
        "optimizer": optimizer.state_dict() if optimizer is not None and not half else None,
        "extra": extra or {},
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(blob, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> tuple[SurfSurg6D, TrainConfig, dict]:
    """(model in eval mode, its training config, the raw checkpoint dict)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:  # weights_only: a checkpoint holds tensors and plain values, never code
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for corrupt files
        raise CheckpointError(f"{path}: not a readable checkpoint ({e.__class__.__name__}: {e})") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a surftrack SurfSurg6D checkpoint")
    try:
        cfg = TrainConfig.from_dict(blob["config"], str(path))
        model = SurfSurg6D([PartInfo.from_dict(p) for p in blob["parts"]], cfg.model)
        state = {k: v.float() if v.is_floating_point() else v for k, v in blob["state_dict"].items()}
        model.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: inconsistent checkpoint ({e.__class__.__name__}: {e})") from None
    return model.to(device).eval(), cfg, blob

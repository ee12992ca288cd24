"""One checkpoint file holds everything inference needs: weights, the training config, the part
identities (ids, names, meshes, mesh hashes, normalisation) and, for resuming, the optimiser state."""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import torch

from surftrack import __version__
from surftrack.model.config import TrainConfig
from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D

FORMAT = "surftrack-surfsurg6d"


class CheckpointError(ValueError):
    """An unreadable or foreign checkpoint; the message names the file."""


def quantize_int8(w: torch.Tensor) -> dict[str, torch.Tensor]:
    """Symmetric per-output-channel int8 of a weight tensor (dim 0 = output channels): ``q`` int8 and
    ``scale`` fp32 with ``w ~= q * scale``."""
    flat = w.detach().float().reshape(w.shape[0], -1)
    scale = (flat.abs().amax(1) / 127.0).clamp_min(1e-12)
    q = torch.round(flat / scale[:, None]).clamp(-127, 127).to(torch.int8).reshape(w.shape)
    return {"q": q, "scale": scale}


def _export_state(model: SurfSurg6D, half: bool, int8: bool) -> tuple[dict, dict]:
    """(state dict, int8 part). int8: weights of the U-Net's convolutions (>= 2-D tensors of ``net.``)
    quantised per output channel; the SIREN fields stay fp16 (their sine layers amplify weight error by
    omega_0 = 30); everything else fp16."""
    state, q8 = {}, {}
    for k, v in model.state_dict().items():
        v = v.detach().cpu()
        if int8 and k.startswith("net.") and v.is_floating_point() and v.ndim >= 2:
            q8[k] = quantize_int8(v)
        elif (half or int8) and v.is_floating_point():
            state[k] = v.half()
        else:
            state[k] = v
    return state, q8


def save_checkpoint(path: str | Path, model: SurfSurg6D, cfg: TrainConfig, step: int,
                    optimizer: torch.optim.Optimizer | None = None, extra: dict[str, Any] | None = None,
                    half: bool = False, int8: bool = False) -> Path:
    """Write atomically. ``half`` stores floating-point weights as fp16 (inference export); ``int8``
    additionally stores the U-Net's convolution weights as per-channel int8 (about half the fp16 size;
    the bundled default model)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state, q8 = _export_state(model, half, int8)
    export = half or int8
    blob = {
        "format": FORMAT, "version": __version__, "step": step, "config": cfg.to_dict(),
        "parts": [p.to_dict() for p in model.parts], "state_dict": state, "fp16": export, "int8": q8,
        "optimizer": optimizer.state_dict() if optimizer is not None and not export else None,
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
    except pickle.UnpicklingError:  # torch's own message advises loading code from the file: never relay it
        raise CheckpointError(f"{path}: not a surftrack checkpoint (not a file of tensors and plain values, as "
                              f"`surftrack train` writes; surftrack never loads code from a model file)") from None
    except Exception as e:  # torch raises several types for corrupt files
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise CheckpointError(f"{path}: not a readable checkpoint ({e.__class__.__name__}"
                              f"{': ' + first if first else ''})") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a surftrack SurfSurg6D checkpoint")
    try:
        cfg = TrainConfig.from_dict(blob["config"], str(path))
        model = SurfSurg6D([PartInfo.from_dict(p) for p in blob["parts"]], cfg.model)
        state = {k: v.float() if v.is_floating_point() else v for k, v in blob["state_dict"].items()}
        for k, qs in (blob.get("int8") or {}).items():
            shape = (-1,) + (1,) * (qs["q"].ndim - 1)
            state[k] = qs["q"].float() * qs["scale"].float().reshape(shape)
        model.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointError(f"{path}: inconsistent checkpoint ({e.__class__.__name__}: {e})") from None
    return model.to(device).eval(), cfg, blob

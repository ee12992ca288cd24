"""Training configuration: dataclasses with defaults (the paper's), loaded from ``configs/train/*.yaml``."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from surftrack.configio import build_dataclass, read_config_yaml


class TrainConfigError(ValueError):
    """A malformed training configuration; the message names the file and the key."""


@dataclass(frozen=True)
class ModelCfg:
    emb_dim: int = 12
    decoder_widths: tuple[int, ...] = (256, 128, 64, 64, 64)
    single_decoder: bool = False
    siren_hidden: int = 256


@dataclass(frozen=True)
class DataCfg:
    crop: int = 224
    scale: float = 1.2
    jitter: float = 0.1
    max_rotation_deg: float = 0.0
    mask_mode: str = "amodal"
    min_visib_fract: float = 0.1
    augment: dict[str, Any] = field(default_factory=dict)
    real_data: str | None = None     # a second (real) BOP dataset with the same models, mixed into each batch
    # label a near-symmetric instrument as one of its roll twins (shaft x axis away from the camera): both
    # give the same image, so drawn alike they would give one crop two sets of targets (data.twin_labels)
    canonical_twin: bool = True
    syn_real_ratio: tuple[int, int] = (1, 1)  # the paper's syn:real 1:1


@dataclass(frozen=True)
class LossCfg:
    alpha: float = 1.0
    beta: float = 1.0
    lam: float = 10.0
    m: float = 0.01
    pen_floor: float = 0.01
    n_pos: int = 1024
    n_neg: int = 1024
    key_noise: float = 1e-3


@dataclass(frozen=True)
class OptimCfg:
    lr_net: float = 3e-4
    lr_field: float = 3e-5
    batch: int = 20
    steps: int = 13000
    warmup: int = 0
    schedule: str = "constant"   # or "cosine": after warmup, decay to 10 % of each learning rate at the last step


@dataclass(frozen=True)
class RunCfg:
    val_every: int = 500
    val_images: int = 50
    ckpt_every: int = 1000
    log_every: int = 50
    workers: int = 4
    seed: int = 0
    amp: bool = True


@dataclass(frozen=True)
class TrainConfig:
    model: ModelCfg = field(default_factory=ModelCfg)
    data: DataCfg = field(default_factory=DataCfg)
    loss: LossCfg = field(default_factory=LossCfg)
    optim: OptimCfg = field(default_factory=OptimCfg)
    run: RunCfg = field(default_factory=RunCfg)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict, where: str = "config") -> TrainConfig:
        return build_dataclass(cls, data, where, TrainConfigError)

    def replace(self, **sections: dict) -> TrainConfig:
        """A copy with some fields of some sections replaced: ``cfg.replace(optim={"steps": 10})``."""
        d = self.to_dict()
        for k, v in sections.items():
            d[k].update(v)
        return TrainConfig.from_dict(d)


def load_train_config(path: str | Path) -> TrainConfig:
    """Load ``path`` (YAML); a bare name like ``lite`` means ``configs/train/lite.yaml``."""
    p, data = read_config_yaml(path, "train", "training config", TrainConfigError)
    cfg = build_dataclass(TrainConfig, data, str(p), TrainConfigError)
    if cfg.data.mask_mode not in ("amodal", "modal"):
        raise TrainConfigError(f"{p}: data.mask_mode must be 'amodal' or 'modal', got {cfg.data.mask_mode!r}")
    if cfg.optim.schedule not in ("constant", "cosine"):
        raise TrainConfigError(f"{p}: optim.schedule must be 'constant' or 'cosine', got {cfg.optim.schedule!r}")
    return cfg


def lr_factor(optim: OptimCfg, step: int, total_steps: int) -> float:
    """Multiplier of the base learning rates at ``step`` (0-based): linear warm-up over ``optim.warmup``
    steps, then constant or a cosine decay reaching 10 % at ``total_steps``."""
    if optim.warmup > 0 and step < optim.warmup:
        return (step + 1) / optim.warmup
    if optim.schedule == "constant":
        return 1.0
    span = max(total_steps - optim.warmup, 1)
    x = min(max(step - optim.warmup, 0) / span, 1.0)
    return 0.1 + 0.9 * 0.5 * (1.0 + math.cos(math.pi * x))

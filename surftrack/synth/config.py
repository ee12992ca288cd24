"""Synthesis configuration: dataclasses with defaults, loaded from YAML (``configs/synth/*.yaml``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

Range = tuple[float, float]


class ConfigError(ValueError):
    """A malformed synthesis configuration; the message names the file and the key."""


@dataclass(frozen=True)
class ImageCfg:
    width: int = 640
    height: int = 512


@dataclass(frozen=True)
class CameraCfg:
    hfov_deg: Range = (60.0, 80.0)
    principal_jitter: float = 0.02


@dataclass(frozen=True)
class TissueCfg:
    distance_mm: Range = (100.0, 170.0)
    tilt_deg: Range = (0.0, 40.0)
    fold_depth_mm: Range = (6.0, 18.0)
    extent_mm: tuple[float, float] = (400.0, 340.0)
    spacing_mm: float = 3.0
    texel_mm: float = 0.6
    images_per_tissue: int = 10
    jitter_mm: float = 4.0
    jitter_deg: float = 4.0
    min_coverage: float = 0.97


@dataclass(frozen=True)
class PoseCfg:
    target_radius: float = 0.3
    shaft_to_axis_deg: Range = (35.0, 75.0)
    tip_to_tissue_mm: Range = (30.0, 100.0)
    roll_deg: Range = (-30.0, 30.0)
    pitch_deg: Range = (0.0, 60.0)
    yaw_deg: Range = (0.0, 60.0)
    wrist_sign: str = "random"
    opening_deg: Range = (0.0, 60.0)
    min_depth_mm: float = 20.0
    second_target_mm: float = 25.0


@dataclass(frozen=True)
class RejectionCfg:
    min_visib_fract: float = 0.15
    margin_px: int = 4
    max_attempts: int = 60


@dataclass(frozen=True)
class LightingCfg:
    endoscope_intensity: Range = (0.6, 1.3)
    color_jitter: float = 0.08
    extra_lights: tuple[int, int] = (0, 2)
    extra_intensity: Range = (0.1, 0.5)
    ambient: Range = (0.02, 0.07)


@dataclass(frozen=True)
class OutputCfg:
    split: str = "train"
    images_per_scene: int = 1000
    rgb_format: str = "jpg"
    jpg_quality: int = 95
    depth_scale: float = 0.1


@dataclass(frozen=True)
class SynthConfig:
    """Everything that defines a synthetic dataset, apart from the seed and the image count."""

    image: ImageCfg = field(default_factory=ImageCfg)
    camera: CameraCfg = field(default_factory=CameraCfg)
    instruments: tuple[str, ...] = ("large_needle_driver",)
    two_instruments_prob: float = 0.3
    tissue: TissueCfg = field(default_factory=TissueCfg)
    pose: PoseCfg = field(default_factory=PoseCfg)
    rejection: RejectionCfg = field(default_factory=RejectionCfg)
    lighting: LightingCfg = field(default_factory=LightingCfg)
    effects: dict[str, Any] = field(default_factory=dict)  # surftrack.synth.effects.CameraEffects fields
    output: OutputCfg = field(default_factory=OutputCfg)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def validate(self) -> SynthConfig:
        """Check values that would otherwise fail late or silently; returns self."""
        checks = [
            (self.image.width % 2 == 0 and self.image.height % 2 == 0, "image width and height must be even"),
            (len(self.instruments) > 0, "instruments must list at least one instrument"),
            (0.0 <= self.two_instruments_prob <= 1.0, "two_instruments_prob must be in [0, 1]"),
            (0.0 < self.rejection.min_visib_fract <= 1.0, "rejection.min_visib_fract must be in (0, 1]"),
            (self.pose.wrist_sign in ("random", "positive"), "pose.wrist_sign must be 'random' or 'positive'"),
            (self.output.rgb_format in ("jpg", "png"), "output.rgb_format must be 'jpg' or 'png'"),
            (self.output.images_per_scene > 0 and self.tissue.images_per_tissue > 0, "image counts must be > 0"),
            (self.output.images_per_scene % self.tissue.images_per_tissue == 0,
             "output.images_per_scene must be a multiple of tissue.images_per_tissue"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)
        for name in ("camera", "tissue", "pose", "lighting"):
            for f in dataclasses.fields(getattr(self, name)):
                v = getattr(getattr(self, name), f.name)
                if f.type == "Range" and v[0] > v[1]:
                    raise ConfigError(f"{name}.{f.name}: range {list(v)} has lower > upper")
        return self


def _build(cls: type, data: Any, where: str) -> Any:
    if not dataclasses.is_dataclass(cls):
        return data
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(data) - set(fields)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(fields)}")
    kwargs = {}
    for k, v in data.items():
        default = getattr(cls(), k) if k in fields else None
        if dataclasses.is_dataclass(default):
            kwargs[k] = _build(type(default), v, f"{where}.{k}")
        elif isinstance(default, tuple) and isinstance(v, list):
            kwargs[k] = tuple(v)
        else:
            kwargs[k] = v
    return cls(**kwargs)


def load_synth_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> SynthConfig:
    """Load a synthesis config (default: ``configs/synth/default.yaml``); ``overrides`` replace top-level keys."""
    from surftrack.paths import configs_dir

    p = Path(path) if path else configs_dir() / "synth" / "default.yaml"
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"{p}: cannot read synthesis config: {e}") from None
    data.update(overrides or {})
    try:
        return _build(SynthConfig, data, str(p)).validate()
    except ConfigError as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None
    except TypeError as e:
        raise ConfigError(f"{p}: {e}") from None

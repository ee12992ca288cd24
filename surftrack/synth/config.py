"""Synthesis configuration: dataclasses with defaults, loaded from YAML (``configs/synth/*.yaml``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from surftrack.configio import build_dataclass, yaml_problem

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
    source: str = "procedural"     # procedural | mesh | images
    mesh: str | None = None        # source 'mesh': an OBJ/PLY tissue surface (see synth.tissue.load_tissue_mesh)
    mesh_units: str = "mm"         # mm | cm | m
    images: str | None = None      # source 'images': an image file or a folder of them (one per tissue group)


TISSUE_SOURCES = ("procedural", "mesh", "images")
ROLL_ZEROS = ("view", "across")  # see surftrack.synth.sampling.roll_reference
JOINT_SOURCES = ("ranges", "limits")  # see surftrack.synth.sampling.sample_joints
MESH_UNITS = ("mm", "cm", "m")


@dataclass(frozen=True)
class PoseCfg:
    joint_source: str = "ranges"  # 'ranges': the *_deg ranges below (the paper's); 'limits': the instrument's own
    target_radius: float = 0.3
    shaft_to_axis_deg: Range = (35.0, 75.0)
    tip_to_tissue_mm: Range = (30.0, 100.0)
    roll_deg: Range = (-30.0, 30.0)
    pitch_deg: Range = (0.0, 60.0)
    yaw_deg: Range = (0.0, 60.0)
    wrist_sign: str = "random"
    roll_zero: str = "view"
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
        from surftrack.synth.effects import CameraEffects

        w, h = self.image.width, self.image.height
        if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 and v % 2 == 0 for v in (w, h)):
            raise ConfigError(f"image width and height must be even positive integers, got {w!r} x {h!r}")
        for name in ("camera", "tissue", "pose", "lighting"):
            for f in dataclasses.fields(getattr(self, name)):
                v = getattr(getattr(self, name), f.name)
                if f.type == "Range" and not (isinstance(v, (tuple, list)) and len(v) == 2 and all(
                        isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
                    raise ConfigError(f"{name}.{f.name}: expected a [lo, hi] range of numbers, got {v!r}")
        if not isinstance(self.effects, dict):
            raise ConfigError(f"effects: expected a mapping of camera effects, got {self.effects!r}")
        try:  # the workers build these: a bad value found there would stall a pool that restarts them
            CameraEffects.from_dict(self.effects)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"effects: {e}") from None
        checks = [
            (len(self.instruments) > 0, "instruments must list at least one instrument"),
            (0.0 <= self.two_instruments_prob <= 1.0, "two_instruments_prob must be in [0, 1]"),
            (0.0 < self.rejection.min_visib_fract <= 1.0, "rejection.min_visib_fract must be in (0, 1]"),
            (self.pose.wrist_sign in ("random", "positive"), "pose.wrist_sign must be 'random' or 'positive'"),
            (self.pose.roll_zero in ROLL_ZEROS, f"pose.roll_zero must be one of {', '.join(ROLL_ZEROS)}"),
            (self.pose.joint_source in JOINT_SOURCES,
             f"pose.joint_source must be one of {', '.join(JOINT_SOURCES)}"),
            (self.output.rgb_format in ("jpg", "png"), "output.rgb_format must be 'jpg' or 'png'"),
            (self.output.images_per_scene > 0 and self.tissue.images_per_tissue > 0, "image counts must be > 0"),
            (self.output.images_per_scene % self.tissue.images_per_tissue == 0,
             "output.images_per_scene must be a multiple of tissue.images_per_tissue"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)
        self._validate_tissue_source()
        for name in ("camera", "tissue", "pose", "lighting"):
            for f in dataclasses.fields(getattr(self, name)):
                v = getattr(getattr(self, name), f.name)
                if f.type == "Range" and v[0] > v[1]:
                    raise ConfigError(f"{name}.{f.name}: range {list(v)} has lower > upper")
        return self


    def _validate_tissue_source(self) -> None:
        from surftrack.synth.tissue import image_files

        t = self.tissue
        if t.source not in TISSUE_SOURCES:
            raise ConfigError(f"tissue.source: {t.source!r} is not one of {list(TISSUE_SOURCES)}")
        if t.mesh_units not in MESH_UNITS:
            raise ConfigError(f"tissue.mesh_units: {t.mesh_units!r} is not one of {list(MESH_UNITS)}")
        if t.source == "procedural":
            return
        key = t.source  # 'mesh' or 'images': the key holding the path
        path = getattr(t, key)
        if not isinstance(path, (str, Path)) or not str(path):
            raise ConfigError(f"tissue.{key}: tissue.source is {t.source!r} but tissue.{key} gives no path")
        if key == "mesh" and not Path(path).is_file():
            raise ConfigError(f"tissue.mesh: tissue mesh file not found: {path}")
        if key == "images":
            try:
                image_files(path)
            except ValueError as e:
                raise ConfigError(f"tissue.images: {e}") from None


def _resolve_tissue_paths(data: dict, base: Path) -> None:
    """Relative ``tissue.mesh`` / ``tissue.images`` paths in a config file are tried against the working
    directory first, then against the config file's folder."""
    tissue = data.get("tissue")
    if not isinstance(tissue, dict):
        return
    for key in ("mesh", "images"):
        v = tissue.get(key)
        if isinstance(v, str) and v and not Path(v).is_absolute() and not Path(v).exists() and (base / v).exists():
            tissue[key] = str(base / v)


def load_synth_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> SynthConfig:
    """Load a synthesis config: a YAML file, or the name of one in ``configs/synth`` (``default``, ``paper``;
    default: ``default``); ``overrides`` replace top-level keys."""
    from surftrack.paths import configs_dir

    named = configs_dir() / "synth" / f"{path or 'default'}.yaml"
    p = named if not path or (not Path(path).suffix and named.is_file()) else Path(path)
    if not p.is_file() and not Path(path or "").suffix:
        names = sorted(f.stem for f in (configs_dir() / "synth").glob("*.yaml"))
        raise ConfigError(f"{path}: no such synthesis config (a YAML file, or one of {', '.join(names)})")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"{p}: cannot read synthesis config: {yaml_problem(e)}") from None
    if isinstance(data, dict):
        _resolve_tissue_paths(data, p.parent)
        data.update(overrides or {})
    try:
        return build_dataclass(SynthConfig, data, str(p), ConfigError).validate()
    except (ConfigError, TypeError, ValueError) as e:  # validate() messages do not name the file yet; a
        msg = str(e)  # value of the wrong type (a string for a number) fails one of its comparisons
        raise ConfigError(msg if msg.startswith(str(p)) else f"{p}: {msg}") from None

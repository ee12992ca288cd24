"""A fixed held-out suite: image sets that isolate what a model must cope with, made once with fixed seeds
and never trained on, and one table of ADD-10 per part and per set (mean over pose-solver seeds).

The suite file (``configs/eval/suite.yaml``) names each set's synthesis config (a file or a name in
``configs/synth``), seed, image count and overrides (merged into the config section by section). The
sets are made on first use in a folder of their own (resumable; a set made with other settings is
refused, as ``surftrack synth`` refuses to mix them) and evaluated on their ``train`` split.

Its ``clips`` are tracking clips (``surftrack synth-clip``: the instrument driven over its joint limits,
a second tool crossing it) with their seed, length and frame rate, made on first use the same way; the
CLI scores per-frame estimation on them (:func:`surftrack.annotate.evaluate_clips`), since tracking
belongs to a later stage than this module.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from surftrack.configio import build_dataclass, yaml_problem
from surftrack.instruments import BUILTIN, InstrumentRegistry
from surftrack.paths import configs_dir

if TYPE_CHECKING:
    from surftrack.synth.clip import ClipConfig


class SuiteError(ValueError):
    """A malformed suite file; the message names the file."""


@dataclass(frozen=True)
class SuiteSet:
    name: str
    config: str                     # synthesis config: a YAML path or a name in configs/synth
    seed: int
    images: int
    overrides: dict[str, Any] = field(default_factory=dict)
    about: str = ""


@dataclass(frozen=True)
class SuiteClip:
    """A tracking clip of the suite: ``surftrack synth-clip`` with this ``seed``, ``seconds`` long at ``fps``;
    ``roll_deg`` / ``roll_swing_deg`` (degrees, [lo, hi]) as its options of those names, None for their
    defaults."""

    name: str
    seed: int
    seconds: float = 10.0
    fps: float = 15.0
    about: str = ""
    roll_deg: tuple[float, float] | None = None
    roll_swing_deg: tuple[float, float] | None = None

    @property
    def roll(self) -> dict[str, tuple[float, float]]:
        """The roll settings given (the others keep the clip config's defaults)."""
        return {k: v for k, v in (("roll_deg", self.roll_deg), ("roll_swing_deg", self.roll_swing_deg))
                if v is not None}

    def clip_config(self) -> ClipConfig:
        """The :class:`~surftrack.synth.clip.ClipConfig` it is made with (``ValueError`` when invalid)."""
        from surftrack.synth.clip import ClipConfig

        return ClipConfig(seconds=self.seconds, fps=self.fps, **self.roll)

    def stamp(self, instrument: str) -> dict:
        """What a made clip records of its settings (the roll keys only where set, so that clips made before
        they existed still match)."""
        return {"instrument": instrument, "seed": self.seed, "seconds": self.seconds, "fps": self.fps,
                **{k: list(v) for k, v in self.roll.items()}}


def _deep_merge(base: dict, extra: Mapping) -> dict:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
    return out


def _read_suite(path: str | Path | None) -> tuple[Path, dict]:
    p = Path(path) if path else configs_dir() / "eval" / "suite.yaml"
    try:
        doc = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SuiteError(f"{p}: cannot read suite: {yaml_problem(e)}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("sets"), dict) or not doc["sets"]:
        raise SuiteError(f"{p}: a suite needs 'sets': a mapping of set names to {{config, seed, images}}")
    unknown = set(doc) - {"images", "sets", "clips"}
    if unknown:
        raise SuiteError(f"{p}: unknown key(s) {sorted(unknown)} (known: images, sets, clips)")
    return p, doc


def load_suite(path: str | Path | None = None) -> list[SuiteSet]:
    """The sets of a suite file (default ``configs/eval/suite.yaml``)."""
    p, doc = _read_suite(path)
    out = []
    for name, spec in doc["sets"].items():
        if not isinstance(spec or {}, dict):
            raise SuiteError(f"{p}: set {name!r} must be a mapping of settings, got {spec!r}")
        spec = dict(spec or {})
        bad = set(spec) - {"config", "seed", "images", "overrides", "about"}
        if bad:
            raise SuiteError(f"{p}: set {name!r}: unknown key(s) {sorted(bad)}")
        if not isinstance(spec.get("seed"), int):
            raise SuiteError(f"{p}: set {name!r} needs an integer 'seed'")
        images = spec.get("images", doc.get("images", 100))
        if not isinstance(images, int) or isinstance(images, bool) or images < 1:
            raise SuiteError(f"{p}: set {name!r}: 'images' must be a positive integer, got {images!r}")
        if not isinstance(spec.get("overrides") or {}, dict):
            raise SuiteError(f"{p}: set {name!r}: 'overrides' must be a mapping of synthesis settings")
        out.append(SuiteSet(str(name), str(spec.get("config", "default")), int(spec["seed"]), images,
                            dict(spec.get("overrides") or {}), str(spec.get("about", ""))))
    return out


def load_suite_clips(path: str | Path | None = None) -> list[SuiteClip]:
    """The tracking clips of a suite file (none when it has no ``clips``)."""
    p, doc = _read_suite(path)
    clips = doc.get("clips") or {}
    if not isinstance(clips, dict):
        raise SuiteError(f"{p}: 'clips' must map clip names to {{seed, seconds, fps}}")
    out = []
    for name, spec in clips.items():
        if not isinstance(spec or {}, dict):
            raise SuiteError(f"{p}: clip {name!r} must be a mapping of settings, got {spec!r}")
        spec = dict(spec or {})
        bad = set(spec) - {"seed", "seconds", "fps", "about", "roll_deg", "roll_swing_deg"}
        if bad:
            raise SuiteError(f"{p}: clip {name!r}: unknown key(s) {sorted(bad)}")
        if not isinstance(spec.get("seed"), int):
            raise SuiteError(f"{p}: clip {name!r} needs an integer 'seed'")
        try:
            seconds, fps = float(spec.get("seconds", 10.0)), float(spec.get("fps", 15.0))
        except (TypeError, ValueError):
            raise SuiteError(f"{p}: clip {name!r}: seconds and fps must be numbers") from None
        if not (seconds > 0 and fps > 0 and seconds * fps >= 2):
            raise SuiteError(f"{p}: clip {name!r}: needs seconds > 0, fps > 0 and at least 2 frames")
        clip = SuiteClip(str(name), int(spec["seed"]), seconds, fps, str(spec.get("about", "")),
                         *(_pair(spec.get(k)) for k in ("roll_deg", "roll_swing_deg")))
        try:
            clip.clip_config()
        except (TypeError, ValueError) as e:
            raise SuiteError(f"{p}: clip {name!r}: {e}") from None
        out.append(clip)
    return out


def _pair(v):
    """A [lo, hi] setting as a tuple (None stays None; anything else is left for the clip config to refuse)."""
    return tuple(v) if isinstance(v, (list, tuple)) else v


def make_suite_clips(clips: Sequence[SuiteClip], root: str | Path, instrument: str = "large_needle_driver",
                     instruments: InstrumentRegistry = BUILTIN) -> dict[str, Path]:
    """Make every clip under ``root/<name>`` unless it is there already, made with the same settings (a
    ``suite_clip.json`` beside it records them; a clip made otherwise is refused); returns name -> folder."""
    import json

    from surftrack.synth.clip import make_clip

    out = {}
    for c in clips:
        folder = Path(root) / c.name
        stamp = c.stamp(instrument)
        marker = folder / "suite_clip.json"
        if marker.is_file():
            try:
                made = json.loads(marker.read_text())
            except ValueError:
                raise SuiteError(f"{marker}: not a JSON record of a suite clip's settings; remove the clip "
                                 f"folder or use another --suite-dir") from None
            if made != stamp:
                raise SuiteError(f"{folder}: made with other settings ({marker.read_text().strip()}); "
                                 f"remove it or use another --suite-dir")
        else:
            make_clip(folder, instrument, c.clip_config(), seed=c.seed, instruments=instruments)
            marker.write_text(json.dumps(stamp) + "\n")  # last: an interrupted clip is made again
        out[c.name] = folder
    return out


def clip_table(table: Mapping[str, Mapping], clips: Sequence[SuiteClip]) -> str:
    """Markdown: a row per clip (seed, frames), a column per part (ADD-10 % over the frames it is visible,
    mean over solver seeds), the part-frames pooled, and the pooled figure's range over the seeds.
    ``table``: clip name -> {"frames": n, "parts": {part: mean ADD-10 %}, "per_seed": [pooled %],
    "per_seed_twin": [pooled % with the roll twin counted as a symmetry] or None (then no such column)}."""
    parts = list(dict.fromkeys(p for row in table.values() for p in row["parts"]))
    twin = any(row.get("per_seed_twin") for row in table.values())
    head = ["clip", "seed", "frames", *parts, "all parts", "seed range", *(["up to the roll twin"] if twin else [])]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in clips:
        row = table[c.name]
        cells = [f"{row['parts'][p]:.1f}" if p in row["parts"] else "–" for p in parts]
        extra = ([f"{np.mean(row['per_seed_twin']):.1f}" if row.get("per_seed_twin") else "–"] if twin else [])
        lines.append("| " + " | ".join([c.name, str(c.seed), str(row["frames"]), *cells,
                                        f"{np.mean(row['per_seed']):.1f}",
                                        f"{min(row['per_seed']):.1f}-{max(row['per_seed']):.1f}", *extra]) + " |")
    notes = [f"- {c.name}: {c.about}" for c in clips if c.about]
    return "\n".join(lines + ["", "Per-frame estimation on tracking clips: ADD-10 (%) over each part's visible "
                               "frames (SurgRIPE diameter), mean over pose-solver seeds."
                               + (" Up to the roll twin: all parts pooled, each frame's instrument scored as its "
                                  "estimate or that estimate's half turn about the shaft, whichever is nearer the "
                                  "truth." if twin else ""), *notes]) + "\n"


def set_config(s: SuiteSet):
    """The :class:`~surftrack.synth.config.SynthConfig` of one set: its config with its overrides merged in."""
    from surftrack.synth.config import ConfigError, SynthConfig, load_synth_config

    base = load_synth_config(s.config).to_dict()
    return build_dataclass(SynthConfig, _deep_merge(base, s.overrides), f"suite set {s.name}", ConfigError).validate()


def make_suite(sets: Sequence[SuiteSet], root: str | Path, workers: int = 1, progress: bool = False,
               instruments: InstrumentRegistry = BUILTIN) -> dict[str, Path]:
    """Make (or resume) every set under ``root/<name>``; returns name -> dataset folder."""
    from surftrack.synth.generate import generate_dataset

    out = {}
    for s in sets:
        folder = Path(root) / s.name
        generate_dataset(folder, set_config(s), s.images, seed=s.seed, workers=workers, progress=progress,
                         instruments=instruments)
        out[s.name] = folder
    return out


def evaluate_suite(checkpoint, sets: Sequence[SuiteSet], folders: Mapping[str, Path], seeds: Sequence[int] = (0, 1, 2),
                   **kwargs) -> dict[str, dict]:
    """:func:`~surftrack.pose.evaluate.evaluate_seeds` on every set's ``train`` split; returns name ->
    {"parts": {label: ADD-10 mean over seeds, None without instances}, "all": pooled mean, "per_seed": pooled per seed,
    "twin": pooled mean with the instruments' roll twins counted as a symmetry (None without), "images": n}.
    ``kwargs`` go to the evaluation (preset, kinematic, device, instruments, ...)."""
    from surftrack.pose.estimator import PoseEstimator
    from surftrack.pose.evaluate import evaluate_seeds, part_labels
    from surftrack.pose.preset import get_preset

    preset = kwargs.pop("preset", "fast")
    est = checkpoint if isinstance(checkpoint, PoseEstimator) else PoseEstimator(
        checkpoint, get_preset(preset) if isinstance(preset, str) else preset, device=kwargs.pop("device", None),
        instruments=kwargs.get("instruments", BUILTIN))
    # the table's labels, as evaluate() writes them (a part found by its obj_id, whatever its label in a set)
    labels = part_labels({info.obj_id: (info.instrument, info.name) for info in est.model.parts})
    table = {}
    for s in sets:
        results = evaluate_seeds(est, folders[s.name], list(seeds), split="train", **kwargs)
        key = "add10_surgripe"
        # every part of the model, in its order; None where the set has no instance of it
        parts = {}
        for info in est.model.parts:
            got = [[v["all"][key] for v in r["parts"].values() if v["obj_id"] == info.obj_id] for r in results]
            parts[labels[info.obj_id]] = float(np.mean([g[0] for g in got])) if got[0] else None
        per_seed = [float(r["overall"]["all"][key]) for r in results]
        twin = [r["overall"]["all"].get("add10_twin_surgripe") for r in results]
        table[s.name] = {"parts": parts, "all": float(np.mean(per_seed)), "per_seed": per_seed,
                         "twin": float(np.mean(twin)) if all(v is not None for v in twin) else None,
                         "images": results[0]["n_images"], "warnings": results[0]["warnings"]}
    return table


def suite_table(table: Mapping[str, Mapping], sets: Sequence[SuiteSet]) -> str:
    """Markdown: a row per set (its seed and what it isolates), a column per part, pooled last (ADD-10 %)."""
    labels = list(dict.fromkeys(label for row in table.values() for label in row["parts"]))
    short = [label.split(" ", 1)[-1] for label in labels]
    twin = any(table[s.name].get("twin") is not None for s in sets)
    head = ["set", "seed", "images", *short, "all parts", "seed range", *(["up to the roll twin"] if twin else [])]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in sets:
        row = table[s.name]
        cells = [f"{100 * row['parts'][label]:.1f}" if row["parts"].get(label) is not None else "–" for label in labels]
        extra = ([f"{100 * row['twin']:.1f}" if row.get("twin") is not None else "–"] if twin else [])
        lines.append("| " + " | ".join([s.name, str(s.seed), str(row["images"]), *cells, f"{100 * row['all']:.1f}",
                                        f"{100 * min(row['per_seed']):.1f}-{100 * max(row['per_seed']):.1f}",
                                        *extra]) + " |")
    notes = [f"- {s.name}: {s.about}" for s in sets if s.about]
    about = ["", "ADD-10 (%) with the SurgRIPE diameter, mean over pose-solver seeds."
             + (" Up to the roll twin: with each instrument's half turn about its shaft (the jaws exchanged, which "
                "one image cannot tell from the truth) counted as a symmetry, over the images whose instrument "
                "was estimated whole." if twin else "")]
    return "\n".join(lines + about + notes) + "\n"


__all__ = ["SuiteClip", "SuiteError", "SuiteSet", "clip_table", "evaluate_suite", "load_suite", "load_suite_clips",
           "make_suite", "make_suite_clips", "set_config", "suite_table"]

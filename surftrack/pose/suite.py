"""A fixed held-out suite: image sets that isolate what a model must cope with, made once with fixed seeds
and never trained on, and one table of ADD-10 per part and per set (mean over pose-solver seeds).

The suite file (``configs/eval/suite.yaml``) names each set's synthesis config (a file or a name in
``configs/synth``), seed, image count and overrides (merged into the config section by section). The
sets are made on first use in a folder of their own (resumable; a set made with other settings is
refused, as ``surftrack synth`` refuses to mix them) and evaluated on their ``train`` split.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from surftrack.configio import build_dataclass, yaml_problem
from surftrack.instruments import BUILTIN, InstrumentRegistry
from surftrack.paths import configs_dir


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


def _deep_merge(base: dict, extra: Mapping) -> dict:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
    return out


def load_suite(path: str | Path | None = None) -> list[SuiteSet]:
    """The sets of a suite file (default ``configs/eval/suite.yaml``)."""
    p = Path(path) if path else configs_dir() / "eval" / "suite.yaml"
    try:
        doc = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SuiteError(f"{p}: cannot read suite: {yaml_problem(e)}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("sets"), dict) or not doc["sets"]:
        raise SuiteError(f"{p}: a suite needs 'sets': a mapping of set names to {{config, seed, images}}")
    unknown = set(doc) - {"images", "sets"}
    if unknown:
        raise SuiteError(f"{p}: unknown key(s) {sorted(unknown)} (known: images, sets)")
    out = []
    for name, spec in doc["sets"].items():
        spec = dict(spec or {})
        bad = set(spec) - {"config", "seed", "images", "overrides", "about"}
        if bad:
            raise SuiteError(f"{p}: set {name!r}: unknown key(s) {sorted(bad)}")
        if not isinstance(spec.get("seed"), int):
            raise SuiteError(f"{p}: set {name!r} needs an integer 'seed'")
        out.append(SuiteSet(str(name), str(spec.get("config", "default")), int(spec["seed"]),
                            int(spec.get("images", doc.get("images", 100))), dict(spec.get("overrides") or {}),
                            str(spec.get("about", ""))))
    return out


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
    "images": n}. ``kwargs`` go to the evaluation (preset, kinematic, device, instruments, ...)."""
    from surftrack.pose.estimator import PoseEstimator
    from surftrack.pose.evaluate import evaluate_seeds
    from surftrack.pose.preset import get_preset

    preset = kwargs.pop("preset", "fast")
    est = checkpoint if isinstance(checkpoint, PoseEstimator) else PoseEstimator(
        checkpoint, get_preset(preset) if isinstance(preset, str) else preset, device=kwargs.pop("device", None))
    table = {}
    for s in sets:
        results = evaluate_seeds(est, folders[s.name], list(seeds), split="train", **kwargs)
        key = "add10_surgripe"
        # every part of the model, in its order; None where the set has no instance of it
        parts = {label: float(np.mean([r["parts"][label]["all"][key] for r in results]))
                 if label in results[0]["parts"] else None
                 for label in (f"{info.instrument} {info.name}" for info in est.model.parts)}
        per_seed = [float(r["overall"]["all"][key]) for r in results]
        table[s.name] = {"parts": parts, "all": float(np.mean(per_seed)), "per_seed": per_seed,
                         "images": results[0]["n_images"], "warnings": results[0]["warnings"]}
    return table


def suite_table(table: Mapping[str, Mapping], sets: Sequence[SuiteSet]) -> str:
    """Markdown: a row per set (its seed and what it isolates), a column per part, pooled last (ADD-10 %)."""
    labels = list(dict.fromkeys(label for row in table.values() for label in row["parts"]))
    short = [label.split(" ", 1)[-1] for label in labels]
    head = ["set", "seed", "images", *short, "all parts", "seed range"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in sets:
        row = table[s.name]
        cells = [f"{100 * row['parts'][label]:.1f}" if row["parts"].get(label) is not None else "–" for label in labels]
        lines.append("| " + " | ".join([s.name, str(s.seed), str(row["images"]), *cells, f"{100 * row['all']:.1f}",
                                        f"{100 * min(row['per_seed']):.1f}-{100 * max(row['per_seed']):.1f}"]) + " |")
    notes = [f"- {s.name}: {s.about}" for s in sets if s.about]
    return "\n".join(lines + ["", "ADD-10 (%) with the SurgRIPE diameter, mean over pose-solver seeds.", *notes]) + "\n"


__all__ = ["SuiteError", "SuiteSet", "evaluate_suite", "load_suite", "make_suite", "set_config", "suite_table"]

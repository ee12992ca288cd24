"""Instrument-level consistency: the per-part poses of one instrument replaced by the forward kinematics of
the articulated configuration that best explains them.

SurfSurg6D estimates every rigid part on its own, so nothing ties a jaw to the wrist that carries it, and a
near-symmetric shaft's roll about its own axis is barely observable in its crop. The parts of one
instrument are not independent: :func:`surftrack.instruments.fit_configuration` fits the base pose and the
joints (roll, wrist pitch, wrist yaw, jaw opening) to the part estimates, weighted by their scores, and the
fitted forward kinematics give every part a pose consistent with the others: the shaft's roll comes from
the wrist, a jaw's position from the wrist and its own rotation from one joint angle.

``anchor`` gets ``anchor_weight`` times its score as the weight of its rotation: the part the estimator
gets right most often (the LND's wrist: the largest, least symmetric part) then fixes the orientation and
the others follow it. Its translation gets only ``anchor_translation_weight`` times its score: a monocular
pose's weak coordinate is depth (on LND development images the part estimates are off by ~2 mm along
the viewing ray and ~0.2 mm across it), the four parts' depth errors are nearly uncorrelated (|r| <= 0.17),
and the wrist's is only about half the others' (median relative depth error 2.3 % against 3.9-8.1 %), so
inverse-variance fusion gives it about 3x a part's weight, not 10x. Every part, the anchor included,
takes its fitted pose. Both weights were chosen on development sets (80 LND images, seed 14; 200, seed
22) separate from the held-out sets of the model card, which gives what the fusion gained (it varies
with the solver's random draws).

:func:`consistent_poses` works on poses; :func:`apply_kinematics` on a frame's :class:`PartPose` list,
grouped by instrument instance.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections import defaultdict
from collections.abc import Hashable, Mapping, Sequence
from typing import Any
from dataclasses import dataclass

import numpy as np

from surftrack.instruments import (
    BUILTIN,
    FitConfig,
    Instrument,
    InstrumentError,
    InstrumentRegistry,
    JointFit,
    fit_configuration,
)
from surftrack.instruments.part import GEOMETRY_TOL_MM


@dataclass(frozen=True)
class KinematicConfig:
    """``anchor`` / ``anchor_weight`` / ``anchor_translation_weight``: the part whose weights are
    multiplied, for its rotation and its translation (see the module docstring). ``min_weight``: weight
    floor of a part with a low or negative score. ``rotation_scale_mm``: mm of residual per radian of
    rotation error in the fit (:class:`FitConfig`)."""

    anchor: str = "wrist"
    anchor_weight: float = 10.0
    min_weight: float = 0.05
    rotation_scale_mm: float = 30.0
    anchor_translation_weight: float = 3.0

    def __post_init__(self) -> None:
        for name in ("anchor_weight", "min_weight", "rotation_scale_mm", "anchor_translation_weight"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise ValueError(f"kinematic {name} must be a positive number, got {v!r}")

    def weight(self, part: str, score: float, translation: bool = False) -> float:
        """Fit weight of ``part``'s rotation (``translation``: of its translation) given its estimator
        score (or tracking confidence)."""
        w = max(float(score), self.min_weight) if math.isfinite(score) else self.min_weight
        if part != self.anchor:
            return w
        return w * (self.anchor_translation_weight if translation else self.anchor_weight)


def check_anchor(config: KinematicConfig, model_parts: Sequence) -> None:
    """Raise ``ValueError`` when an anchor other than the default names no part of the model
    (``model.parts``): a misspelt anchor would otherwise silently fit every part with equal trust and move
    the anchor too. The default anchor is not checked: an instrument without a part of that name is fitted
    with equal trust, as :func:`apply_kinematics` says."""
    names = sorted({info.name for info in model_parts})
    if config.anchor != KinematicConfig.anchor and config.anchor not in names:
        raise ValueError(f"kinematic anchor {config.anchor!r} is not a part of the model (parts: "
                         f"{', '.join(names)}); name one of them, or turn the kinematic fit off")


_instruments: dict[tuple, tuple[Instrument | None, str]] = {}
_warned: set[str] = set()


def described_instrument(name: str, model_parts: Mapping[str, Any] | None = None,
                         caller_reports: bool = False,
                         registry: InstrumentRegistry = BUILTIN) -> tuple[Instrument | None, str]:
    """(instrument, "") for the instrument ``name`` known to ``registry`` when its parts' meshes are those
    the model was trained on (``model_parts``: part name -> the checkpoint's :class:`PartInfo`, compared by
    geometry within :data:`~surftrack.instruments.part.GEOMETRY_TOL_MM`, so a CAD whose dataset models went
    through a float32 round trip still matches); else (None, why not): unknown, or other meshes, so no
    kinematic model applies. ``caller_reports``: the caller tells the user why, so
    :func:`kinematic_instrument` does not warn about it. Cached per process, registry and mesh hashes
    (edit a description, restart)."""
    model_parts = model_parts or {}
    key = (name, registry, tuple(sorted((p, info.mesh_sha256) for p, info in model_parts.items())))
    if key not in _instruments:
        try:
            inst: Instrument | None = registry.load(name)
            why = ""
        except InstrumentError:
            inst, why = None, (f"instrument {name!r} has no description (built-in, or its YAML passed with "
                               f"--instrument or listed in $SURFTRACK_INSTRUMENTS)")
        if inst is not None:
            bad = [p for p, info in model_parts.items()
                   if p not in inst.parts or not (inst.parts[p].mesh_hash == info.mesh_sha256
                                                  or inst.parts[p].same_geometry(info.vertices, info.faces))]
            if bad:
                where = inst.source or "its description"
                inst, why = None, (f"instrument {name!r}: the model's meshes of {bad} differ from those of {where} "
                                   f"(by more than {GEOMETRY_TOL_MM:g} mm)")
        _instruments[key] = (inst, why)
    if caller_reports and _instruments[key][1]:
        _warned.add(_instruments[key][1])
    return _instruments[key]


def instrument_parts(model_parts: Sequence) -> dict[str, dict[str, Any]]:
    """Instrument -> {part: PartInfo} of a model's parts (``model.parts``), as :func:`described_instrument`
    takes them."""
    out: dict[str, dict[str, Any]] = defaultdict(dict)
    for info in model_parts:
        out[info.instrument][info.name] = info
    return dict(out)


def kinematic_instrument(name: str, model_parts: Mapping[str, Any] | None = None,
                         registry: InstrumentRegistry = BUILTIN) -> Instrument | None:
    """:func:`described_instrument`'s instrument; None with one warning (per process and cause) when
    there is none, so its parts keep their per-part poses."""
    inst, why = described_instrument(name, model_parts, registry=registry)
    if inst is None and why not in _warned:
        _warned.add(why)
        warnings.warn(f"{why}: its parts keep their per-part poses", stacklevel=2)
    return inst


def consistent_poses(instrument: Instrument, observed: Mapping[str, tuple[np.ndarray, np.ndarray, float]],
                     config: KinematicConfig | None = None, init: JointFit | None = None,
                     trocar_mm: np.ndarray | None = None) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], JointFit]:
    """Fit ``instrument`` to ``observed`` ({part: (R, t mm, score)}, model-to-camera) and return the
    fitted pose of every part of the instrument ({part: (R, t)}) and the fit. Raises ``ValueError`` when
    nothing can be fitted (no known part)."""
    cfg = config or KinematicConfig()
    poses = {p: (R, t) for p, (R, t, _) in observed.items()}
    weights = {p: cfg.weight(p, s) for p, (_, _, s) in observed.items()}
    translation_weights = {p: cfg.weight(p, s, translation=True) for p, (_, _, s) in observed.items()}
    fit = fit_configuration(instrument, poses, weights=weights, trocar_mm=trocar_mm, init=init,
                            config=FitConfig(rotation_scale_mm=cfg.rotation_scale_mm),
                            translation_weights=translation_weights)
    return {p: (T[:3, :3].copy(), T[:3, 3].copy()) for p, T in fit.part_poses(instrument).items()}, fit


def apply_kinematics(results: Sequence, groups: Sequence[Hashable], model_parts: Sequence,
                     config: KinematicConfig | None = None, registry: InstrumentRegistry = BUILTIN) -> list:
    """Replace each :class:`PartPose` in ``results`` (one frame) by its instrument-consistent pose.

    ``groups[i]``: the instrument instance ``results[i]`` belongs to (parts of one instrument with the same
    key are fitted together). ``model_parts``: the model's :class:`PartInfo` list (``model.parts``), whose
    meshes must match the instrument description's (found in ``registry``).
    A group is fitted only when its anchor part (``config.anchor``) was estimated and seen (score > 0:
    some pixel supports its pose; a score <= 0 anchor is the network seeing nothing of it, and the tracker
    drops such a part rather than trust it). Every part of a fitted group takes its fitted pose, the anchor
    too (its depth is fused with the others'). Failed estimates (``ok`` False), groups of one part, groups
    that repeat a part and instruments without a kinematic model are left as they are. Replaced results
    carry ``kinematic=True``."""
    if len(groups) != len(results):
        raise ValueError(f"need one group key per result, got {len(groups)} for {len(results)}")
    cfg = config or KinematicConfig()
    by_instrument = instrument_parts(model_parts)
    members: dict[tuple, list[int]] = defaultdict(list)
    for i, (r, g) in enumerate(zip(results, groups)):
        members[(r.instrument, g)].append(i)
    out = list(results)
    for (name, _), idx in members.items():
        parts = [results[i].part for i in idx]
        if len(idx) < 2 or len(set(parts)) != len(parts):
            continue
        inst = kinematic_instrument(name, by_instrument.get(name), registry)
        if inst is None:
            continue
        obs = {results[i].part: (results[i].R, results[i].t, results[i].score) for i in idx if results[i].ok}
        if len(obs) < 2 or (cfg.anchor in inst.parts and (cfg.anchor not in obs or obs[cfg.anchor][2] <= 0.0)):
            continue  # without its anchor the fit would place the parts relative to less reliable ones
        try:
            fitted, _ = consistent_poses(inst, obs, cfg)
        except ValueError:
            continue
        for i in idx:
            if not results[i].ok:
                continue  # a failed estimate stays a failure
            R, t = fitted[results[i].part]
            out[i] = dataclasses.replace(results[i], R=R, t=t, kinematic=True)
    return out

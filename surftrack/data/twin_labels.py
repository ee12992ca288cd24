"""Training labels of near-symmetric instruments made a function of the image.

A grasper and its roll twin (half a turn about the shaft, the jaws exchanged: :mod:`surftrack.instruments.twin`)
give the same image. Synthesis over the instrument's whole reach draws both equally often, so the same crop
would be labelled jaw_left half the time and jaw_right the other half, the shaft and wrist turned half a
turn alike. :class:`TwinLabels` labels every such instance as the twin whose shaft x axis points away from
the camera (roll within +-90 deg of synthesis's `view` zero, where the paper's ranges lie; the other twin's x
axis points towards it), so that one image has one set of targets. A model trained so answers with that
twin, and is scored up to the twin (``surftrack eval``'s ``add10_twin_surgripe``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from surftrack.instruments import BUILTIN, HALF_TURN, InstrumentError, InstrumentRegistry
from surftrack.instruments.check import random_joint_states


@dataclass(frozen=True)
class TwinLabels:
    """``partner``: obj id -> the obj id its twin labels it as (itself for a shaft or a wrist), for the
    parts of instruments with a roll twin. ``axis_parts``: obj ids whose x axis is their instrument's
    shaft x axis in every configuration (the shaft, a wrist pitching about it); one of them decides."""

    partner: dict[int, int]
    axis_parts: frozenset[int]

    def flips(self, instances: Sequence) -> list[bool]:
        """Per instance (:class:`~surftrack.data.bop.Instance` with ``extra['instrument_index']``): whether its
        instrument, in its image, is annotated as the twin whose shaft x axis points towards the camera. An
        instrument none of whose ``axis_parts`` is among ``instances`` keeps its labels."""
        towards: dict[tuple, bool] = {}
        for inst in instances:
            if inst.obj_id in self.axis_parts:
                key = (inst.scene_id, inst.im_id, inst.extra.get("instrument_index", 0))
                towards.setdefault(key, float(inst.R[:, 0] @ inst.t) < 0.0)
        return [inst.obj_id in self.partner
                and towards.get((inst.scene_id, inst.im_id, inst.extra.get("instrument_index", 0)), False)
                for inst in instances]

    def relabel(self, obj_id: int, pose: np.ndarray) -> tuple[int, np.ndarray]:
        """The twin's label of an instance: its partner's obj id and the pose (4x4 model-to-camera, mm)
        turned half a turn about the part's own z axis."""
        out = np.array(pose, dtype=np.float64)
        out[:3, :3] = out[:3, :3] @ HALF_TURN
        return self.partner[obj_id], out


def twin_labels(objects: Mapping[int, tuple[str, str]],
                registry: InstrumentRegistry = BUILTIN) -> TwinLabels | None:
    """The :class:`TwinLabels` of a dataset whose ``objects`` map obj id -> (instrument, part) (its
    ``dataset_card.json``); None when none of its instruments has a roll twin. Instruments without a
    description, or whose twin names a part the dataset lacks, keep their labels."""
    by_instrument: dict[str, dict[str, int]] = {}
    for o, (instrument, part) in objects.items():
        by_instrument.setdefault(instrument, {})[part] = int(o)
    partner: dict[int, int] = {}
    axis: set[int] = set()
    for name, ids in by_instrument.items():
        try:
            inst = registry.load(name)
        except InstrumentError:
            continue
        twin = inst.roll_twin
        if twin is None or not all(twin.partner.get(p, p) in ids for p in ids):
            continue  # a partner the dataset lacks: the twin's labels would name no model
        root = inst.part_names[0]
        shared = set(inst.part_names)
        for q in random_joint_states(inst, 4):
            poses = inst.forward(np.eye(4), q)
            shared &= {p for p in inst.part_names if np.allclose(poses[p][:3, 0], poses[root][:3, 0], atol=1e-9)}
        partner.update({ids[p]: ids[twin.partner[p]] for p in ids if p in twin.partner})
        axis.update(ids[p] for p in shared if p in ids)
    return TwinLabels(partner, frozenset(axis)) if partner else None

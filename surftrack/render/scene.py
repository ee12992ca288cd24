"""Putting instruments into a :class:`Renderer`: one instance per part plus its render-only attachments."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from surftrack.instruments.library import Instrument
from surftrack.render.renderer import Renderer


@dataclass
class InstrumentInstances:
    """Renderer instance ids of one instrument: its parts and its attachments (e.g. the long shaft)."""

    instrument: Instrument
    parts: dict[str, int]
    attachments: list[tuple[str, int]] = field(default_factory=list)

    def poses(self, part_poses: dict[str, np.ndarray]) -> dict[int, np.ndarray]:
        """Instance id -> pose for :meth:`Renderer.render`, from part name -> part-to-camera pose."""
        out = {iid: part_poses[p] for p, iid in self.parts.items()}
        out.update({iid: part_poses[p] for p, iid in self.attachments})
        return out

    def part_of(self, instance_id: int) -> str | None:
        """The part name rendered as ``instance_id`` (None for attachments and other instances)."""
        return next((p for p, i in self.parts.items() if i == instance_id), None)


def add_instrument(renderer: Renderer, instrument: Instrument, like: InstrumentInstances | None = None) -> InstrumentInstances:
    """Add every part (amodal masks on) and attachment (amodal off) of ``instrument`` to ``renderer``.

    With ``like`` (an already added copy of the same instrument) the geometry is shared, not re-uploaded.
    """
    parts, atts = {}, []
    for pname, part in instrument.parts.items():
        if like is not None:
            parts[pname] = renderer.add_instance(like.parts[pname], amodal=True, name=f"{instrument.name}/{pname}")
        else:
            parts[pname] = renderer.add_mesh(part.mesh, part.material, amodal=True, name=f"{instrument.name}/{pname}")
    for k, att in enumerate(instrument.attachments):
        mat = instrument.parts[att.part].material
        if like is not None:
            atts.append((att.part, renderer.add_instance(like.attachments[k][1], amodal=False)))
        else:
            atts.append((att.part, renderer.add_mesh(att.mesh, mat, amodal=False, name=f"{instrument.name}/{att.part}+")))
    return InstrumentInstances(instrument, parts, atts)

"""Which contacts between an instrument's own parts are physical, for CAD as labs have it.

CAD parts touch where they are pinned together (a jaw's hub in the wrist's clevis) and often overlap a
little at the hubs even at the rest configuration; an all-pairs collision test then rejects every pose.
The rule (:class:`ContactRule`): a pair already in contact at the rest configuration (all joints zero,
clipped to the limits) is not tested; a pair linked by a joint (parent and child) may touch and may
penetrate up to ``tolerance_mm``; any other pair may not touch. Penetration is the deepest contact fcl
reports between the two meshes' triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from surftrack.instruments.library import Instrument

#: Penetration allowed between a part and the part it hangs from (mm): CAD pins sit in their bores with no
#: clearance, and triangle meshes of round pins and bores cut into each other by a fraction of a mm.
LINKED_TOLERANCE_MM = 0.3

Pair = tuple[str, str]


def _pair(a: str, b: str) -> Pair:
    return (a, b) if a < b else (b, a)


def collision_manager(meshes: dict[str, trimesh.Trimesh]) -> trimesh.collision.CollisionManager:
    """An fcl manager holding ``meshes`` under their names; pose them with ``set_transform`` (building the
    meshes' BVHs is the costly part, so reuse one manager over many poses)."""
    m = trimesh.collision.CollisionManager()
    for name, mesh in meshes.items():
        m.add_object(name, mesh)
    return m


def contact_depths(manager: trimesh.collision.CollisionManager, poses: dict[str, np.ndarray]) -> dict[Pair, float]:
    """Deepest penetration (mm, >= 0) of every pair of the manager's meshes in contact, posed by ``poses``
    (name -> 4x4)."""
    for name, T in poses.items():
        manager.set_transform(name, T)
    return depths_of(manager)


def depths_of(manager: trimesh.collision.CollisionManager) -> dict[Pair, float]:
    """Deepest penetration per colliding pair of the objects in ``manager`` (as they are posed now)."""
    hit, contacts = manager.in_collision_internal(return_data=True)
    out: dict[Pair, float] = {}
    for c in contacts if hit else []:
        a, b = sorted(c.names)
        out[(a, b)] = max(out.get((a, b), 0.0), float(max(c.depth, 0.0)))
    return out


@dataclass(frozen=True)
class ContactRule:
    """The contacts between one instrument's parts that reject a pose (see the module docstring)."""

    at_rest: dict[Pair, float]       # pairs in contact at rest -> depth there (mm); never tested
    linked: frozenset[Pair]          # parent-child pairs
    tolerance_mm: float = LINKED_TOLERANCE_MM

    @classmethod
    def of(cls, instrument: Instrument, tolerance_mm: float = LINKED_TOLERANCE_MM) -> ContactRule:
        manager = collision_manager({n: p.mesh for n, p in instrument.parts.items()})
        at_rest = contact_depths(manager, instrument.forward(np.eye(4), instrument.rest))
        linked = frozenset(_pair(n, j.parent) for n, j in instrument.chain.joints.items() if j.parent is not None)
        return cls(at_rest, linked, tolerance_mm)

    def rejects(self, a: str, b: str, depth: float) -> bool:
        """Whether parts ``a`` and ``b``, in contact with penetration ``depth`` (mm), make a pose invalid."""
        pair = _pair(a, b)
        if pair in self.at_rest:
            return False
        return pair not in self.linked or depth > self.tolerance_mm

"""Rejection tests for sampled scenes: view, instrument-tissue and part-part collisions, visibility."""

from __future__ import annotations

import numpy as np
import trimesh

from surftrack.geometry import PinholeCamera, transform_points
from surftrack.instruments import Instrument
from surftrack.instruments.contacts import ContactRule, depths_of
from surftrack.synth.sampling import InstrumentSample
from surftrack.synth.tissue import Tissue

def in_view(sample: InstrumentSample, camera: PinholeCamera, margin: float, min_depth: float) -> bool:
    """Wrist and tool tips project at least ``margin`` px inside the image, at least ``min_depth`` mm away."""
    kps = sample.keypoints()
    pts = np.array([p for k, p in kps.items() if k.endswith("/tip") or k.startswith("wrist/")])
    if (pts[:, 2] < min_depth).any():
        return False
    uv = camera.project(pts)
    return bool(((uv[:, 0] >= margin) & (uv[:, 0] <= camera.width - 1 - margin)
                 & (uv[:, 1] >= margin) & (uv[:, 1] <= camera.height - 1 - margin)).all())


class TissueCollision:
    """Instrument-tissue test against the tissue height field: surface samples of every part (and of the
    render-only shaft extension) must lie in front of the surface wherever they are over the patch."""

    def __init__(self, instrument: Instrument, samples_per_part: int = 600, seed: int = 0):
        self.points: dict[str, np.ndarray] = {}
        for name, part in instrument.parts.items():
            self.points[name] = part.sample_surface(samples_per_part, seed=seed)[0]
        for k, att in enumerate(instrument.attachments):
            pts = trimesh.sample.sample_surface(att.mesh, 4 * samples_per_part, seed=seed)[0]
            self.points[att.part] = np.concatenate([self.points[att.part], pts])

    def collides(self, poses: dict[str, np.ndarray], tissue: Tissue, tissue_pose: np.ndarray, clearance: float = 0.0) -> bool:
        inv = np.linalg.inv(tissue_pose)
        w, h = tissue.extent
        for name, pts in self.points.items():
            local = transform_points(inv @ poses[name], pts)
            over = (np.abs(local[:, 0]) < w / 2) & (np.abs(local[:, 1]) < h / 2)
            if not over.any():
                continue
            surf = tissue.height_at(local[over, 0], local[over, 1])
            if (local[over, 2] > surf - clearance).any():
                return True
        return False


class PartCollision:
    """Mesh-mesh collisions (python-fcl) among the parts of up to ``slots`` posed instruments, shaft
    extensions included. One collision manager per (slot, instrument): the parts of an instrument are
    tested with each other under its :class:`ContactRule` (pairs touching at rest are not tested, parts
    linked by a joint may touch; its shaft extension is not tested: it overlaps its own shaft by design and
    sits behind it, out of reach of the other parts), and every pair of instruments across managers."""

    def __init__(self, instruments: list[Instrument], slots: int = 2):
        self.managers: dict[tuple[int, str], tuple[trimesh.collision.CollisionManager, list[tuple[str, str]]]] = {}
        self.rules = {inst.name: ContactRule.of(inst) for inst in instruments}
        for slot in range(slots):
            for inst in instruments:
                m, names = trimesh.collision.CollisionManager(), []
                for pname, part in inst.parts.items():
                    m.add_object(pname, part.mesh)
                    names.append((pname, pname))
                for k, att in enumerate(inst.attachments):
                    m.add_object(f"{att.part}|ext{k}", att.mesh)
                    names.append((f"{att.part}|ext{k}", att.part))
                self.managers[(slot, inst.name)] = (m, names)

    def collisions_of(self, posed: list[tuple[Instrument, dict[str, np.ndarray]]]) -> list[tuple[str, str]]:
        """Colliding pairs ``slot|part`` for instruments given as (instrument, part poses), in slot order."""
        managers = []
        for slot, (inst, poses) in enumerate(posed):
            m, names = self.managers[(slot, inst.name)]
            for obj, part in names:
                m.set_transform(obj, poses[part])
            managers.append(m)
        out = []
        for slot, (m, (inst, _)) in enumerate(zip(managers, posed)):
            hit, pairs = m.in_collision_internal(return_names=True)
            rule = self.rules[inst.name]
            pairs = sorted(p for p in pairs if "|ext" not in p[0] + p[1] and p not in rule.at_rest)
            if not hit or not pairs:
                continue
            # penetration depths (all contacts of the manager, slower) only where they decide
            depths = depths_of(m) if any(p in rule.linked for p in pairs) else {}
            out += [(f"{slot}|{a}", f"{slot}|{b}") for a, b in pairs if rule.rejects(a, b, depths.get((a, b), 0.0))]
        for i in range(len(managers)):
            for j in range(i + 1, len(managers)):
                hit, pairs = managers[i].in_collision_other(managers[j], return_names=True)
                if hit:
                    out += [(f"{i}|{a}", f"{j}|{b}") for a, b in sorted(pairs)]
        return out

    def collisions(self, samples: list[InstrumentSample]) -> list[tuple[str, str]]:
        """Colliding pairs for sampled instruments (see :meth:`collisions_of`)."""
        return self.collisions_of([(s.instrument, s.poses) for s in samples])

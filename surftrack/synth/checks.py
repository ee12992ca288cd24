"""Rejection tests for sampled scenes: view, instrument-tissue and part-part collisions, visibility."""

from __future__ import annotations

import numpy as np
import trimesh

from surftrack.geometry import PinholeCamera, transform_points
from surftrack.instruments import Instrument
from surftrack.synth.sampling import InstrumentSample
from surftrack.synth.tissue import Tissue

_FAR = np.eye(4)
_FAR[:3, 3] = 1e7  # where unused collision objects are parked


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
    """Mesh-mesh collisions (python-fcl) among the parts of up to ``slots`` instruments, including the
    shaft extensions. Within one instrument the extension overlaps its own shaft by design: not counted."""

    def __init__(self, instruments: list[Instrument], slots: int = 2):
        self.manager = trimesh.collision.CollisionManager()
        self.names: dict[tuple[int, str], list[str]] = {}
        for slot in range(slots):
            for inst in instruments:
                for pname, part in inst.parts.items():
                    self._add(slot, inst, pname, part.mesh, f"{slot}|{inst.name}|{pname}")
                for k, att in enumerate(inst.attachments):
                    self._add(slot, inst, att.part, att.mesh, f"{slot}|{inst.name}|{att.part}|ext{k}")

    def _add(self, slot: int, inst: Instrument, part: str, mesh: trimesh.Trimesh, name: str) -> None:
        self.manager.add_object(name, mesh, transform=_FAR)
        self.names.setdefault((slot, inst.name), []).append(name)

    def collisions(self, samples: list[InstrumentSample]) -> list[tuple[str, str]]:
        """Colliding object pairs ``slot|instrument|part[|extK]`` for the posed instruments."""
        for key, names in self.names.items():
            for n in names:
                self.manager.set_transform(n, _FAR)
        active = set()
        for slot, s in enumerate(samples):
            for n in self.names[(slot, s.instrument.name)]:
                self.manager.set_transform(n, s.poses[n.split("|")[2]])
                active.add(n)
        hit, pairs = self.manager.in_collision_internal(return_names=True)
        if not hit:
            return []
        out = []
        for a, b in sorted(tuple(sorted(p)) for p in pairs):
            if a not in active or b not in active:  # parked objects overlap each other far away
                continue
            sa, sb = a.split("|"), b.split("|")
            same_instrument = sa[0] == sb[0]
            if same_instrument and (len(sa) == 4 or len(sb) == 4):
                continue
            out.append((a, b))
        return out

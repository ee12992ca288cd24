"""The roll twin of a near-symmetric wristed instrument.

Turned half a turn about its shaft, a grasper looks almost the same: the wrist clevis maps onto itself and
the two jaws trade places. The configuration (roll + 180 deg, -pitch, -yaw, same opening) with the jaws'
labels exchanged then explains an image nearly as well as the true one. On our Large Needle Driver the only
difference is the shaft's groove (1.2 mm wide, 0.45 mm deep, on a black shaft), and the bundled model does
not read it: on the held-out full-reach set, 32 of 36 shaft estimates at |roll| 120-180 deg are this twin
(docs/results/2026-12-05-roll-twin.md). ADD scores a twin as a failure; the kinematics read wrist pitch and
yaw with the wrong sign and the jaws swapped. A single image cannot tell the two apart; in a video only
continuity can, and only from a frame where the right one is known.

Each part's twin pose is its pose turned by 180 deg about its own z axis (``R @ HALF_TURN``, same
translation), taken as the pose of its partner part. That holds when every part's mesh, so turned, matches
its partner's, and when the half turn maps the kinematic chain onto itself (joint axes along or normal to
z, origins on it); :func:`find_roll_twin` checks both on the meshes and the forward kinematics.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
import trimesh

from surftrack.instruments.kinematics import JointState

if TYPE_CHECKING:
    from surftrack.instruments.library import Instrument

#: A part's half turn about its own z axis (the shaft axis at zero pitch and yaw).
HALF_TURN = np.diag([-1.0, -1.0, 1.0])
#: Largest surface deviation (99th percentile, mm) between a half-turned part and its partner for the two
#: to count as one shape: about what a 128-px crop of a part 100 mm from the lens resolves (5 px per mm at
#: f = 480 px). The LND's groove deviates 0.45 mm; the spatula 1.2 mm, the clip applier's bent jaws 1.5,
#: the scissors' curved blades 1.8.
TWIN_TOL_MM = 1.0

Pose = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class RollTwin:
    """``partner``: part -> the part its half-turned mesh matches (itself for a shaft or a clevis).
    ``deviation_mm``: per part, the 99th percentile surface distance between the two."""

    partner: dict[str, str]
    deviation_mm: dict[str, float]

    def closed(self, parts: Iterable[str]) -> bool:
        """Whether ``parts`` hold every one of their partners (a twin of only some of them is undefined)."""
        names = set(parts)
        return all(self.partner[p] in names for p in names)

    def poses(self, poses: Mapping[str, Pose]) -> dict[str, Pose]:
        """The twin's poses ({part: (R (3, 3), t (3,) mm)}, model-to-camera) of the parts in ``poses``,
        which must be :meth:`closed`."""
        if not self.closed(poses):
            raise ValueError(f"the twin of {sorted(poses)} needs their partners too")
        return {self.partner[p]: (np.asarray(R) @ HALF_TURN, np.asarray(t, dtype=np.float64).copy())
                for p, (R, t) in poses.items()}

    def nearer(self, poses: Mapping[str, Pose], cost: Callable[[str, np.ndarray, np.ndarray], float]
               ) -> tuple[dict[str, Pose], bool]:
        """``poses`` (:meth:`closed`) or their twin, whichever has the smaller summed ``cost(part, R, t)``
        (each part's error against its truth): the instrument scored with its twin counted as a symmetry,
        as BOP scores a symmetric object. Returns the chosen poses and whether they are the twin's."""
        turned = self.poses(poses)
        same = sum(cost(p, *pose) for p, pose in poses.items())
        other = sum(cost(p, *pose) for p, pose in turned.items())
        return (turned, True) if other < same else (dict(poses), False)

    @staticmethod
    def joints(q: JointState) -> JointState:
        """The twin's joint state (radians): half a turn more roll, the wrist's angles negated."""
        return JointState(roll=q.roll + np.pi, pitch=-q.pitch, yaw=-q.yaw, opening=q.opening)


def _surface(mesh: trimesh.Trimesh, n: int) -> np.ndarray:
    return np.asarray(trimesh.sample.sample_surface(mesh, n, seed=0)[0], dtype=np.float64)


def find_roll_twin(instrument: Instrument, tol_mm: float = TWIN_TOL_MM, samples: int = 8000) -> RollTwin | None:
    """The instrument's :class:`RollTwin`, or None when some part's half turn matches no part within
    ``tol_mm`` or the forward kinematics of the twin joint state do not give the twin poses. ``samples``
    surface samples per part put the sampling's own share of a deviation near 0.1 mm (about 0.05 s a part;
    :attr:`Instrument.roll_twin` caches it)."""
    names = instrument.part_names
    area = {p: instrument.parts[p].mesh.area for p in names}
    pts = {p: _surface(instrument.parts[p].mesh, samples) for p in names}
    trees = {p: cKDTree(v) for p, v in pts.items()}
    partner: dict[str, str] = {}
    deviation: dict[str, float] = {}
    for p in names:
        turned = pts[p] @ HALF_TURN.T
        turned_tree = cKDTree(turned)
        best = None
        for q in names:
            if abs(area[q] - area[p]) > 0.05 * area[p]:
                continue  # a turn keeps the area: not the partner
            d = max(np.percentile(trees[q].query(turned)[0], 99), np.percentile(turned_tree.query(pts[q])[0], 99))
            if best is None or d < best[0]:
                best = (float(d), q)
        if best is None or best[0] > tol_mm:
            return None
        partner[p], deviation[p] = best[1], best[0]
    if sorted(partner.values()) != sorted(names):
        return None  # not a permutation: two parts would claim the same partner
    from surftrack.instruments.check import random_joint_states  # check imports the library, which imports this

    twin = RollTwin(partner, deviation)
    for q in random_joint_states(instrument, 4):
        poses = {n: (T[:3, :3], T[:3, 3]) for n, T in instrument.forward(np.eye(4), q).items()}
        expect = instrument.forward(np.eye(4), RollTwin.joints(q))
        for n, (R, t) in twin.poses(poses).items():
            if not (np.allclose(R, expect[n][:3, :3], atol=1e-6) and np.allclose(t, expect[n][:3, 3], atol=1e-6)):
                return None
    return twin

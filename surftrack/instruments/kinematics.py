"""Kinematic chain of an articulated instrument.

Joint variables (radians) are the EndoWrist ones: ``roll`` about the shaft axis, wrist ``pitch``, wrist
``yaw`` and jaw ``opening`` (each jaw turns by a fixed fraction of it, +-1/2 for a two-jaw tool). Every
rigid part hangs from its parent by one revolute joint whose angle is a linear combination of the joint
variables, so one description covers two-jaw graspers, scissors and one-piece tips alike.

The base frame is the shaft frame at zero roll: origin on the shaft axis at the wrist pitch axis, +z along
the shaft towards the tip. ``forward`` maps the base pose (base-to-camera) and a joint state to every
part's pose (part-to-camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from surftrack.geometry import rotation_about, se3

JOINT_NAMES = ("roll", "pitch", "yaw", "opening")


@dataclass(frozen=True)
class JointState:
    """The instrument's joint variables, radians."""

    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    opening: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return {n: float(getattr(self, n)) for n in JOINT_NAMES}

    @classmethod
    def from_degrees(cls, **deg: float) -> JointState:
        unknown = set(deg) - set(JOINT_NAMES)
        if unknown:
            raise ValueError(f"unknown joint(s) {sorted(unknown)}; joints are {JOINT_NAMES}")
        return cls(**{k: float(np.radians(v)) for k, v in deg.items()})


@dataclass(frozen=True)
class PartJoint:
    """Revolute joint of one part: ``T_parent_part = T(origin) @ R_fixed @ Rot(axis, sum_k coeff_k * q_k)``.

    ``origin`` (mm) and ``rotation`` (the fixed rotation, row-major 3x3; identity by default) place the
    joint frame in the parent's frame, as a URDF joint's ``<origin xyz rpy>`` does; ``axis`` is expressed
    in the joint frame, which is the part's frame at zero angle."""

    parent: str | None
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    coefficients: dict[str, float] = field(default_factory=dict)
    rotation: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        bad = set(self.coefficients) - set(JOINT_NAMES)
        if bad:
            raise ValueError(f"joint angle refers to unknown joint(s) {sorted(bad)}; joints are {JOINT_NAMES}")
        if np.linalg.norm(self.axis) < 1e-9:
            raise ValueError("joint axis must be non-zero")
        R = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("joint rotation must be a proper rotation")

    def angle(self, q: JointState) -> float:
        return float(sum(c * getattr(q, k) for k, c in self.coefficients.items()))

    def transform(self, q: JointState) -> np.ndarray:
        """Pose of the part in its parent's frame (the base frame for the root part)."""
        fixed = np.asarray(self.rotation, dtype=np.float64).reshape(3, 3)
        return se3(fixed @ rotation_about(self.axis, self.angle(q)), np.asarray(self.origin, dtype=np.float64))


@dataclass(frozen=True)
class JointLimits:
    """Closed interval per joint variable, radians."""

    ranges: dict[str, tuple[float, float]]

    def __post_init__(self) -> None:
        for name, (lo, hi) in self.ranges.items():
            if name not in JOINT_NAMES:
                raise ValueError(f"limit for unknown joint {name!r}; joints are {JOINT_NAMES}")
            if lo > hi:
                raise ValueError(f"joint limit for {name!r} has lower {lo} > upper {hi}")

    def contains(self, q: JointState, tol: float = 1e-9) -> bool:
        return all(lo - tol <= getattr(q, n) <= hi + tol for n, (lo, hi) in self.ranges.items())

    def clip(self, q: JointState) -> JointState:
        vals = q.as_dict()
        for n, (lo, hi) in self.ranges.items():
            vals[n] = float(np.clip(vals[n], lo, hi))
        return JointState(**vals)


class KinematicChain:
    """Tree of parts linked by :class:`PartJoint`; parts are kept in an order where parents come first."""

    def __init__(self, joints: dict[str, PartJoint]):
        roots = [n for n, j in joints.items() if j.parent is None]
        if len(roots) != 1:
            raise ValueError(f"an instrument needs exactly one root part (no parent), found {roots}")
        order: list[str] = []
        pending = dict(joints)
        while pending:
            ready = [n for n, j in pending.items() if j.parent is None or j.parent in order]
            if not ready:
                raise ValueError(f"parts {sorted(pending)} have unknown parents or form a cycle")
            for n in ready:
                order.append(n)
                del pending[n]
        self.joints = joints
        self.order = tuple(order)

    def origin_reach(self, a: str, b: str) -> float:
        """A bound (mm) on how far apart the origins of parts ``a`` and ``b`` can be, whatever the joint
        angles: the summed lengths of the joint offsets on the chain between them (a revolute joint turns
        its part about an axis through its offset's end, so each offset's length is fixed). The LND: 0
        between the shaft and the wrist, 9.1 mm from either to a jaw, 18.2 between the jaws (which share
        their origin: a bound, not the distance). KeyError for a part not in the chain."""
        def up(n: str) -> list[str]:
            path = [n]
            while self.joints[path[-1]].parent is not None:
                path.append(self.joints[path[-1]].parent)
            return path
        pa, pb = up(a), up(b)
        common = next(n for n in pa if n in pb)
        hops = pa[:pa.index(common)] + pb[:pb.index(common)]
        return float(sum(np.linalg.norm(self.joints[n].origin) for n in hops))

    def forward(self, base_pose: np.ndarray, q: JointState) -> dict[str, np.ndarray]:
        """Pose (4x4, part-to-camera) of every part, for base (shaft at zero roll) pose ``base_pose``."""
        poses: dict[str, np.ndarray] = {}
        for name in self.order:
            j = self.joints[name]
            parent = np.asarray(base_pose, dtype=np.float64) if j.parent is None else poses[j.parent]
            poses[name] = parent @ j.transform(q)
        return poses


def rcm_base_pose(trocar: np.ndarray, pitch_point: np.ndarray, roll_reference: np.ndarray | None = None) -> np.ndarray:
    """Base pose (zero-roll shaft frame to camera) of a shaft that passes through the ``trocar`` (remote
    centre of motion) and has its wrist pitch axis at ``pitch_point`` (both camera frame, mm).

    The shaft's +z points from the trocar to the pitch point. The base x axis is the component of
    ``roll_reference`` (default: camera +z, the viewing direction) orthogonal to the shaft, so zero roll is
    a well-defined, smooth function of the shaft direction; roll then turns about the shaft.
    """
    # plain floats: the instrument fit builds this pose several times per solver iteration
    px, py, pz = (float(v) for v in np.asarray(pitch_point, dtype=np.float64).reshape(3))
    tx, ty, tz = (float(v) for v in np.asarray(trocar, dtype=np.float64).reshape(3))
    zx, zy, zz = px - tx, py - ty, pz - tz
    n = math.sqrt(zx * zx + zy * zy + zz * zz)
    if n < 1e-6:
        raise ValueError("the pitch point must differ from the trocar point")
    zx, zy, zz = zx / n, zy / n, zz / n
    rx, ry, rz = (0.0, 0.0, 1.0) if roll_reference is None else (
        float(v) for v in np.asarray(roll_reference, dtype=np.float64).reshape(3))
    dot = rx * zx + ry * zy + rz * zz
    xx, xy, xz = rx - zx * dot, ry - zy * dot, rz - zz * dot
    if math.sqrt(xx * xx + xy * xy + xz * xz) < 1e-6:  # shaft along the reference: any perpendicular will do
        ax, ay, az = (1.0, 0.0, 0.0) if abs(zx) < 0.9 else (0.0, 1.0, 0.0)
        xx, xy, xz = zy * az - zz * ay, zz * ax - zx * az, zx * ay - zy * ax
    m = math.sqrt(xx * xx + xy * xy + xz * xz)
    xx, xy, xz = xx / m, xy / m, xz / m
    yx, yy, yz = zy * xz - zz * xy, zz * xx - zx * xz, zx * xy - zy * xx
    return np.array([[xx, yx, zx, px], [xy, yy, zy, py], [xz, yz, zz, pz], [0.0, 0.0, 0.0, 1.0]])

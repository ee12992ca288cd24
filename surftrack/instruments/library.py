"""Instruments described in YAML (``configs/instruments/*.yaml``): built-in procedural ones and a user's CAD.

A description names the parts in kinematic order, each with a mesh (a procedural ``builder`` with its
parameters, or a CAD ``file`` with its ``units``), the revolute joint that carries it, a material,
extra keypoints and render-only ``attachments`` (the long shaft tube towards the trocar). Joint limits are
given in degrees. See ``configs/instruments/large_needle_driver.yaml`` for a complete example.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
import trimesh
import yaml

from surftrack.configio import yaml_problem
from surftrack.geometry import transform_points
from surftrack.instruments.cad import (
    ROTATION_KEYS,
    UNITS_TO_MM,
    cut_shaft,
    load_cad_mesh,
    rotation_from_spec,
    vector_from_spec,
)
from surftrack.instruments.kinematics import JOINT_NAMES, JointLimits, JointState, KinematicChain, PartJoint
from surftrack.instruments.part import Material, Part
from surftrack.instruments.procedural import build, finish
from surftrack.instruments.twin import RollTwin, find_roll_twin
from surftrack.paths import configs_dir

INSTRUMENTS_ENV = "SURFTRACK_INSTRUMENTS"


class InstrumentError(ValueError):
    """A malformed instrument description; the message names the file and the problem."""


@dataclass(eq=False)
class Attachment:
    """A render-only mesh rigidly attached to a part (mm, in that part's frame)."""

    part: str
    mesh: trimesh.Trimesh


@dataclass(eq=False)
class Instrument:
    """An articulated instrument: rigid parts (parents first), their kinematic chain and joint limits."""

    name: str
    parts: dict[str, Part]
    chain: KinematicChain
    limits: JointLimits
    description: str = ""
    aliases: tuple[str, ...] = ()
    attachments: list[Attachment] = field(default_factory=list)
    source: Path | None = None
    derived_tips: tuple[str, ...] = ()  # parts whose ``tip`` keypoint was derived from the mesh

    @property
    def part_names(self) -> tuple[str, ...]:
        return self.chain.order

    def reach(self) -> dict[str, tuple[float, float]]:
        """Where each joint moves (radians), what synthesis draws from and ``instruments --check`` tries:
        its limits; the roll within one turn (it is periodic; centred on 0 where the limits allow); the
        opening from closed (0: a negative opening clamps the jaws into each other); a joint without a
        limit held at 0."""
        out = {n: self.limits.ranges.get(n, (0.0, 0.0)) for n in JOINT_NAMES}
        lo, hi = out["roll"]
        if hi - lo >= 2 * np.pi:
            centre = float(np.clip(0.0, lo + np.pi, hi - np.pi))
            out["roll"] = (centre - np.pi, centre + np.pi)
        lo, hi = out["opening"]
        out["opening"] = (min(max(lo, 0.0), hi), hi)
        return out

    @cached_property
    def roll_twin(self) -> RollTwin | None:
        """The configuration that looks the same turned half a turn about the shaft, with the jaws
        exchanged (:mod:`surftrack.instruments.twin`); None for an instrument without one."""
        return find_roll_twin(self)

    @property
    def rest(self) -> JointState:
        """The rest configuration: all joints zero, clipped to the limits."""
        return self.limits.clip(JointState())

    def forward(self, base_pose: np.ndarray, q: JointState) -> dict[str, np.ndarray]:
        """Pose (part-to-camera, 4x4) of every part for the base (zero-roll shaft frame) pose."""
        return self.chain.forward(base_pose, q)

    def tool_tip(self, poses: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
        """The tool tip for part poses ``poses`` (part-to-camera, 4x4, mm): (R 3x3, t (3,) mm), ``t`` the mean
        of the distal parts' ``tip`` keypoints (between the jaw tips of a grasper) and ``R`` the orientation
        of the part they hang from (the wrist); None without a posed tip."""
        parents = {j.parent for j in self.chain.joints.values()}
        tips = [n for n, p in self.parts.items() if n not in parents and "tip" in p.keypoints and n in poses]
        if not tips:
            return None
        t = np.mean([transform_points(poses[n], self.parts[n].keypoints["tip"][None])[0] for n in tips], axis=0)
        holder = self.chain.joints[tips[0]].parent or tips[0]
        return poses[holder if holder in poses else tips[0]][:3, :3].copy(), t

    def keypoints(self, poses: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Camera-frame position of every named keypoint, keyed ``part/keypoint``."""
        out = {}
        for pname, part in self.parts.items():
            for kname, p in part.keypoints.items():
                out[f"{pname}/{kname}"] = transform_points(poses[pname], p[None])[0]
        return out


TOP_KEYS = ("name", "aliases", "description", "joint_limits_deg", "parts")
PART_KEYS = ("name", "parent", "mesh", "joint", "material", "keypoints", "attachments")
FILE_MESH_KEYS = ("file", "units", "origin", *ROTATION_KEYS, "scale", "shaft_length_mm")
JOINT_KEYS = ("axis", "origin", *ROTATION_KEYS, "angle")
MATERIAL_KEYS = ("color", "metallic", "roughness")


def _known_keys(spec: object, known: Sequence[str], where: str) -> dict:
    """``spec`` as a mapping whose keys are all in ``known``; :class:`InstrumentError` naming the first
    unknown key (a typo such as ``rotation:`` for ``rpy:`` must not be silently ignored)."""
    if spec is None:
        return {}
    if not isinstance(spec, Mapping):
        raise InstrumentError(f"{where}: expected a mapping of {', '.join(known)}, got {spec!r}")
    for key in spec:
        if key not in known:
            raise InstrumentError(f"{where}: unknown key {key!r} (known: {', '.join(known)})")
    return dict(spec)


def _load_mesh(spec: object, base: Path, where: str) -> tuple[trimesh.Trimesh, dict[str, np.ndarray],
                                                             trimesh.Trimesh | None]:
    """(mesh in mm in the part frame, its builder's keypoints, the piece cut off by ``shaft_length_mm``
    or None). ``spec`` is a builder with its parameters, a CAD file with ``units`` and an optional
    transform (:mod:`surftrack.instruments.cad`), or a list of CAD files joined into one part."""
    if isinstance(spec, list):
        if not spec:
            raise InstrumentError(f"{where}: an empty list of meshes")
        loaded = [_load_mesh(s, base, f"{where} #{k}") for k, s in enumerate(spec)]
        rest = [cut for _, _, cut in loaded if cut is not None]
        kps = {k: v for _, item_kps, _ in loaded for k, v in item_kps.items()}
        return (finish(trimesh.util.concatenate([m for m, _, _ in loaded])), kps,
                trimesh.util.concatenate(rest) if rest else None)
    if isinstance(spec, Mapping) and "builder" in spec:
        params = {k: v for k, v in spec.items() if k != "builder"}
        try:
            mesh, kps = build(spec["builder"], **params)
        except (ValueError, TypeError) as e:
            raise InstrumentError(f"{where}: {e}") from None
        return mesh, kps, None
    spec = _known_keys(spec, FILE_MESH_KEYS, where)
    if "file" not in spec:
        raise InstrumentError(f"{where}: a mesh needs either 'builder' or 'file' (+ 'units')")
    path = Path(str(spec["file"])).expanduser()
    path = path if path.is_absolute() else base / path
    units = spec.get("units")
    if not isinstance(units, str) or units not in UNITS_TO_MM:
        raise InstrumentError(f"{where}: mesh 'units' must be one of {sorted(UNITS_TO_MM)}, got {units!r}")
    if not path.is_file():
        raise InstrumentError(f"{where}: mesh file {path} does not exist")
    try:
        mesh = load_cad_mesh(path, units, spec, where)
    except ValueError as e:  # MeshFileError included
        raise InstrumentError(str(e) if str(e).startswith(where) else f"{where}: {e}") from None
    mesh, rest = finish(mesh), None
    if "shaft_length_mm" in spec:
        length = spec["shaft_length_mm"]
        if not isinstance(length, (int, float)) or isinstance(length, bool) or not length > 0:
            raise InstrumentError(f"{where}: shaft_length_mm must be a positive number of mm, got {length!r}")
        try:
            mesh, rest = cut_shaft(mesh, float(length))
        except ValueError as e:
            raise InstrumentError(f"{where}: {e}") from None
    return mesh, {}, rest


def _joint(spec: object, parent: object, where: str) -> PartJoint:
    j = _known_keys(spec, JOINT_KEYS, f"{where} joint")
    try:
        rotation = rotation_from_spec(j, f"{where} joint")
        origin = vector_from_spec(j, "origin", f"{where} joint")
        axis = vector_from_spec(j, "axis", f"{where} joint", (0.0, 0.0, 1.0))
        angle = j.get("angle") or {}
        if not isinstance(angle, Mapping):
            raise ValueError(f"{where} joint: angle must map joint names to coefficients, e.g. {{yaw: 1.0}}")
        return PartJoint(parent=None if parent is None else str(parent), origin=tuple(origin), axis=tuple(axis),
                         coefficients={str(k): float(v) for k, v in angle.items()},
                         rotation=tuple(rotation.ravel()))
    except (ValueError, TypeError) as e:
        msg = str(e)
        raise InstrumentError(msg if msg.startswith(where) else f"{where} joint: {msg}") from None


def load_instrument_file(path: str | Path) -> Instrument:
    """Build an :class:`Instrument` from its YAML description. Every key is checked: an unknown one is an
    :class:`InstrumentError` naming it and the file."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise InstrumentError(f"{path}: cannot read instrument description: {yaml_problem(e)}") from None
    if not isinstance(doc, dict) or not doc.get("parts"):
        raise InstrumentError(f"{path}: an instrument description needs 'name' and a list of 'parts'")
    _known_keys(doc, TOP_KEYS, str(path))
    _, aliases = _checked_names(doc, path)
    limits_deg = _known_keys(doc.get("joint_limits_deg"), JOINT_NAMES, f"{path}: joint_limits_deg")
    try:
        limits = JointLimits({k: (float(np.radians(lo)), float(np.radians(hi))) for k, (lo, hi) in limits_deg.items()})
    except (ValueError, TypeError) as e:
        raise InstrumentError(f"{path}: joint_limits_deg: {e}") from None
    if not isinstance(doc["parts"], list):
        raise InstrumentError(f"{path}: 'parts' must be a list of parts")
    parts: dict[str, Part] = {}
    joints: dict[str, PartJoint] = {}
    attachments: list[Attachment] = []
    for i, p in enumerate(doc["parts"]):
        name = p.get("name") if isinstance(p, dict) else None
        if not name:
            raise InstrumentError(f"{path}: part #{i} has no 'name'")
        if name in parts:
            raise InstrumentError(f"{path}: part name {name!r} is used twice")
        where = f"{path}: part {name!r}"
        _known_keys(p, PART_KEYS, where)
        mesh, kps, rest = _load_mesh(p.get("mesh", {}), path.parent, f"{where} mesh")
        if rest is not None:
            attachments.append(Attachment(name, rest))
        user_kps = p.get("keypoints") or {}
        if not isinstance(user_kps, Mapping):
            raise InstrumentError(f"{where} keypoints: expected a mapping of names to [x, y, z] (mm)")
        try:
            kps.update({str(k): vector_from_spec(user_kps, k, f"{where} keypoints") for k in user_kps})
        except ValueError as e:
            raise InstrumentError(str(e)) from None
        joints[name] = _joint(p.get("joint"), p.get("parent"), where)
        mat = _known_keys(p.get("material"), MATERIAL_KEYS, f"{where} material")
        try:
            if "color" in mat:
                mat["color"] = tuple(float(c) for c in mat["color"])
            parts[name] = Part(name, mesh, Material(**mat), kps)
        except (ValueError, TypeError) as e:
            raise InstrumentError(f"{where}: {e}") from None
        for k, a in enumerate(p.get("attachments") or []):
            amesh, _, cut = _load_mesh(a, path.parent, f"{where} attachment #{k}")
            if cut is not None:
                raise InstrumentError(f"{where} attachment #{k}: shaft_length_mm cuts a tracked part's mesh; an "
                                      f"attachment is rendered whole")
            attachments.append(Attachment(name, amesh))
    try:
        chain = KinematicChain(joints)
    except ValueError as e:
        raise InstrumentError(f"{path}: {e}") from None
    inst = Instrument(
        name=str(doc["name"]), parts={n: parts[n] for n in chain.order}, chain=chain, limits=limits,
        description=str(doc.get("description", "")), aliases=tuple(aliases),
        attachments=attachments, source=path,
    )
    inst.derived_tips = tuple(derive_tips(inst))
    return inst


def tool_axis_in_part(instrument: Instrument, part: str) -> np.ndarray:
    """Unit direction (3,) of the tool's axis (the shaft's +z, towards the tip) in ``part``'s frame at the
    rest configuration (all joints zero)."""
    pose = instrument.chain.forward(np.eye(4), instrument.rest)[part]
    return pose[:3, :3].T @ np.array([0.0, 0.0, 1.0])


def derive_tips(instrument: Instrument) -> list[str]:
    """Give every distal part (one no other part hangs from) without a ``tip`` keypoint one: its vertex
    farthest along the tool's axis at rest. Synthesis places and frames the tool by its tips. Returns the
    parts that got one."""
    parents = {j.parent for j in instrument.chain.joints.values()}
    derived = []
    for name, part in instrument.parts.items():
        if name in parents or "tip" in part.keypoints:
            continue
        v = np.asarray(part.mesh.vertices)
        part.keypoints["tip"] = v[int(np.argmax(v @ tool_axis_in_part(instrument, name)))].astype(np.float64)
        derived.append(name)
    return derived


@dataclass(frozen=True)
class InstrumentRegistry:
    """Where instrument names are looked up: the built-in descriptions (``configs/instruments``) and then a
    user's YAML files or folders of them (``user``, in order; where two claim a name, the first wins).

    Passed down explicitly rather than read from the environment, so that one process can hold several
    (a test, a notebook, a command with ``--instrument``). The command line builds it once from
    ``$SURFTRACK_INSTRUMENTS`` (:meth:`from_env`) and puts ``--instrument`` files ahead (:meth:`ahead`).
    Hashable and picklable: spawned workers and caches take it as it is."""

    user: tuple[Path, ...] = ()

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> InstrumentRegistry:
        """The registry named by ``$SURFTRACK_INSTRUMENTS`` (files or folders of ``*.yaml``, separated by
        ``os.pathsep``) in ``environ`` (default ``os.environ``)."""
        value = (os.environ if environ is None else environ).get(INSTRUMENTS_ENV, "")
        return cls(tuple(Path(e) for e in value.split(os.pathsep) if e))

    def ahead(self, files: Sequence[str | Path]) -> InstrumentRegistry:
        """This registry with ``files`` (instrument YAML files, checked here) searched first."""
        for f in files:
            if not Path(f).is_file():
                raise InstrumentError(f"{f}: no such instrument description (a YAML file)")
            load_instrument_file(f)  # a malformed description fails here, naming the file
        return InstrumentRegistry(tuple(Path(f).resolve() for f in files) + self.user)

    def user_files(self) -> list[Path]:
        """The user's description files, in search order. Raises :class:`InstrumentError` for an entry
        that does not exist."""
        files: list[Path] = []
        for p in self.user:
            if p.is_dir():
                files += sorted(p.glob("*.yaml")) + sorted(p.glob("*.yml"))
            elif p.is_file():
                files.append(p)
            else:
                raise InstrumentError(f"{p}: instrument description not found (from ${INSTRUMENTS_ENV} or "
                                      "--instrument)")
        return files

    def files(self) -> dict[str, Path]:
        """Known instrument descriptions, keyed by name and by alias. A user's description may not claim a
        built-in name or alias: that raises :class:`InstrumentError` naming both files."""
        return {key: f for key, (f, _) in self._known().items()}

    def names(self) -> list[str]:
        """Names (not aliases) of the known instruments."""
        return sorted({name for _, name in self._known().values()})

    def path(self, name_or_path: str | Path) -> Path:
        """The description file of a known instrument (name or alias, e.g. ``lnd``), or the YAML path
        itself; :class:`InstrumentError` when there is none."""
        p = Path(name_or_path)
        if p.suffix in (".yaml", ".yml"):
            if not p.is_file():
                raise InstrumentError(f"{p}: instrument description not found")
            return p
        files = self.files()
        if str(name_or_path) not in files:
            raise InstrumentError(f"unknown instrument {str(name_or_path)!r}; known: {', '.join(sorted(files))} "
                                  f"(give its YAML file, pass it with --instrument, or list it in "
                                  f"${INSTRUMENTS_ENV})")
        return files[str(name_or_path)]

    def load(self, name_or_path: str | Path) -> Instrument:
        """A known instrument by name or alias, or one described by a YAML file path. Cached per file
        and modification time; treat the result as read-only."""
        p = self.path(name_or_path).resolve()
        return _load_cached(str(p), p.stat().st_mtime)

    def _known(self) -> dict[str, tuple[Path, str]]:
        out: dict[str, tuple[Path, str]] = {}
        builtin: set[str] = set()
        for user, f in ([(False, f) for f in sorted((configs_dir() / "instruments").glob("*.yaml"))]
                        + [(True, f) for f in self.user_files()]):
            try:
                doc = yaml.safe_load(f.read_text())
            except (OSError, yaml.YAMLError) as e:
                raise InstrumentError(f"{f}: cannot read instrument description: {yaml_problem(e)}") from None
            if not isinstance(doc, dict):
                raise InstrumentError(f"{f}: an instrument description needs 'name' and a list of 'parts'")
            name, aliases = _checked_names(doc, f)
            for key in [name, *aliases]:
                if not user:
                    out[key] = (f, name)
                    builtin.add(key)
                elif key in builtin and out[key][0].resolve() != f.resolve():
                    raise InstrumentError(f"{f}: {key!r} is the built-in instrument described in {out[key][0]}; "
                                          "give your instrument another name and aliases")
                else:
                    out.setdefault(key, (f, name))
        return out


#: The built-in instruments only: what library calls use when given no registry.
BUILTIN = InstrumentRegistry()


def _checked_names(doc: dict, where: Path) -> tuple[str, list[str]]:
    """(name, aliases) of a parsed description, or :class:`InstrumentError` naming ``where``."""
    if not isinstance(doc.get("name"), str) or not doc["name"]:
        raise InstrumentError(f"{where}: an instrument description needs 'name' and a list of 'parts'")
    aliases = doc.get("aliases") or []
    if not isinstance(aliases, list) or not all(isinstance(a, str) and a for a in aliases):
        raise InstrumentError(f"{where}: 'aliases' must be a list of names, e.g. [lnd]")
    return doc["name"], aliases


def instrument_files(registry: InstrumentRegistry = BUILTIN) -> dict[str, Path]:
    """:meth:`InstrumentRegistry.files` of ``registry`` (default: the built-in instruments)."""
    return registry.files()


def list_instruments(registry: InstrumentRegistry = BUILTIN) -> list[str]:
    """:meth:`InstrumentRegistry.names` of ``registry`` (default: the built-in instruments)."""
    return registry.names()


@lru_cache(maxsize=32)
def _load_cached(path: str, mtime: float) -> Instrument:
    return load_instrument_file(path)


def load_instrument(name_or_path: str | Path, registry: InstrumentRegistry = BUILTIN) -> Instrument:
    """A known instrument by name or alias (``lnd``) in ``registry`` (default: the built-in ones), or one
    described by a YAML file path; see :meth:`InstrumentRegistry.load`."""
    return registry.load(name_or_path)


__all__ = ["BUILTIN", "Attachment", "Instrument", "InstrumentError", "InstrumentRegistry", "JOINT_NAMES",
           "load_instrument", "load_instrument_file", "list_instruments", "instrument_files", "INSTRUMENTS_ENV"]

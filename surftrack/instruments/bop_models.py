"""BOP ``models/`` folders: one PLY per rigid part (mm, with normals) plus ``models_info.json``.

``models_info.json`` holds bop_toolkit's keys (``diameter`` = max pairwise vertex distance, ``min_x``..,
``size_x``..) and, as extra keys that bop_toolkit passes through, the instrument and part names, the
bounding-box-diagonal diameter (SurgRIPE's convention), the mesh hash and the part keypoints.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from surftrack.atomic import write_atomic
from surftrack.instruments.library import Instrument
from surftrack.instruments.part import Part


def model_info(part: Part) -> dict:
    """bop_toolkit's per-model record for ``part`` (mm)."""
    lo, hi = part.mesh.bounds
    size = hi - lo
    return {
        "diameter": part.diameter_max_pairwise,
        "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
        "size_x": float(size[0]), "size_y": float(size[1]), "size_z": float(size[2]),
    }


def assign_obj_ids(instruments: list[Instrument], first_id: int = 1) -> dict[int, tuple[Instrument, str]]:
    """Consecutive BOP object ids for every part of every instrument, in the given order."""
    ids: dict[int, tuple[Instrument, str]] = {}
    for inst in instruments:
        for pname in inst.part_names:
            ids[first_id + len(ids)] = (inst, pname)
    return ids


def export_bop_models(instruments: list[Instrument], out_dir: str | Path, first_id: int = 1) -> dict[int, tuple[str, str]]:
    """Write ``out_dir/obj_XXXXXX.ply`` and ``models_info.json``; returns obj_id -> (instrument, part)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info: dict[str, dict] = {}
    names: dict[int, tuple[str, str]] = {}
    for obj_id, (inst, pname) in assign_obj_ids(instruments, first_id).items():
        part = inst.parts[pname]
        ply = trimesh.exchange.ply.export_ply(part.mesh, encoding="binary", vertex_normal=True)
        write_atomic(out / f"obj_{obj_id:06d}.ply", ply)
        rec = model_info(part)
        rec.update({
            "instrument": inst.name, "part": pname,
            "diameter_bbox_diagonal": part.diameter_bbox_diagonal,
            "mesh_sha256": part.mesh_hash,
            "keypoints": {k: v.tolist() for k, v in part.keypoints.items()},
        })
        info[str(obj_id)] = rec
        names[obj_id] = (inst.name, pname)
    write_atomic(out / "models_info.json", json.dumps(info, indent=2))
    return names


def load_bop_models(models_dir: str | Path) -> dict[int, Part]:
    """Parts of a BOP ``models/`` folder (ours or any BOP dataset's), keyed by obj id.

    Part names come from our extra keys when present, else ``obj_XXXXXX``. A model file that cannot be
    read raises ``ValueError`` naming it.
    """
    d = Path(models_dir)
    info_path = d / "models_info.json"
    if not info_path.is_file():
        raise FileNotFoundError(f"{info_path}: models_info.json is missing")
    info = json.loads(info_path.read_text())
    parts: dict[int, Part] = {}
    for key, rec in sorted(info.items(), key=lambda kv: int(kv[0])):
        obj_id = int(key)
        ply = d / f"obj_{obj_id:06d}.ply"
        if not ply.is_file():
            raise FileNotFoundError(f"{ply}: model listed in models_info.json is missing")
        try:
            mesh = trimesh.load(ply, force="mesh", process=False)
        except Exception as e:  # noqa: BLE001 - a mesh reader's errors are many kinds; one line names the file
            raise ValueError(f"{ply}: cannot read the model ({type(e).__name__}: {e})") from None
        kps = {k: np.asarray(v) for k, v in rec.get("keypoints", {}).items()}
        try:
            parts[obj_id] = Part(rec.get("part", f"obj_{obj_id:06d}"), mesh, keypoints=kps)
        except ValueError as e:  # an empty or degenerate mesh (a file cut off mid-write)
            raise ValueError(f"{ply}: cannot read the model ({e})") from None
    return parts

"""Reading BOP-format datasets (ours, bop_toolkit's, SynSurg6D's) as a flat list of object instances.

Layout (bop_toolkit's, see ``docs`` / notes section 2)::

    <root>/models/models_info.json + obj_XXXXXX.ply        (mm; obj ids as in models_info.json)
      or  <root>/models/000000.ply, 000001.ply, ...        (SynSurg6D's flat layout: obj id = index + 1;
                                                             models_info.json optional)
    <root>/<split>/<scene 06d>/scene_camera.json            {im: {cam_K (9, row-major), depth_scale}}
                              /scene_gt.json                {im: [{obj_id, cam_R_m2c (9), cam_t_m2c (mm)}, ...]}
                              /scene_gt_info.json           {im: [{bbox_obj, bbox_visib, px_count_visib,
                                                                   visib_fract, ...}, ...]}
                              /rgb/<im 06d>.{png,jpg}
                              /mask_visib/<im 06d>_<gt 06d>.png   (0/255; read on demand)
                              /depth/<im 06d>.png           (optional; uint16 * depth_scale = mm)

Extra keys of ``scene_gt.json`` entries (our instrument, part, joints_deg, ...) are kept in
:attr:`Instance.extra`. Every problem is reported as one :class:`DatasetError` naming the file.

:func:`import_surgripe` rearranges a SurgRIPE-style folder (images + 3x4 [R|t] poses in mm + optional
masks) into this layout, so the rest of the pipeline reads it like any BOP dataset.
"""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh

from surftrack.geometry import PinholeCamera
from surftrack.instruments.bop_models import load_bop_models, model_info
from surftrack.instruments.cad import read_mesh_file
from surftrack.instruments.part import Part

RGB_EXTS = (".png", ".jpg", ".jpeg")
_SCENE_RE = re.compile(r"^\d{6}$")
_FLAT_RE = re.compile(r"^\d{6}\.ply$")


class DatasetError(ValueError):
    """A missing, malformed or empty dataset; the message names the file or the filter at fault."""


@dataclass(eq=False)
class Instance:
    """One annotated object in one image. ``R`` (3, 3) and ``t`` (3,) mm map model to camera; boxes are
    BOP's [x, y, w, h] with ``w = xmax - xmin`` over pixel indices (see :func:`surftrack.geometry.box_from_bop`)."""

    scene_id: int
    im_id: int
    gt_index: int
    obj_id: int
    R: np.ndarray
    t: np.ndarray
    K: np.ndarray
    bbox_visib: tuple[int, int, int, int]
    bbox_obj: tuple[int, int, int, int]
    visib_fract: float
    px_count_visib: int
    extra: dict = field(default_factory=dict)

    @property
    def pose(self) -> np.ndarray:
        """4x4 model-to-camera pose (mm)."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T

    def camera(self, width: int, height: int) -> PinholeCamera:
        return PinholeCamera(self.K, width, height)


def read_json(path: Path):
    """Parsed JSON of ``path``; a :class:`DatasetError` naming the file if missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file is missing")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: malformed JSON ({e})") from None


# ---------------------------------------------------------------------- models
def models_layout(models_dir: Path) -> str:
    """``"bop"`` (obj_XXXXXX.ply + models_info.json) or ``"flat"`` (0-based 000000.ply); else an error."""
    d = Path(models_dir)
    if not d.is_dir():
        raise DatasetError(f"{d}: models folder is missing (expected obj_XXXXXX.ply + models_info.json, "
                           f"or SynSurg6D's 000000.ply, 000001.ply, ...)")
    names = [p.name for p in d.iterdir()]
    if any(n.startswith("obj_") and n.endswith(".ply") for n in names):
        if "models_info.json" not in names:
            raise DatasetError(f"{d / 'models_info.json'}: models_info.json is missing (needed beside obj_XXXXXX.ply)")
        return "bop"
    if any(_FLAT_RE.match(n) for n in names):
        return "flat"
    raise DatasetError(f"{d}: no models: expected obj_XXXXXX.ply + models_info.json (BOP) or 000000.ply, "
                       f"000001.ply, ... (SynSurg6D, obj id = index + 1)")


def load_models(models_dir: str | Path) -> dict[int, Part]:
    """Parts of a ``models/`` folder in either layout (see :func:`models_layout`), keyed by obj id."""
    d = Path(models_dir)
    layout = models_layout(d)
    if layout == "bop":
        read_json(d / "models_info.json")  # malformed JSON -> DatasetError naming the file
        try:
            return load_bop_models(d)
        except FileNotFoundError as e:
            raise DatasetError(str(e)) from None
        except ValueError as e:  # a truncated or empty mesh, a part it cannot describe
            raise DatasetError(f"{d}: cannot load the models ({e})") from None
    files = sorted(p for p in d.iterdir() if _FLAT_RE.match(p.name))
    idx = [int(p.stem) for p in files]
    if idx != list(range(len(files))):
        missing = sorted(set(range(max(idx) + 1)) - set(idx))
        raise DatasetError(f"{d}: flat model layout needs consecutive 000000.ply, 000001.ply, ...; "
                           f"missing {[f'{i:06d}.ply' for i in missing]}")
    info = read_json(d / "models_info.json") if (d / "models_info.json").is_file() else {}
    parts: dict[int, Part] = {}
    for i, p in enumerate(files):
        try:
            mesh = read_mesh_file(p)
        except ValueError as e:
            raise DatasetError(str(e)) from None
        rec = info.get(str(i + 1), {})
        kps = {k: np.asarray(v) for k, v in rec.get("keypoints", {}).items()}
        parts[i + 1] = Part(rec.get("part", f"obj_{i + 1:06d}"), mesh, keypoints=kps)
    return parts


# ---------------------------------------------------------------------- dataset
def _bbox(v, where: str) -> tuple[int, int, int, int]:
    if v is None or len(v) != 4:
        raise DatasetError(f"{where}: bbox must be [x, y, w, h], got {v}")
    return tuple(int(round(float(x))) for x in v)


class BopDataset:
    """The instances of one split of a BOP dataset, filtered; see the module docstring.

    ``obj_ids`` keeps only those objects; ``min_visib_fract`` and ``min_px_visib`` drop instances with a
    smaller visible fraction / fewer visible pixels (BOP's ``visib_fract``, ``px_count_visib``).
    ``models`` maps obj id -> :class:`Part` (all objects of the dataset, not only ``obj_ids``).
    """

    def __init__(self, root: str | Path, split: str = "train", obj_ids: list[int] | None = None,
                 min_visib_fract: float = 0.1, min_px_visib: int = 64, load_models_now: bool = True):
        self.root = Path(root)
        self.split = split
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: dataset root is missing")
        self.models_dir = self.root / "models"
        self.models: dict[int, Part] = load_models(self.models_dir) if load_models_now else {}
        split_dir = self.root / split
        if not split_dir.is_dir():
            others = sorted(p.name for p in self.root.iterdir() if p.is_dir() and p.name != "models")
            raise DatasetError(f"{split_dir}: split folder is missing (folders here: {others})")
        scenes = sorted(int(p.name) for p in split_dir.iterdir() if p.is_dir() and _SCENE_RE.match(p.name))
        if not scenes:
            raise DatasetError(f"{split_dir}: no scene folders (<scene 06d>/) in split {split!r}")
        self._rgb_ext: dict[int, dict[int, str]] = {}
        self._depth_scale: dict[tuple[int, int], float] = {}
        all_inst: list[Instance] = []
        for s in scenes:
            all_inst += self._read_scene(s)
        self.obj_ids = None if obj_ids is None else [int(o) for o in obj_ids]
        if self.obj_ids is not None and self.models:
            unknown = sorted(set(self.obj_ids) - set(self.models))
            if unknown:
                raise DatasetError(f"{self.models_dir}: obj_ids {unknown} have no model (models: {sorted(self.models)})")
        kept = all_inst
        counts = [("instances in the split", len(kept))]
        if self.obj_ids is not None:
            kept = [i for i in kept if i.obj_id in self.obj_ids]
            counts.append((f"obj_ids={self.obj_ids} (dataset has {sorted({i.obj_id for i in all_inst})})", len(kept)))
        kept = [i for i in kept if i.visib_fract >= min_visib_fract]
        counts.append((f"min_visib_fract={min_visib_fract}", len(kept)))
        kept = [i for i in kept if i.px_count_visib >= min_px_visib]
        counts.append((f"min_px_visib={min_px_visib}", len(kept)))
        if not kept:
            steps = "; ".join(f"{name}: {n} left" for name, n in counts)
            culprit = next((name for name, n in counts if n == 0), counts[0][0])
            raise DatasetError(f"{split_dir}: no instances left after filtering (removed by {culprit}); {steps}")
        self.filter_counts = counts
        self.instances: list[Instance] = kept

    def _read_scene(self, scene_id: int) -> list[Instance]:
        d = self.root / self.split / f"{scene_id:06d}"
        gts = read_json(d / "scene_gt.json")
        cams = read_json(d / "scene_camera.json")
        infos = read_json(d / "scene_gt_info.json")
        rgb_dir = d / "rgb"
        if not rgb_dir.is_dir():
            raise DatasetError(f"{rgb_dir}: rgb folder is missing")
        present = {p.stem: p.suffix for p in rgb_dir.iterdir() if p.suffix.lower() in RGB_EXTS}
        exts: dict[int, str] = {}
        out: list[Instance] = []
        bad = [key for key in gts if not str(key).isdigit()]
        if bad:
            raise DatasetError(f"{d / 'scene_gt.json'}: image keys must be image numbers, got {bad[:3]}")
        for key in sorted(gts, key=int):
            im = int(key)
            name = f"{im:06d}"
            if name not in present:
                raise DatasetError(f"{rgb_dir / name}.png|.jpg: image listed in {d / 'scene_gt.json'} is missing")
            exts[im] = present[name]
            if key not in cams:
                raise DatasetError(f"{d / 'scene_camera.json'}: no entry for image {im}")
            if key not in infos or len(infos[key]) != len(gts[key]):
                raise DatasetError(f"{d / 'scene_gt_info.json'}: image {im} needs one entry per scene_gt.json "
                                   f"entry ({len(gts[key])})")
            cam = cams[key]
            try:
                K = np.asarray(cam["cam_K"], dtype=np.float64).reshape(3, 3)
                self._depth_scale[(scene_id, im)] = float(cam.get("depth_scale", 1.0))
            except (KeyError, ValueError) as e:
                raise DatasetError(f"{d / 'scene_camera.json'}: image {im}: bad cam_K ({e})") from None
            for k, (gt, info) in enumerate(zip(gts[key], infos[key])):
                try:
                    R = np.asarray(gt["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
                    t = np.asarray(gt["cam_t_m2c"], dtype=np.float64).reshape(3)
                    obj_id = int(gt["obj_id"])
                except (KeyError, ValueError, TypeError) as e:
                    raise DatasetError(f"{d / 'scene_gt.json'}: image {im} entry {k}: bad or missing {e}") from None
                try:
                    inst = Instance(
                        scene_id, im, k, obj_id, R, t, K,
                        _bbox(info["bbox_visib"], f"{d / 'scene_gt_info.json'} image {im} entry {k}"),
                        _bbox(info.get("bbox_obj", info["bbox_visib"]), f"{d / 'scene_gt_info.json'} image {im} entry {k}"),
                        float(info["visib_fract"]), int(info["px_count_visib"]),
                        {a: b for a, b in gt.items() if a not in ("obj_id", "cam_R_m2c", "cam_t_m2c")})
                except KeyError as e:
                    raise DatasetError(f"{d / 'scene_gt_info.json'}: image {im} entry {k}: missing key {e}") from None
                except (TypeError, ValueError) as e:
                    raise DatasetError(f"{d / 'scene_gt_info.json'}: image {im} entry {k}: bad value ({e})") from None
                if self.models and obj_id not in self.models:
                    raise DatasetError(f"{d / 'scene_gt.json'}: image {im} entry {k}: obj_id {obj_id} has no model in "
                                       f"{self.models_dir} (models: {sorted(self.models)})")
                out.append(inst)
        self._rgb_ext[scene_id] = exts
        return out

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.instances)

    def __getitem__(self, i: int) -> Instance:
        return self.instances[i]

    def scene_dir(self, scene_id: int) -> Path:
        return self.root / self.split / f"{scene_id:06d}"

    def image_path(self, scene_id: int, im_id: int) -> Path:
        ext = self._rgb_ext.get(scene_id, {}).get(im_id, ".png")
        return self.scene_dir(scene_id) / "rgb" / f"{im_id:06d}{ext}"

    def mask_visib_path(self, scene_id: int, im_id: int, gt_index: int) -> Path:
        return self.scene_dir(scene_id) / "mask_visib" / f"{im_id:06d}_{gt_index:06d}.png"

    def load_rgb(self, scene_id: int, im_id: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB (grey images are repeated to three channels)."""
        p = self.image_path(scene_id, im_id)
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"{p}: image is missing or unreadable")
        if img.dtype != np.uint8:
            img = (img / (256.0 if img.dtype == np.uint16 else 1.0)).clip(0, 255).astype(np.uint8)
        if img.ndim == 2:
            return np.repeat(img[..., None], 3, axis=2)
        return cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)

    def load_mask_visib(self, scene_id: int, im_id: int, gt_index: int) -> np.ndarray:
        """(H, W) bool visible mask of one annotation."""
        p = self.mask_visib_path(scene_id, im_id, gt_index)
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise DatasetError(f"{p}: mask_visib image is missing or unreadable")
        return m > 127

    def load_depth(self, scene_id: int, im_id: int) -> np.ndarray | None:
        """(H, W) float32 depth in mm, or None when the dataset has no ``depth/`` image."""
        p = self.scene_dir(scene_id) / "depth" / f"{im_id:06d}.png"
        if not p.is_file():
            return None
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise DatasetError(f"{p}: depth image is unreadable")
        return d.astype(np.float32) * self._depth_scale.get((scene_id, im_id), 1.0)


# ---------------------------------------------------------------------- SurgRIPE
SURGRIPE_DIRS = {"image": ("image", "images", "rgb"), "pose": ("pose", "poses"), "mask": ("mask", "masks")}


def _find_dir(src: Path, kind: str, required: bool) -> Path | None:
    for name in SURGRIPE_DIRS[kind]:
        if (src / name).is_dir():
            return src / name
    if required:
        raise DatasetError(f"{src}: no {kind} folder (looked for {', '.join(SURGRIPE_DIRS[kind])})")
    return None


def import_surgripe(src: str | Path, dst: str | Path, obj_name: str, mesh_path: str | Path, K: np.ndarray,
                    split: str = "test", scene_id: int = 0, obj_id: int = 1, mesh_scale: float = 1.0) -> int:
    """Rearrange a SurgRIPE-style folder into our BOP layout (one scene, one object); returns the image count.

    Assumed source layout ("SurgRIPE rearranged into BOP"; the real release may name things differently,
    rearrange it into this first)::

        <src>/image/<stem>.png|jpg      (also images/ or rgb/)  the frames
        <src>/pose/<stem>.npy           (also poses/)           3x4 [R|t] (or 4x4), model to camera, t in mm
        <src>/mask/<stem>.png           (also masks/, optional)  the object's visible mask, > 0 = object

    Every image needs a pose of the same stem; images are numbered in sorted stem order and the stem is
    kept as the extra scene_gt key ``source_stem``. ``mesh_path`` is the object's mesh in the pose's model
    frame; ``mesh_scale`` converts it to mm (1000 for metres). ``K`` is the 3x3 intrinsic matrix.

    Written: ``models/obj_<obj_id>.ply`` + ``models_info.json`` (``diameter`` is BOP's max pairwise vertex
    distance; SurgRIPE's own convention, the bounding-box diagonal, is kept as ``diameter_bbox_diagonal``),
    ``<split>/<scene>/rgb`` (copied), ``mask/`` (full silhouette rendered from the mesh), ``mask_visib/``
    (the given mask; the rendered silhouette when no mask is given, i.e. assumed unoccluded) and the three
    scene JSON files with BOP's boxes and pixel counts. Rendering needs a GL context (main process).
    """
    from surftrack.render import Renderer
    from surftrack.synth import bop_writer

    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise DatasetError(f"{src}: SurgRIPE folder is missing")
    img_dir, pose_dir = _find_dir(src, "image", True), _find_dir(src, "pose", True)
    mask_dir = _find_dir(src, "mask", False)
    images = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in RGB_EXTS)
    if not images:
        raise DatasetError(f"{img_dir}: no .png/.jpg images")
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    mesh_path = Path(mesh_path)
    if not mesh_path.is_file():
        raise DatasetError(f"{mesh_path}: mesh file is missing")
    try:
        mesh = read_mesh_file(mesh_path)  # STL, OBJ, PLY with n-gon faces, glTF, COLLADA
    except ValueError as e:
        raise DatasetError(str(e)) from None
    if mesh_scale != 1.0:
        mesh.apply_scale(mesh_scale)
    part = Part(obj_name, mesh)

    models = dst / "models"
    models.mkdir(parents=True, exist_ok=True)
    (models / f"obj_{obj_id:06d}.ply").write_bytes(
        trimesh.exchange.ply.export_ply(part.mesh, encoding="binary", vertex_normal=True))
    info = model_info(part)
    info.update({"part": obj_name, "diameter_bbox_diagonal": part.diameter_bbox_diagonal,
                 "mesh_sha256": part.mesh_hash, "source": str(mesh_path)})
    (models / "models_info.json").write_text(json.dumps({str(obj_id): info}, indent=2))

    scene = dst / split / f"{scene_id:06d}"
    for sub in ("rgb", "mask", "mask_visib"):
        (scene / sub).mkdir(parents=True, exist_ok=True)
    renderer = None
    cams, gts, infos = {}, {}, {}
    try:
        for im, img_path in enumerate(images):
            stem = img_path.stem
            pose_path = pose_dir / f"{stem}.npy"
            if not pose_path.is_file():
                raise DatasetError(f"{pose_path}: pose for image {img_path.name} is missing")
            P = np.load(pose_path).astype(np.float64)
            if P.shape not in ((3, 4), (4, 4)):
                raise DatasetError(f"{pose_path}: pose must be 3x4 [R|t] (or 4x4), got shape {P.shape}")
            T = np.eye(4)
            T[:3] = P[:3]
            img = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise DatasetError(f"{img_path}: image is unreadable")
            H, W = img.shape[:2]
            if renderer is None or (renderer.width, renderer.height) != (W, H):
                if renderer is not None:
                    renderer.release()
                renderer = Renderer(W, H)
                iid = renderer.add_mesh(part.mesh, name=obj_name)
            pad = max(W, H) // 2
            res = renderer.render(PinholeCamera(K, W, H), {iid: T}, modalities={"instance", "amodal"}, amodal_pad=pad)
            full_pad, full = res.amodal[iid], res.amodal_in_image(iid)
            if mask_dir is not None:
                mp = mask_dir / f"{stem}.png"
                m = cv2.imread(str(mp), cv2.IMREAD_GRAYSCALE)
                if m is None:
                    raise DatasetError(f"{mp}: mask for image {img_path.name} is missing or unreadable")
                if m.shape != (H, W):
                    raise DatasetError(f"{mp}: mask is {m.shape[1]}x{m.shape[0]}, image is {W}x{H}")
                visib = m > 0
            else:
                visib = full
            name = f"{im:06d}"
            shutil.copyfile(img_path, scene / "rgb" / f"{name}{img_path.suffix.lower()}")
            cv2.imwrite(str(scene / "mask" / f"{name}_000000.png"), full.astype(np.uint8) * 255)
            cv2.imwrite(str(scene / "mask_visib" / f"{name}_000000.png"), visib.astype(np.uint8) * 255)
            n_all, n_vis = int(full_pad.sum()), int(visib.sum())
            cams[str(im)] = {"cam_K": K.ravel().tolist(), "depth_scale": 1.0}
            gts[str(im)] = [{"obj_id": obj_id, "cam_R_m2c": T[:3, :3].ravel().tolist(),
                             "cam_t_m2c": T[:3, 3].tolist(), "part": obj_name, "source_stem": stem}]
            infos[str(im)] = [{"bbox_obj": bop_writer.bbox_xywh(full_pad, offset=pad),
                               "bbox_visib": bop_writer.bbox_xywh(visib), "px_count_all": n_all,
                               "px_count_visib": n_vis, "visib_fract": min(n_vis / n_all, 1.0) if n_all else 0.0}]
    finally:
        if renderer is not None:
            renderer.release()
    for name, store in (("scene_camera.json", cams), ("scene_gt.json", gts), ("scene_gt_info.json", infos)):
        (scene / name).write_text(json.dumps(store, indent=1))
    return len(images)

"""Training crops of a BOP dataset as a torch ``Dataset``, and syn:real mixing per batch.

Each item is one annotated instance, cropped square around its box (optionally jittered and rotated in
the image plane), with the targets rendered in the crop camera (:mod:`surftrack.data.targets`) and
photometric augmentation (:mod:`surftrack.data.augment`). Items are deterministic functions of
``(seed, epoch, index)``: call :meth:`CropDataset.set_epoch` before each epoch.

Workers: targets are rendered with OpenGL, created lazily in the process that renders. With
``num_workers > 0`` the DataLoader MUST take its workers from ``worker_context()`` (a fork server, or
``spawn``)::

    DataLoader(ds, batch_size=20, num_workers=4, multiprocessing_context=surftrack.render.worker_context(),
               sampler=MixedSampler(len(syn), len(real), batch_size=20))

(a forked worker of a process that already holds a GL context cannot create one and raises
``RenderError``). Keep ``persistent_workers=False`` (the default) so each epoch's workers receive the
dataset with the epoch set by :meth:`set_epoch`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset, Sampler

from surftrack.data.augment import AugmentConfig, augment
from surftrack.data.bop import BopDataset, DatasetError
from surftrack.data.crops import crop_box
from surftrack.data.targets import TargetRenderer, modal_mask
from surftrack.data.twin_labels import TwinLabels
from surftrack.geometry import crop_with_rotation, pose_in_crop, warp_image

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
MASK_MODES = ("amodal", "modal")
BOX_SOURCES = ("visib", "obj")


def normalise_image(rgb: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (3, H, W) float32 normalised with ImageNet mean / std."""
    x = (rgb.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))


def denormalise_image(image: torch.Tensor) -> np.ndarray:
    """Inverse of :func:`normalise_image`: (3, H, W) -> (H, W, 3) uint8."""
    x = image.detach().cpu().numpy().transpose(1, 2, 0) * IMAGENET_STD + IMAGENET_MEAN
    return np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class CropConfig:
    """Crop side (px), box ``scale``, ``jitter`` (see :func:`crop_box`), in-plane rotation limit (deg),
    which box the crop is centred on (``"visib"`` = bbox_visib like a detector's, ``"obj"`` = bbox_obj)
    and which mask trains the mask head / gives the query pixels (``mask_mode``)."""

    size: int = 224
    scale: float = 1.2
    jitter: float = 0.0
    max_rotation_deg: float = 0.0
    box: str = "visib"
    mask_mode: str = "amodal"

    def __post_init__(self) -> None:
        if self.mask_mode not in MASK_MODES:
            raise ValueError(f"mask_mode must be one of {MASK_MODES}, got {self.mask_mode!r}")
        if self.box not in BOX_SOURCES:
            raise ValueError(f"box must be one of {BOX_SOURCES}, got {self.box!r}")
        if self.size <= 0 or self.scale <= 0 or self.jitter < 0 or self.max_rotation_deg < 0:
            raise ValueError(f"invalid crop config {self}")


class CropDataset(Dataset):
    """Crops of the instances of ``bop`` whose obj id is in ``obj_ids``; ``obj_ids`` also fixes the part
    order (``part_index`` = position in it; default: all models of the dataset, sorted).

    Item (S = ``crop_size``)::

        image        (3, S, S) float32  ImageNet-normalised RGB after augmentation
        mask_modal   (S, S) float32     visible mask (mask_visib warped, minus synthetic occluders)
        mask_amodal  (S, S) float32     full silhouette (rendered)
        mask_train   (S, S) float32     the one of the two chosen by ``mask_mode``
        coord_norm   (S, S, 3) float32  object coordinates in the part's normalised frame, 0 off the surface
        coord_valid  (S, S) bool        the object's surface is rendered there (amodal: also where occluded)
        part_index, obj_id, scene_id, im_id, gt_index, index   int64 scalars
        K (3, 3), R (3, 3), t (3,)      float32 crop intrinsics and model-to-crop-camera pose (t in mm)
        bbox (4,) float32               crop box (x0, y0, x1, y1), pixel edges of the original image
        angle () float32                in-plane rotation of the crop (rad)

    ``twins``: label near-symmetric instruments as one of their two roll twins (:mod:`surftrack.data.twin_labels`;
    the item's obj_id, part_index, pose and targets are then the twin's).
    """

    def __init__(self, bop: BopDataset, obj_ids: list[int] | None = None, crop_size: int = 224,
                 scale: float = 1.2, jitter: float = 0.0, max_rotation_deg: float = 0.0,
                 augment: AugmentConfig | dict | None = None, mask_mode: str = "amodal", box: str = "visib",
                 seed: int = 0, twins: TwinLabels | None = None):
        self.bop = bop
        self.cfg = CropConfig(int(crop_size), float(scale), float(jitter), float(max_rotation_deg), box, mask_mode)
        self.obj_ids = [int(o) for o in (obj_ids if obj_ids is not None else sorted(bop.models))]
        missing = sorted(set(self.obj_ids) - set(bop.models))
        if missing:
            raise DatasetError(f"{bop.models_dir}: obj_ids {missing} have no model (models: {sorted(bop.models)})")
        self._part_index = {o: k for k, o in enumerate(self.obj_ids)}
        self.items = [k for k, inst in enumerate(bop.instances) if inst.obj_id in self._part_index]
        if not self.items:
            raise DatasetError(f"{bop.root / bop.split}: no instance of obj_ids {self.obj_ids} "
                               f"(instances have {sorted({i.obj_id for i in bop.instances})})")
        if augment is None:
            self.augment = AugmentConfig.none()
        else:
            self.augment = augment if isinstance(augment, AugmentConfig) else AugmentConfig.from_dict(augment)
        self.seed = int(seed)
        self.epoch = 0
        self.twins = twins
        self._flip = ({k for k, f in enumerate(twins.flips(bop.instances)) if f} if twins is not None else set())
        lacking = sorted({twins.partner[bop.instances[k].obj_id] for k in self._flip} - set(self._part_index))
        if lacking:
            raise DatasetError(f"{bop.root / bop.split}: twin labels name obj_ids {lacking} outside obj_ids "
                               f"{self.obj_ids}")
        self.targets = TargetRenderer(bop.models, self.cfg.size)  # GL created on first use, in the worker

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.items)

    @property
    def mask_mode(self) -> str:
        return self.cfg.mask_mode

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not 0 <= index < len(self.items):
            raise IndexError(f"index {index} out of range for {len(self.items)} crops")
        cfg = self.cfg
        rng = np.random.default_rng([self.seed, self.epoch, int(index)])
        inst = self.bop.instances[self.items[index]]
        rgb = self.bop.load_rgb(inst.scene_id, inst.im_id)
        visib = self.bop.load_mask_visib(inst.scene_id, inst.im_id, inst.gt_index)
        H, W = rgb.shape[:2]
        camera = inst.camera(W, H)
        first, second = (inst.bbox_visib, inst.bbox_obj) if cfg.box == "visib" else (inst.bbox_obj, inst.bbox_visib)
        bbox = first if first[2] >= 0 and first[3] >= 0 else second  # BOP writes [-1] * 4 for an empty box
        box = crop_box(bbox, cfg.scale, cfg.jitter, rng)
        angle = 0.0
        if cfg.max_rotation_deg > 0:
            angle = float(np.radians(rng.uniform(-cfg.max_rotation_deg, cfg.max_rotation_deg)))
        M, crop_cam, R_crop = crop_with_rotation(camera, box, cfg.size, angle)
        obj_id, pose = inst.obj_id, inst.pose
        if self.items[index] in self._flip:  # the same pixels, labelled as the instrument's other twin
            obj_id, pose = self.twins.relabel(obj_id, pose)
        T = pose_in_crop(R_crop, pose)
        image = warp_image(rgb, M, cfg.size)
        modal = modal_mask(visib, M, cfg.size)
        tg = self.targets.render(obj_id, crop_cam, T)
        image, modal = augment(image, modal, self.augment, rng)
        amodal = tg.valid
        train = amodal if cfg.mask_mode == "amodal" else modal
        i64 = lambda v: torch.tensor(int(v), dtype=torch.int64)  # noqa: E731
        return {
            "image": normalise_image(image),
            "mask_modal": torch.from_numpy(modal.astype(np.float32)),
            "mask_amodal": torch.from_numpy(amodal.astype(np.float32)),
            "mask_train": torch.from_numpy(train.astype(np.float32)),
            "coord_norm": torch.from_numpy(tg.coord_norm),
            "coord_valid": torch.from_numpy(tg.valid.copy()),
            "part_index": i64(self._part_index[obj_id]),
            "obj_id": i64(obj_id),
            "scene_id": i64(inst.scene_id),
            "im_id": i64(inst.im_id),
            "gt_index": i64(inst.gt_index),
            "index": i64(index),
            "K": torch.from_numpy(crop_cam.K.astype(np.float32)),
            "R": torch.from_numpy(T[:3, :3].astype(np.float32)),
            "t": torch.from_numpy(T[:3, 3].astype(np.float32)),
            "bbox": torch.tensor(box, dtype=torch.float32),
            "angle": torch.tensor(angle, dtype=torch.float32),
        }


# ---------------------------------------------------------------------- syn:real mixing
def mixed_dataset(a: Dataset, b: Dataset) -> ConcatDataset:
    """``ConcatDataset([a, b])``: indices < len(a) are a's, the rest b's (offset by len(a))."""
    return ConcatDataset([a, b])


def mixed_indices(len_a: int, len_b: int, n: int, ratio: tuple[int, int] = (1, 1),
                  rng: np.random.Generator | None = None, batch_size: int | None = None) -> np.ndarray:
    """``n`` indices into ``ConcatDataset([a, b])`` where every consecutive batch of ``batch_size``
    (default ``sum(ratio)``) holds ``round(batch_size * ra / (ra + rb))`` items of a and the rest of b
    (a shorter last batch is split the same way), shuffled within the batch. Each dataset is walked in
    random permutations, reshuffled when used up, so every item is seen before any repeats."""
    ra, rb = (int(r) for r in ratio)
    if ra < 0 or rb < 0 or ra + rb == 0:
        raise ValueError(f"ratio must be two non-negative integers, not both 0, got {ratio}")
    if (ra and len_a <= 0) or (rb and len_b <= 0):
        raise ValueError(f"ratio {ratio} draws from an empty dataset (sizes {len_a}, {len_b})")
    rng = rng if rng is not None else np.random.default_rng()
    bs = int(batch_size) if batch_size else ra + rb
    if bs <= 0 or n < 0:
        raise ValueError(f"need batch_size > 0 and n >= 0, got {batch_size}, {n}")

    def stream(length: int, offset: int):
        while True:
            yield from (rng.permutation(length) + offset).tolist()

    sa, sb = stream(len_a, 0), stream(len_b, len_a)
    out: list[int] = []
    while len(out) < n:
        size = min(bs, n - len(out))
        na = int(round(size * ra / (ra + rb)))
        batch = [next(sa) for _ in range(na)] + [next(sb) for _ in range(size - na)]
        out += rng.permutation(batch).tolist()
    return np.asarray(out, dtype=np.int64)


class MixedSampler(Sampler[int]):
    """Sampler over ``ConcatDataset([a, b])`` giving every batch of ``batch_size`` the ``ratio`` a:b
    (SurfSurg6D: syn:real 1:1); use it with the same ``batch_size`` in the DataLoader. ``num_samples``
    defaults to ``len_a + len_b`` rounded up to whole batches. Deterministic per (seed, epoch)."""

    def __init__(self, len_a: int, len_b: int, batch_size: int, ratio: tuple[int, int] = (1, 1),
                 num_samples: int | None = None, seed: int = 0):
        self.len_a, self.len_b, self.batch_size, self.ratio = int(len_a), int(len_b), int(batch_size), tuple(ratio)
        self.num_samples = int(num_samples) if num_samples is not None else \
            math.ceil((self.len_a + self.len_b) / self.batch_size) * self.batch_size
        self.seed, self.epoch = int(seed), 0
        mixed_indices(self.len_a, self.len_b, 0, self.ratio, batch_size=self.batch_size)  # validate now

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.num_samples

    def __iter__(self):
        rng = np.random.default_rng([self.seed, self.epoch])
        return iter(mixed_indices(self.len_a, self.len_b, self.num_samples, self.ratio, rng, self.batch_size).tolist())

"""Training targets of one instance in a crop camera: object coordinates and the amodal silhouette.

The instance is rendered ALONE, so its coordinate map is the object's own front surface everywhere in
its silhouette, also where something occludes it in the image (SurfEmb's amodal targets); that
silhouette is the amodal mask. The modal (visible) mask is the dataset's ``mask_visib`` warped into the
crop (:func:`modal_mask`).

GL: the :class:`~surftrack.render.Renderer` is created on the first :meth:`TargetRenderer.render` call
and dropped when pickled, so a TargetRenderer (and a dataset holding one) can be sent to worker
processes. Those workers must come from ``surftrack.render.worker_context()`` (a fork server, or ``spawn``):
a child forked from a process holding a GL context cannot make its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surftrack.geometry import PinholeCamera, warp_image
from surftrack.instruments.part import Part


@dataclass
class Targets:
    """Per-pixel targets of one crop (S = crop side). ``xyz`` (S, S, 3) float32 object coordinates in mm
    and ``coord_norm`` (S, S, 3) float32 in the part's normalised frame (0 where no surface); ``valid``
    (S, S) bool: the object's surface is rendered there (= the amodal mask)."""

    xyz: np.ndarray
    coord_norm: np.ndarray
    valid: np.ndarray

    @property
    def mask_amodal(self) -> np.ndarray:
        return self.valid


class TargetRenderer:
    """Renders :class:`Targets` for the parts in ``models`` (obj id -> Part) at ``size`` x ``size``."""

    def __init__(self, models: dict[int, Part], size: int, near: float = 1.0, far: float = 3000.0):
        self.models = dict(models)
        self.size = int(size)
        self.near, self.far = float(near), float(far)
        self._renderer = None
        self._ids: dict[int, int] = {}

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_renderer"], state["_ids"] = None, {}
        return state

    def _instance(self, obj_id: int) -> int:
        if self._renderer is None:
            from surftrack.render import Renderer

            self._renderer = Renderer(self.size, self.size, self.near, self.far)
        if obj_id not in self._ids:
            if obj_id not in self.models:
                raise KeyError(f"no model for obj_id {obj_id} (models: {sorted(self.models)})")
            self._ids[obj_id] = self._renderer.add_mesh(self.models[obj_id].mesh, name=str(obj_id))
        return self._ids[obj_id]

    def render(self, obj_id: int, camera: PinholeCamera, pose: np.ndarray) -> Targets:
        """Targets of object ``obj_id`` at ``pose`` (4x4 model-to-camera, mm) seen by ``camera`` (the crop
        camera, ``size`` x ``size``)."""
        iid = self._instance(obj_id)
        res = self._renderer.render(camera, {iid: np.asarray(pose, dtype=np.float64)}, lights=[],
                                    modalities={"xyz", "instance"})
        valid = res.instance == iid
        xyz = np.where(valid[..., None], res.xyz, 0.0).astype(np.float32)
        norm = np.zeros_like(xyz)
        norm[valid] = self.models[obj_id].normalise(xyz[valid]).astype(np.float32)
        return Targets(xyz, norm, valid)

    def release(self) -> None:
        if self._renderer is not None:
            self._renderer.release()
        self._renderer, self._ids = None, {}


def modal_mask(mask_visib: np.ndarray, M: np.ndarray, size: int) -> np.ndarray:
    """The image's visible mask (H, W) bool warped into the crop by ``M`` (nearest): (size, size) bool."""
    return warp_image(np.asarray(mask_visib, dtype=bool), M, size, nearest=True)

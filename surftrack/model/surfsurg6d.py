"""The SurfSurg6D model: image network (ResNet18 U-Net) + one SIREN surface field per part, and the
part identities (meshes, normalisation) that make a checkpoint self-contained."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import nn

from surftrack.instruments import Part
from surftrack.model.config import ModelCfg
from surftrack.model.resnet_unet import ResNetUNet
from surftrack.model.siren import KeyFields

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class PartInfo:
    """What a model knows of one part: ids, names, mesh (mm) and its normalisation sphere."""

    obj_id: int
    instrument: str
    name: str
    mesh_sha256: str
    center: np.ndarray
    radius: float
    vertices: np.ndarray
    faces: np.ndarray
    keypoints: dict[str, list[float]]

    @classmethod
    def from_part(cls, obj_id: int, instrument: str, part: Part) -> PartInfo:
        c, r = part.bounding_sphere
        return cls(obj_id, instrument, part.name, part.mesh_hash, np.asarray(c), float(r),
                   np.asarray(part.mesh.vertices, np.float64), np.asarray(part.mesh.faces, np.int64),
                   {k: v.tolist() for k, v in part.keypoints.items()})

    def to_part(self) -> Part:
        return Part(self.name, trimesh.Trimesh(self.vertices, self.faces, process=False),
                    keypoints={k: np.asarray(v) for k, v in self.keypoints.items()})

    def to_dict(self) -> dict:
        return {"obj_id": self.obj_id, "instrument": self.instrument, "name": self.name,
                "mesh_sha256": self.mesh_sha256, "center": self.center.tolist(), "radius": self.radius,
                "vertices": torch.from_numpy(self.vertices.astype(np.float32)),
                "faces": torch.from_numpy(self.faces.astype(np.int32)),
                "keypoints": self.keypoints}

    @classmethod
    def from_dict(cls, d: dict) -> PartInfo:
        return cls(int(d["obj_id"]), d["instrument"], d["name"], d["mesh_sha256"], np.asarray(d["center"]),
                   float(d["radius"]), np.asarray(d["vertices"]).astype(np.float64), np.asarray(d["faces"]).astype(np.int64),
                   d.get("keypoints", {}))


class SurfSurg6D(nn.Module):
    """``forward(images, part_index)`` -> (mask logits (B, S, S), queries (B, E, S, S));
    ``keys(part_index, coords_norm)`` -> (N, E) surface keys."""

    def __init__(self, parts: list[PartInfo], cfg: ModelCfg):
        super().__init__()
        if not parts:
            raise ValueError("a model needs at least one part")
        self.parts, self.cfg = parts, cfg
        self.net = ResNetUNet(len(parts), cfg.emb_dim, tuple(cfg.decoder_widths), cfg.single_decoder)
        self.fields = KeyFields(len(parts), cfg.emb_dim, cfg.siren_hidden)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def part_index(self, obj_id: int) -> int:
        for i, p in enumerate(self.parts):
            if p.obj_id == obj_id:
                return i
        raise KeyError(f"model has no part with obj_id {obj_id}; it knows {[p.obj_id for p in self.parts]}")

    def forward(self, images: torch.Tensor, part_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.net(images, part_index)

    def keys(self, part: int, coords_norm: torch.Tensor) -> torch.Tensor:
        return self.fields(part, coords_norm)

    def normalize_images(self, rgb_uint8: torch.Tensor) -> torch.Tensor:
        """(B, H, W, 3) uint8 -> (B, 3, H, W) float normalised with the ImageNet statistics."""
        x = rgb_uint8.permute(0, 3, 1, 2).float() / 255.0
        return (x - self.mean) / self.std


def surface_bank(part: PartInfo, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform surface samples of a part: normalised coordinates (count, 3) and normals (count, 3)."""
    mesh = trimesh.Trimesh(part.vertices, part.faces, process=False)
    pts, fi = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return ((pts - part.center) / part.radius).astype(np.float32), mesh.face_normals[fi].astype(np.float32)

"""Training data: BOP datasets, object crops (optionally rotated; the crop geometry is
:mod:`surftrack.geometry`'s), rendered targets, augmentation and torch datasets. Rendering needs workers
not forked from a process with a GL context: see :mod:`surftrack.data.dataset`."""

from surftrack.data.augment import AugmentConfig, augment
from surftrack.data.bop import BopDataset, DatasetError, Instance, import_surgripe, load_models, models_layout
from surftrack.data.crops import crop_box
from surftrack.data.dataset import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    MASK_MODES,
    CropConfig,
    CropDataset,
    MixedSampler,
    denormalise_image,
    mixed_dataset,
    mixed_indices,
    normalise_image,
)
from surftrack.data.targets import TargetRenderer, Targets, modal_mask

__all__ = [
    "AugmentConfig", "BopDataset", "CropConfig", "CropDataset", "DatasetError", "IMAGENET_MEAN", "IMAGENET_STD",
    "Instance", "MASK_MODES", "MixedSampler", "TargetRenderer", "Targets", "augment", "crop_box",
    "denormalise_image", "import_surgripe", "load_models", "mixed_dataset", "mixed_indices", "modal_mask",
    "models_layout", "normalise_image",
]

"""SurfSurg6D: ResNet18 U-Net queries, SIREN surface keys, penalised InfoNCE and consistency losses."""

from surftrack.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from surftrack.model.config import TrainConfig, TrainConfigError, load_train_config
from surftrack.model.surfsurg6d import PartInfo, SurfSurg6D, surface_bank

__all__ = ["CheckpointError", "PartInfo", "SurfSurg6D", "TrainConfig", "TrainConfigError", "load_checkpoint",
           "load_train_config", "save_checkpoint", "surface_bank"]

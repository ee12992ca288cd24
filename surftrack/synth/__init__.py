"""Synthetic scenes: procedural tissue, instrument placement, datasets and clips."""

from surftrack.synth.tissue import Tissue, image_backdrop, load_tissue_mesh, procedural_tissue

__all__ = ["Tissue", "image_backdrop", "load_tissue_mesh", "procedural_tissue"]

"""Synthetic scenes: procedural tissue, instrument placement, datasets and clips."""

from surftrack.synth.tissue import Tissue, procedural_tissue

__all__ = ["Tissue", "procedural_tissue"]

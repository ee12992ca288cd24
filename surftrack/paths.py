"""Where surftrack finds its bundled configuration files."""

from __future__ import annotations

import os
from pathlib import Path


def configs_dir() -> Path:
    """The ``configs/`` folder: ``$SURFTRACK_CONFIGS`` if set, else the one beside the package."""
    env = os.environ.get("SURFTRACK_CONFIGS")
    return Path(env) if env else Path(__file__).resolve().parent.parent / "configs"


def default_model_path() -> Path:
    """The bundled default model: ``$SURFTRACK_MODEL`` if set, else ``models/default.pt`` beside the
    package (the Large Needle Driver, trained with our own pipeline; see ``models/MODEL_CARD.md``)."""
    env = os.environ.get("SURFTRACK_MODEL")
    return Path(env) if env else Path(__file__).resolve().parent.parent / "models" / "default.pt"

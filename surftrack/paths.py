"""Where surftrack finds the files it ships: the configuration folder and the bundled model.

Both are package data (``surftrack.configs`` and ``surftrack.models``; in the source tree the top-level
``configs/`` and ``models/`` folders, mapped by ``pyproject.toml``), found through
:mod:`importlib.resources`, so an editable checkout, a wheel and an sdist install behave the same from any
working directory. surftrack installs as files on disk (torch does too), so the resources are real paths.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def _package_dir(package: str) -> Path:
    """The folder of ``package`` on disk. Run from a source tree that is not installed (``PYTHONPATH``),
    the mapped packages do not exist: their folders are then the top-level ones beside ``surftrack/``."""
    try:
        return Path(str(resources.files(package)))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parent.parent / package.rsplit(".", 1)[1]


def configs_dir() -> Path:
    """The bundled ``configs`` folder (instruments, synthesis, tracking and training YAML, schemas)."""
    return _package_dir("surftrack.configs")


def default_model_path() -> Path:
    """The bundled default model (the Large Needle Driver, trained with our own pipeline; see
    ``models/MODEL_CARD.md``). ``$SURFTRACK_MODEL`` overrides it on the command line."""
    return _package_dir("surftrack.models") / "default.pt"

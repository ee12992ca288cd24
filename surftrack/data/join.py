"""Several BOP datasets of the same objects as one training folder, without copying images.

``surftrack train`` reads one ``--data`` folder. To train on a mix (e.g. sets synthesised with different
roll settings), join them: the joined folder's scene folders are relative links to the sources' scenes,
renumbered in order, and its ``models/`` links to the first source's.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

from surftrack.data.bop import DatasetError


def _object_names(card: dict) -> dict:
    """obj id -> (instrument, part) of a dataset card: what joined sets must agree on (their models' bytes
    are compared too; cards of different versions carry different extra fields)."""
    return {k: (v.get("instrument"), v.get("part")) for k, v in (card.get("objects") or {}).items()
            if isinstance(v, dict)}


def _card(src: Path) -> dict:
    try:
        return json.loads((src / "dataset_card.json").read_text())
    except (OSError, ValueError) as e:
        raise DatasetError(f"{src}: no readable dataset_card.json (made by `surftrack synth`): {e}") from None


def join_datasets(out: str | Path, sources: Sequence[str | Path], split: str = "train") -> int:
    """Make ``out`` the union of the ``split`` scenes of ``sources`` and return its number of scenes.

    The sources must hold identical ``models/`` files and objects (checked). ``out`` gets a
    ``dataset_card.json`` naming the parts (training reads the instrument names from it) and the sources.
    It is built under a temporary name and renamed, so an interrupted join is never reused; an existing
    ``out`` is accepted only if it already joins exactly these sources' scenes.
    """
    out, srcs = Path(out), [Path(s) for s in sources]
    if not srcs:
        raise DatasetError(f"{out}: nothing to join: name at least one source dataset")
    for src in srcs:
        if not (src / split).is_dir() or not (src / "models").is_dir():
            raise DatasetError(f"{src}: not a BOP dataset with models/ and {split}/")
        if out.resolve() == src.resolve():
            raise DatasetError(f"{out}: the joined folder cannot be one of its sources")
    scenes = [d for src in srcs for d in sorted((src / split).iterdir()) if d.is_dir()]
    if out.exists():
        have = sorted((out / split).iterdir()) if (out / split).is_dir() else []
        if [d.resolve() for d in have] != [d.resolve() for d in scenes]:
            raise DatasetError(f"{out}: exists and does not join exactly these sources' scenes; remove it or "
                               "choose another folder")
        return len(have)
    cards = [_card(src) for src in srcs]
    names = sorted(f.name for f in (srcs[0] / "models").iterdir())
    for src, card in zip(srcs[1:], cards[1:]):
        if (sorted(f.name for f in (src / "models").iterdir()) != names
                or any((src / "models" / n).read_bytes() != (srcs[0] / "models" / n).read_bytes() for n in names)
                or _object_names(card) != _object_names(cards[0])):
            raise DatasetError(f"{src}: its models differ from those of {srcs[0]}")
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / split).mkdir(parents=True)
    (tmp / "models").symlink_to(os.path.relpath(srcs[0].resolve() / "models", tmp.resolve()), target_is_directory=True)
    for n, scene in enumerate(scenes):
        (tmp / split / f"{n:06d}").symlink_to(os.path.relpath(scene.resolve(), (tmp / split).resolve()),
                                              target_is_directory=True)
    card = {"joined": [str(src) for src in srcs], "objects": cards[0].get("objects"),
            "images": sum(c.get("images", 0) for c in cards), "sources": cards}
    (tmp / "dataset_card.json").write_text(json.dumps(card, indent=1))
    tmp.rename(out)
    return len(scenes)

"""Files replaced whole: written beside their place and renamed over it, so that a reader never sees, and
a crash or a killed run never leaves, half a file (a resumed run then parses what is there).

Used by any stage that writes a file others read back (BOP datasets, clips, instrument models); it
imports nothing from surftrack.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` (bytes, or text as UTF-8) to ``path``: into a temporary file of its own beside it
    (two writers of one path never share one), then renamed over ``path``. Not synced to disk: a killed
    run leaves whole files; a power cut may not (a synthesis resume then writes what it finds missing)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode("utf-8") if isinstance(data, str) else data)
        os.chmod(tmp, 0o644)  # mkstemp makes the file private; these are ordinary data files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise

"""Files replaced whole: written beside their place and renamed over it, so that a reader, a crash or a
killed run never leaves half a file (a resumed run then parses what is there).

Used by any stage that writes a file others read back (BOP datasets, clips, instrument models); it
imports nothing from surftrack.
"""

from __future__ import annotations

import os
from pathlib import Path


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` through ``<path>.tmp`` and one rename."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_bytes(data.encode("utf-8") if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise

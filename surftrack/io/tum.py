"""Per-part pose trajectories as TUM RGB-D text files, for evo and other trajectory tools.

One file per part, ``<directory>/<part name>.tum``, one line per pose::

    time tx ty tz qx qy qz qw

separated by single spaces: time in seconds, the part's model-to-camera translation in METRES (the
part origin in the camera frame) and rotation as a unit quaternion (x, y, z, w) with ``qw >= 0``. The
file starts with one ``#`` comment line naming the columns (evo skips lines starting with ``#``).
Inside surftrack translations are millimetres; the conversion happens here and in :func:`read_tum` only.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import TextIO

import numpy as np

from surftrack.geometry import matrix_from_quat_xyzw, quat_xyzw_from_matrix

__all__ = ["TumWriter", "read_tum", "tum_filename"]

_HEADER = ("# time tx ty tz qx qy qz qw | part {name!r}: model-to-camera pose in the camera frame "
           "(OpenCV axes); time s, translation m, unit quaternion (x, y, z, w) with qw >= 0\n")
_ORTHONORMAL_TOL = 1e-3


def tum_filename(part_name: str) -> str:
    """File name ``<name>.tum`` for a part: characters other than letters, digits, ``_``, ``-`` and ``.``
    become ``_`` and leading dots are dropped, so every name gives a plain file inside the directory."""
    if not isinstance(part_name, str):
        raise ValueError(f"part name must be a string, got {part_name!r}")
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", part_name).lstrip(".")
    if not stem:
        raise ValueError(f"part name {part_name!r} gives no usable file name")
    return f"{stem}.tum"


def _tum_line(time_s: float, R, t_mm) -> str:
    t_s = float(time_s)
    if not math.isfinite(t_s):
        raise ValueError(f"time must be finite, got {time_s!r}")
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"R must be a finite 3x3 rotation matrix, got shape {R.shape}")
    # quaternion conversion would silently project any matrix onto a rotation
    if np.abs(R @ R.T - np.eye(3)).max() > _ORTHONORMAL_TOL or np.linalg.det(R) <= 0:
        raise ValueError(f"R is not a rotation matrix (orthonormal, det +1): {R.tolist()}")
    t = np.asarray(t_mm, dtype=np.float64).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"t must be 3 finite values (mm), got {t_mm!r}")
    q = quat_xyzw_from_matrix(R)
    return " ".join(f"{v:.9f}" for v in (t_s, *(t / 1000.0), *q)) + "\n"


class TumWriter:
    """Writes one TUM trajectory file per part into ``directory`` (created if missing).

    When it closes having written tracks, TUM files an earlier TumWriter left in ``directory`` for other
    parts are removed (other files are left alone).
    :meth:`add` appends a pose; a part's file is created (replacing an older one) at its first pose, and
    every line is flushed at once, so a crash loses nothing already added. Two part names that give the
    same file name (see :func:`tum_filename`) raise ``ValueError``. Use as a context manager, or call
    :meth:`close` (idempotent).
    """

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OSError(e.errno, f"cannot create the TUM output directory {str(self.directory)!r}: "
                                   f"{e.strerror}") from e
        self._files: dict[str, TextIO] = {}
        self._paths: dict[str, Path] = {}
        self._part_of_file: dict[str, str] = {}
        self._closed = False

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def paths(self) -> dict[str, Path]:
        """{part name: its file} for the parts written so far."""
        return dict(self._paths)

    def _file(self, part_name: str) -> TextIO:
        f = self._files.get(part_name)
        if f is not None:
            return f
        name = tum_filename(part_name)
        other = self._part_of_file.get(name)
        if other is not None:
            raise ValueError(f"part names {other!r} and {part_name!r} both map to {name!r}; rename one")
        path = self.directory / name
        try:
            f = open(path, "w", encoding="utf-8", newline="\n")
        except OSError as e:
            raise OSError(e.errno, f"cannot write the TUM file {str(path)!r}: {e.strerror}") from e
        f.write(_HEADER.format(name=part_name))
        f.flush()
        self._files[part_name], self._paths[part_name], self._part_of_file[name] = f, path, part_name
        return f

    def add(self, part_name: str, time_s: float, R: np.ndarray, t_mm: np.ndarray) -> None:
        """Append the pose of ``part_name`` at ``time_s``: model-to-camera ``R`` (3, 3), ``t_mm`` (3,) mm."""
        if self._closed:
            raise ValueError(f"TumWriter for {str(self.directory)!r} is closed")
        line = _tum_line(time_s, R, t_mm)
        f = self._file(part_name)
        f.write(line)
        f.flush()

    def close(self) -> None:
        """Close every part's file (safe to call twice)."""
        if self._closed:
            return
        self._closed = True
        for f in self._files.values():
            f.close()
        if self._paths:  # a run that wrote tracks: an earlier run's file of a part it never posed must not
            self._remove_stale()  # pass for this run's (a run that wrote nothing leaves the folder as it was)

    def _remove_stale(self) -> None:
        ours = set(self._paths.values())
        for old in self.directory.glob("*.tum"):
            if old in ours:
                continue
            try:
                with open(old, encoding="utf-8") as f:
                    written_here = f.readline().startswith(_HEADER.split("{", 1)[0])
            except (OSError, UnicodeDecodeError):
                continue  # unreadable: not a TumWriter's file
            if written_here:
                old.unlink(missing_ok=True)

    def __enter__(self) -> TumWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a TUM trajectory file: ``(times (N,) s, R (N, 3, 3), t_mm (N, 3) mm)``.

    Lines starting with ``#`` and blank lines are skipped; any other line must hold 8 numbers
    ``time tx ty tz qx qy qz qw`` (translation in metres; quaternions are normalised). A missing file or a
    malformed line raises ``ValueError`` naming the path (and line number).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ValueError(f"{path}: cannot read the TUM file ({e.strerror})") from e
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        try:
            values = [float(v) for v in fields]
        except ValueError:
            values = []
        if len(values) != 8 or not all(map(math.isfinite, values)):
            raise ValueError(f"{path}:{lineno}: expected 8 finite numbers 'time tx ty tz qx qy qz qw', "
                             f"got {line[:80]!r}")
        rows.append(values)
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)
    if np.any(np.linalg.norm(data[:, 4:], axis=1) < 1e-9):
        raise ValueError(f"{path}: a quaternion has zero length")
    R = matrix_from_quat_xyzw(data[:, 4:]).reshape(-1, 3, 3)
    return data[:, 0].copy(), R, data[:, 1:4] * 1000.0

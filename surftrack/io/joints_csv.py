"""Joint tracks as CSV: one row per (time, instrument) with the fitted joints in DEGREES, the base pose
(mm, quaternion x, y, z, w) and the fit's quality, for spreadsheets and quick plots.

Columns (units in the names)::

    time_s, instrument, roll_deg, pitch_deg, yaw_deg, opening_deg,
    base_tx_mm, base_ty_mm, base_tz_mm, base_qx, base_qy, base_qz, base_qw,
    rms_mm, parts_used, held, ok, roll_std_deg, pitch_std_deg, yaw_std_deg, opening_std_deg

``parts_used`` and ``held`` (joints kept at the warm start because the seen parts do not determine them,
see :mod:`surftrack.instruments.fit`) are ``;``-separated part / joint names; ``ok`` is 1 or 0. Joints
read off an instrument's tracked state (:mod:`surftrack.track.instrument`) come with their standard
deviations (``*_std_deg``) and no ``rms_mm`` (the parts are views of that state: nothing was fitted);
joints fitted frame by frame come with ``rms_mm`` and no standard deviations.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Iterable

import numpy as np

from surftrack.geometry import quat_xyzw_from_matrix
from surftrack.instruments.fit import JointFit
from surftrack.instruments.kinematics import JOINT_NAMES

__all__ = ["JOINT_CSV_COLUMNS", "JointCsvWriter", "write_joint_csv"]

JOINT_CSV_COLUMNS = (
    "time_s", "instrument", *(f"{n}_deg" for n in JOINT_NAMES),
    "base_tx_mm", "base_ty_mm", "base_tz_mm", "base_qx", "base_qy", "base_qz", "base_qw",
    "rms_mm", "parts_used", "held", "ok", *(f"{n}_std_deg" for n in JOINT_NAMES),
)


class JointCsvWriter:
    """Streams joint rows to ``path`` as a run goes (each row flushed, so a crash loses nothing);
    ``add(time_s, instrument_name, fit)``; ``close()`` is idempotent; a context manager. An unwritable
    path raises ``OSError`` naming it."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        try:
            self._f = open(self.path, "w", newline="", encoding="utf-8")
        except OSError as e:
            raise OSError(e.errno, f"cannot open joint CSV {str(self.path)!r} for writing: {e.strerror}",
                          str(self.path)) from e
        self._csv = csv.writer(self._f)
        self._csv.writerow(JOINT_CSV_COLUMNS)

    def add(self, time_s: float, instrument: str, fit: JointFit, std: dict[str, float] | None = None) -> None:
        """A row for ``fit`` at ``time_s``; ``std``: joint name -> standard deviation (rad), where known."""
        t = float(time_s)
        if not math.isfinite(t):
            raise ValueError(f"{self.path}: row time must be finite, got {time_s!r}")
        q = quat_xyzw_from_matrix(fit.base_R)
        self._csv.writerow([
            f"{t:.9f}", str(instrument),
            *(f"{np.degrees(getattr(fit.joints, n)):.6f}" for n in JOINT_NAMES),
            *(f"{v:.6f}" for v in fit.base_t), *(f"{v:.9f}" for v in q),
            f"{fit.rms_mm:.6f}" if fit.residuals else "", ";".join(fit.parts_used), ";".join(fit.held), int(fit.ok),
            *(f"{np.degrees(std[n]):.6f}" if std and n in std else "" for n in JOINT_NAMES),
        ])
        self._f.flush()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> JointCsvWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_joint_csv(path: str | os.PathLike, rows: Iterable[tuple[float, str, JointFit]]) -> Path:
    """Write ``rows`` of ``(time_s, instrument_name, fit)`` to ``path`` (columns in
    :data:`JOINT_CSV_COLUMNS`; angles in degrees, lengths in mm) and return the path. Rows are written in
    the order given. An unwritable path raises ``OSError`` naming it."""
    with JointCsvWriter(path) as w:
        for time_s, instrument, fit in rows:
            w.add(time_s, instrument, fit)
    return w.path

"""Joint angles fitted to tracked part poses, frame by frame: the kinematics output of a run whose
instrument is tracked part by part (``articulated: false``); with one articulated state per instrument
(:mod:`surftrack.track.instrument`) the joints are read off that state instead.

:class:`ArticulationTracker` fits each instrument's articulated configuration (base pose on the shaft
axis, roll, wrist pitch, wrist yaw, jaw opening; :func:`surftrack.instruments.fit_configuration`) to
the poses of its parts that have one this frame, weighted by their confidence and warm-started from the
previous fit. The trocar (remote centre of motion) is estimated from the measured shaft's axes (its own
pose, not the fit's, which the trocar pulls) once enough of them (``trocar_after``) have been seen,
re-estimated every ``trocar_every`` fits, and used as a constraint from then on; it stays unknown while
the axes barely change direction (they then do not pin a point). The trocar is a point in camera
coordinates, so it assumes the endoscope holds still: when ``trocar_patience`` fits in a row with a
shaft are poor under it (residuals beyond the ``FitConfig`` thresholds: the camera moved, or the first
estimate was wrong), it is forgotten with the axes seen so far and estimated again from the axes that
follow.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from surftrack.geometry import se3
from surftrack.instruments import (
    Instrument,
    JointFit,
    estimate_trocar,
    fit_configuration,
    load_instrument,
)
from surftrack.track.status import POSED
from surftrack.track.state import PartState


class ArticulationTracker:
    """Per (instrument, instance): ``update(states)`` -> the frame's :class:`JointFit`, or None when no
    part is posed or the fit fails."""

    def __init__(self, instrument: Instrument | str, trocar_after: int = 30, trocar_every: int = 30,
                 history: int = 300, trocar_patience: int = 10):
        self.instrument = load_instrument(instrument) if isinstance(instrument, str) else instrument
        self.root = self.instrument.chain.order[0]  # the part whose axis passes the trocar (the shaft)
        self.prev: JointFit | None = None
        self.trocar: np.ndarray | None = None
        self.axes: deque = deque(maxlen=history)
        self.trocar_after, self.trocar_every, self.trocar_patience = trocar_after, trocar_every, trocar_patience
        self._since_trocar = 0
        self._trocar_misses = 0  # fits in a row whose shaft axis missed the trocar

    def update(self, states: list[PartState]) -> JointFit | None:
        poses = {s.spec.part: (s.R, s.t) for s in states if s.status in POSED and s.R is not None}
        if not poses:
            return None
        weights = {s.spec.part: max(s.confidence, 0.05) for s in states if s.spec.part in poses}
        try:
            fit = fit_configuration(self.instrument, poses, weights=weights, trocar_mm=self.trocar, init=self.prev)
            if self.trocar is not None and self.root in fit.parts_used:
                self._trocar_misses = 0 if fit.ok else self._trocar_misses + 1
                if self._trocar_misses >= self.trocar_patience:  # the camera moved: start the trocar afresh
                    self.trocar, self._trocar_misses = None, 0
                    self.axes.clear()
                    fit = fit_configuration(self.instrument, poses, weights=weights, init=self.prev)
        except ValueError:
            return None
        self.prev = fit
        if self.root in fit.parts_used and fit.ok:
            # the root's own axis, not the fit's: a fit pulled through the trocar would confirm a wrong one
            self.axes.append(self._measured_axis(fit, poses[self.root]))
            self._since_trocar += 1
            if len(self.axes) >= self.trocar_after and (self.trocar is None or self._since_trocar >= self.trocar_every):
                self._since_trocar = 0
                try:
                    self.trocar = estimate_trocar(list(self.axes))
                except ValueError:
                    pass  # near-parallel axes: the point is not determined yet
        return fit

    def _measured_axis(self, fit: JointFit, root_pose: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The base pose (R, t) that puts the root part at its measured ``root_pose``, the root's fixed
        offset from the base taken from ``fit``: its shaft axis is the measurement's alone."""
        base_in_root = np.linalg.inv(fit.part_poses(self.instrument)[self.root]) @ fit.base_pose
        T = se3(*root_pose) @ base_in_root
        return T[:3, :3], T[:3, 3]

"""Where a tracking run's frames go: one small interface, one class per output.

:func:`surftrack.annotate.annotate_video` hands every written frame (after smoothing) to each sink's
:meth:`FrameSink.write`: the frame's index, time (s), image (H, W, 3 uint8 RGB, undistorted; None when no
sink needs it) and the parts' :class:`~surftrack.track.PartState`. The files behind the sinks are opened
and closed by the caller (a context stack), so a run that stops early still finishes them.
"""

from __future__ import annotations

import time
from collections import Counter
from typing import Protocol

import cv2
import numpy as np

from surftrack.instruments import JOINT_NAMES
from surftrack.track import PartSpec, PartState, Status
from surftrack.track.instrument import read_joints
from surftrack.track.kalman import speed_std


class FrameSink(Protocol):
    """An output of a tracking run."""

    def write(self, index: int, time_s: float, frame: np.ndarray | None, states: list[PartState]) -> None:
        """Add one frame."""


def status_rgba(status: Status) -> tuple[float, float, float, float]:
    """The overlay's colour of a status as RGBA in [0, 1] (MCAP annotations)."""
    from surftrack.io.overlay import STATUS_COLORS

    return (*(c / 255.0 for c in STATUS_COLORS[status]), 1.0)


def uncertainty(s: PartState) -> dict:
    """Per-axis standard deviations of a part's pose (mm; body rotation, deg), its velocity (camera frame,
    mm/s; body angular velocity, deg/s) and its speed's standard deviation (mm/s) from its filter state,
    for the status message."""
    if s.filter_step is None:
        return {}
    sd = np.sqrt(np.clip(np.diag(s.filter_step.P), 0.0, None))
    x = s.filter_step.x
    v = x[3:6]
    return {"position_std_mm": sd[0:3].round(3).tolist(), "rotation_std_deg": np.degrees(sd[6:9]).round(3).tolist(),
            "velocity_mm_s": v.round(3).tolist(), "angular_velocity_deg_s": np.degrees(x[9:12]).round(3).tolist(),
            "speed_std_mm_s": round(speed_std(v, s.filter_step.P[3:6, 3:6]), 3)}


def image_annotations(K: np.ndarray, states: list[PartState]) -> dict:
    """Projected axes (x red, y green, z blue), boxes and labels for foxglove.ImageAnnotations."""
    from surftrack.io.overlay import project_axes

    points, texts = [], []
    axis_rgb = ((1, 0, 0, 1), (0, 1, 0, 1), (0, 0.4, 1, 1))
    for s in states:
        if s.box is not None:
            x, y, w, h = s.box
            points.append({"points": [(x, y), (x + w, y), (x + w, y + h), (x, y + h)], "type": "line_loop",
                           "color": status_rgba(s.status), "thickness": 1.0})
        if s.R is None:
            continue
        # OpenCV puts pixel centres on integers, Foxglove on half-integers (its origin is the top-left
        # pixel's corner); boxes are in edge coordinates already
        ax = project_axes(K, s.R, s.t, 8.0) + 0.5
        if np.all(np.isfinite(ax)):
            for k in range(3):
                points.append({"points": [ax[0], ax[k + 1]], "type": "line_list", "color": axis_rgb[k],
                               "thickness": 2.0})
            texts.append({"position": ax[0], "text": f"{s.spec.part} {s.status} {s.confidence:.2f}",
                          "font_size": 11.0})
    return {"points": points, "texts": texts}


class McapSink:
    """Poses, ``/tf``, statuses (with the pose's uncertainty), part meshes in the 3D scene while a part has
    a pose, and with ``images`` the JPEG frames and their annotations, to a :class:`~surftrack.io.TrackWriter`."""

    def __init__(self, writer, specs: list[PartSpec], K: np.ndarray, images: bool = False):
        self.writer, self.specs, self.K, self.images = writer, specs, K, images
        self.shown: set[str] = set()

    def write(self, index: int, time_s: float, frame: np.ndarray | None, states: list[PartState]) -> None:
        w = self.writer
        posed = {s.spec.name: (s.R, s.t) for s in states if s.R is not None}
        for s in states:
            w.status(time_s, s.spec.name, s.status, s.confidence, {**s.info.as_dict(), **uncertainty(s)})
        if posed:
            w.poses(time_s, posed)
        now = set(posed)
        if now - self.shown:
            w.scene_meshes(time_s, {s.name: (s.vertices, s.faces, (0.75, 0.75, 0.8, 1.0))
                                    for s in self.specs if s.name in now - self.shown})
        if self.shown - now:
            w.scene_deletions(time_s, sorted(self.shown - now))
        self.shown = now
        if self.images:
            _, jpg = cv2.imencode(".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
            w.image_jpeg(time_s, jpg.tobytes())
            w.annotations(time_s, **image_annotations(self.K, states))


class OverlaySink:
    """Each part's outline, axes, box and status drawn on the frame (:class:`~surftrack.io.overlay.OverlayWriter`)."""

    def __init__(self, overlay):
        self.overlay = overlay

    def write(self, index: int, time_s: float, frame: np.ndarray | None, states: list[PartState]) -> None:
        from surftrack.io.overlay import PartOverlay

        self.overlay.write(frame, time_s, [PartOverlay(s.spec.name, s.status, s.confidence, s.R, s.t, s.box,
                                                       (s.spec.vertices, s.spec.faces), 8.0) for s in states])


class TumSink:
    """One TUM trajectory per part (:class:`~surftrack.io.tum.TumWriter`)."""

    def __init__(self, tum):
        self.tum = tum

    def write(self, index: int, time_s: float, frame: np.ndarray | None, states: list[PartState]) -> None:
        for s in states:
            if s.R is not None:
                self.tum.add(s.spec.name, time_s, s.R, s.t)


class JointsSink:
    """Each instrument's joint angles, as foxglove.JointStates in the MCAP (with their rates as
    ``velocity``, rad/s, where known, and the tool tip, :meth:`~surftrack.instruments.Instrument.tool_tip`,
    on ``.../tool_tip``, with its uncertainty on ``.../tool_tip_std`` when read off the state) and, with
    ``csv``, rows of a :class:`~surftrack.io.joints_csv.JointCsvWriter`.
    An instrument tracked as one articulated state (:mod:`surftrack.track.instrument`) has its joints
    read off that (smoothed) state; otherwise ``fitters`` ((instrument, instance) ->
    :class:`~surftrack.track.articulation.ArticulationTracker`) fit them to the parts' poses.
    ``timing["joints_s"]`` accumulates the time spent."""

    def __init__(self, writer, fitters: dict, csv=None, timing: Counter | None = None):
        self.writer, self.fitters, self.csv = writer, fitters, csv
        self.timing = timing if timing is not None else Counter()

    def write(self, index: int, time_s: float, frame: np.ndarray | None, states: list[PartState]) -> None:
        for (inst, instance), fitter in self.fitters.items():
            t0 = time.perf_counter()
            mine = [s for s in states if (s.spec.instrument, s.spec.instance) == (inst, instance)]
            shared = next((s.shared for s in mine if s.shared is not None), None)
            rates: dict[str, float] = {}
            std: dict[str, float] | None = None
            reading = None
            if shared is not None:
                reading = read_joints(shared[1], shared[2], [s.spec.name for s in mine if s.R is not None])
                fit, tip, rates, std = reading.fit, reading.tip, reading.rates, reading.std
            else:
                fit = fitter.update(mine)
                tip = fitter.instrument.tool_tip(fit.part_poses(fitter.instrument)) if fit is not None else None
            self.timing["joints_s"] += time.perf_counter() - t0
            if fit is None:
                continue
            label = f"{inst}.{instance}"
            self.writer.joint_states(time_s, label, JOINT_NAMES, [getattr(fit.joints, n) for n in JOINT_NAMES],
                                     {"velocity": [rates.get(n) for n in JOINT_NAMES]} if rates else None)
            if std:
                self.writer.joint_states(time_s, label, JOINT_NAMES, [std.get(n) for n in JOINT_NAMES], kind="joints_std")
            if tip is not None:
                self.writer.tool_tip(time_s, label, *tip)
                if reading is not None and reading.tip_cov is not None:
                    self.writer.tool_tip_std(time_s, label, reading.tip_cov, reading.tip_velocity,
                                             reading.tip_speed_std)
            if self.csv is not None:
                self.csv.add(time_s, label, fit, std)

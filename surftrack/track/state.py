"""What the tracker reports for a part on a frame: :class:`PartSpec` (the part tracked), :class:`PartState`
(its status, pose, confidence and the filter state behind it, which smoothing, scoring and the output
sinks read) and :func:`confidence`; :func:`filter_steps` and :func:`ended_revisions` gather a frame's filter
states for the smoother. The state machine that makes them is :mod:`.tracker`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from surftrack.eval import diameter_bbox_diagonal
from surftrack.geometry import Box
from surftrack.track.config import TrackConfig
from surftrack.track.instrument import InstrumentKalman
from surftrack.track.kalman import FilterStep
from surftrack.track.status import Diagnostics, Status


@dataclass(frozen=True)
class PartSpec:
    """A part to track: ``track_id`` (det.json part id), the model's ``obj_id``, names, and the mesh."""

    track_id: int
    obj_id: int
    instrument: str
    instance: int
    part: str
    vertices: np.ndarray
    faces: np.ndarray

    @property
    def name(self) -> str:
        """Topic-safe unique name ``<instrument>.<instance>.<part>``."""
        return f"{self.instrument}.{self.instance}.{self.part}"

    @functools.cached_property
    def diameter(self) -> float:
        """The part's diameter (mm), SurgRIPE's bounding-box diagonal, as ADD-10 scores it."""
        return diameter_bbox_diagonal(self.vertices)


@dataclass
class PartState:
    """One part on one frame. ``R``, ``t`` (mm, model-to-camera) are None when there is no pose.
    ``box``: the box used or predicted (x, y, w, h pixel edges). ``info``: what the tracker did for it
    (:class:`~.status.Diagnostics`: why the estimator ran, its score, the measurements' fit, timings).
    ``confidence``: :func:`confidence` from the filter's covariance (the causal one as :meth:`.tracker.Tracker.step`
    returns it; :meth:`settle` recomputes it from the smoothed state); 0 without a pose."""

    spec: PartSpec
    status: Status
    confidence: float
    R: np.ndarray | None
    t: np.ndarray | None
    box: Box | None
    info: Diagnostics = field(default_factory=Diagnostics)
    filter_step: FilterStep | None = None  # the part's filter this frame (for smoothing; None without a pose)
    # the instrument's articulated state this part is a view of: (its smoothing key, the filter, its step)
    shared: tuple[str, InstrumentKalman, FilterStep] | None = None
    # a part without a pose whose track ended this frame: its last frames' steps as a track restarted in
    # hindsight (:meth:`.tracker._Track.ended_in_hindsight`), which the smoother writes instead (a part that
    # starts again in the same frame carries them on its new step's ``revises``)
    revises: tuple[FilterStep, ...] = ()

    def smoothing_key(self) -> str:
        """The key of the filter state this part's pose comes from (its own, or its instrument's)."""
        return self.shared[0] if self.shared is not None else self.spec.name

    def step_from(self, steps: Mapping[str, FilterStep | None]) -> FilterStep | None:
        """This part's step from the (smoothed) states ``steps`` (key -> step, :func:`filter_steps`)."""
        if self.R is None:
            return None
        step = steps.get(self.smoothing_key())
        if step is None or self.shared is None:
            return step
        return self.shared[1].part_step(step, self.spec.name)

    def with_step(self, step: FilterStep | None) -> PartState:
        """This state with its pose taken from ``step`` (e.g. the smoothed one)."""
        if step is None:
            return self
        R, t = step.pose
        return dataclasses.replace(self, R=R, t=t, filter_step=step)

    def settle(self, steps: Mapping[str, FilterStep | None], cfg: TrackConfig) -> PartState:
        """:meth:`settled` from the frame's (smoothed) filter states ``steps`` (:func:`filter_steps`); the
        instrument state it is a view of becomes the smoothed one too (for the joints read off it)."""
        out = self.settled(self.step_from(steps), cfg)
        if out.shared is not None and steps.get(out.shared[0]) is not None:
            out = dataclasses.replace(out, shared=(out.shared[0], out.shared[1], steps[out.shared[0]]))
        return out

    def settled(self, step: FilterStep | None, cfg: TrackConfig) -> PartState:
        """The state as a run writes it: pose from ``step`` (smoothed, or the filter's when causal) and
        its confidence, :func:`confidence`. Smoothed after a restart in hindsight, the frame where the new
        track begins is the restart (``restarted``), and the frame the tracker restarted on is not."""
        out = self.with_step(step)
        if out.filter_step is None:
            return out
        nis = 1.0 if self.info.nis is None else self.info.nis
        # the smoother moving the pose away from what the forward filter had is a disagreement the
        # covariance does not show (zero when causal)
        moved = 0.0 if self.t is None else float(np.linalg.norm(out.t - self.t))
        causal = self.filter_step
        if step is not None and step is not causal and causal is not None:
            if step.revised:  # restarted in hindsight: the causal pose and its NIS were the old track's
                moved, nis = 0.0, 1.0
                if step.prior is None and causal.prior is not None:  # the smoothed track starts here
                    out = dataclasses.replace(out, status=Status.KEYFRAME,
                                              info=dataclasses.replace(out.info, restarted=True))
            elif causal.revises and self.info.restarted:  # the restart moved back to the revised frames
                out = dataclasses.replace(out, info=dataclasses.replace(out.info, restarted=None))
        conf = confidence(out.filter_step.P[0:3, 0:3], nis, moved, self.spec.diameter, cfg)
        return dataclasses.replace(out, confidence=conf)


def confidence(pos_cov: np.ndarray, nis: float, moved_mm: float, diameter_mm: float, cfg: TrackConfig) -> float:
    """A pose's confidence: the probability that its position error is within ``cfg.confidence_add``
    times the part's diameter (the ADD-10 threshold by default), the error taken as zero-mean Gaussian
    with the filter's position covariance ``pos_cov`` (3x3, mm^2) scaled by the track's running
    normalised innovation ``nis`` (its measurements disagreeing with it more than their covariances
    allow: covariance matching), plus ``moved_mm`` (how far smoothing moved the pose) squared spread over
    the three axes, the standard deviations inflated by ``cfg.confidence_scale``. The probability is
    counted over a fixed set of standard-normal samples (the covariance is not round: depth is the least
    certain). On the three development clips (docs/decisions.md) it ranked ADD with a Spearman rho of
    -0.57 against -0.39 for the earlier ``exp(-s^2 / 2c^2)`` of the covariance; the covariance alone
    ranked clip 22's errors backwards (+0.18: a state settled on a wrong configuration, tight and
    wrong). The rotation's uncertainty is not in it."""
    C = np.asarray(pos_cov, np.float64) * max(nis, 0.0) + np.eye(3) * (moved_mm ** 2 / 3.0)
    var = np.clip(np.linalg.eigvalsh(0.5 * (C + C.T)), 0.0, None) * cfg.confidence_scale ** 2
    r = cfg.confidence_add * diameter_mm
    return float(np.mean((_UNIT_NORMAL ** 2) @ var <= r * r))


# fixed standard-normal samples in 3D for :func:`confidence` (repeatable; resolution 1/4096)
_UNIT_NORMAL = np.random.default_rng(0).standard_normal((4096, 3))


def filter_steps(states: Sequence[PartState]) -> dict[str, FilterStep | None]:
    """The filter states behind a frame's part states, by smoothing key: one per described instrument
    (its articulated state), one per free part."""
    out: dict[str, FilterStep | None] = {}
    for s in states:
        if s.shared is not None:  # set on the parts with a pose only
            out[s.shared[0]] = s.shared[2]
        else:
            out[s.spec.name] = s.filter_step
    return out


def ended_revisions(states: Sequence[PartState]) -> dict[str, tuple[FilterStep, ...]]:
    """The revised steps of the parts whose tracks ended this frame and that have no pose on it
    (:attr:`PartState.revises`), by smoothing key, for :meth:`~.smoother.LagSmoother.push` (the steps of
    the posed parts carry theirs)."""
    return {s.smoothing_key(): s.revises for s in states if s.revises}

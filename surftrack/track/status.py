"""The status of a part on a frame, one vocabulary for the tracker, the overlay, the MCAP and analysis, and
the diagnostics that come with it."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any


class Status(str, Enum):
    """A part's status on one frame (a ``str``: it is written as its value).

    * ``init``: not seen yet (no usable box so far);
    * ``keyframe``: the estimator ran this frame and its pose was taken (fused into the filter);
    * ``tracking``: a region (silhouette) or flow measurement was accepted by the filter;
    * ``predicted``: the filter carried the pose (no acceptable measurement this frame; smoothed runs
      interpolate it from the frames on both sides);
    * ``lost``: no pose (no box and nothing to track, the part left the image, or recovery failed).
    """

    INIT = "init"
    KEYFRAME = "keyframe"
    TRACKING = "tracking"
    PREDICTED = "predicted"
    LOST = "lost"

    def __str__(self) -> str:  # its value, as enum.StrEnum (Python >= 3.11) would give
        return self.value

    @property
    def posed(self) -> bool:
        """Whether a part with this status has a pose."""
        return self in POSED


#: Statuses that come with a pose.
POSED = frozenset({Status.KEYFRAME, Status.TRACKING, Status.PREDICTED})
#: Statuses whose pose was measured this frame (not only carried by the filter).
MEASURED = frozenset({Status.KEYFRAME, Status.TRACKING})
#: Why the estimator ran (``Diagnostics.estimator``) when its pose starts a part's track afresh.
FRESH_STARTS = frozenset({"init", "reappearance"})


def starts_anew(status: str, info: Mapping[str, Any]) -> bool:
    """Whether a part's pose on a frame does not continue its pose on the frame before: the track restarted
    at an estimate its filter had refused (``restarted``: the track was wrong), started again from an
    estimate after it was dropped, or was set from outside. The step into such a frame is a correction or
    a new track, not motion: kinematics count no distance across it. ``status``: the frame's status (a
    :class:`Status` or its value); ``info``: its diagnostics (:meth:`Diagnostics.as_dict`, or the MCAP's
    status ``extra``)."""
    return str(status) == Status.KEYFRAME.value and (
        bool(info.get("restarted")) or info.get("estimator") in FRESH_STARTS or info.get("source") == "set_pose")


@dataclass
class Diagnostics:
    """What the tracker did for one part on one frame; a field is None when it does not apply (the MCAP's
    status messages carry the set ones, :meth:`as_dict`).

    Estimator (a keyframe): ``estimator`` why it ran (``init``, ``reappearance``, ``cadence``, ``box
    disagreement``, ``instrument keyframe``, ``no measurement``), ``estimator_ms`` this
    part's share of the call, ``score`` and ``est_inliers`` its pose's, ``prior_won`` whether the tracked
    pose beat the estimator's hypotheses, ``kinematic`` whether the pose is the instrument fit's,
    ``restarted`` whether the track was restarted at the estimate (``kalman.max_rejections`` estimates in a
    row outside the filter's gate).
    Filter: ``d2`` the accepted measurement's squared Mahalanobis distance, ``rejected_d2`` that of one
    the gate kept out, ``nis`` the track's running normalised innovation (1 when its measurements agree
    with their covariances). Flow: ``points`` followed, ``inliers``, ``inlier_ratio``, ``rms_px`` of its
    PnP, ``flow_ms``, ``refresh_ms`` (picking new points). Region: ``region_lines`` correspondence lines,
    ``agreement`` the share of line pixels on the right side of the fitted outline, ``region_ms``.
    ``source``: ``set_pose`` when the pose was given from outside. ``occluded``: frames held in a row
    while hidden and the rest of the instrument is seen; ``why_lost``: why the part was dropped, or why an
    estimate did not start it.
    """

    estimator: str | None = None
    estimator_ms: float | None = None
    score: float | None = None
    est_inliers: int | None = None
    prior_won: bool | None = None
    kinematic: bool | None = None
    restarted: bool | None = None
    d2: float | None = None
    rejected_d2: float | None = None
    nis: float | None = None
    points: int | None = None
    inliers: int | None = None
    inlier_ratio: float | None = None
    rms_px: float | None = None
    flow_ms: float | None = None
    refresh_ms: float | None = None
    region_lines: int | None = None
    agreement: float | None = None
    region_ms: float | None = None
    source: str | None = None
    occluded: int | None = None
    why_lost: str | None = None

    def as_dict(self) -> dict:
        """The fields that are set, by name (JSON-ready)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}

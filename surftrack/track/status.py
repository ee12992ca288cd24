"""The status of a part on a frame: one vocabulary for the tracker, the overlay, the MCAP and analysis."""

from __future__ import annotations

from enum import Enum


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

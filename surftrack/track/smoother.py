"""Offline smoothing of the pose filter: every frame's pose also uses the frames after it.

:func:`rts_smooth` is the Rauch-Tung-Striebel backward pass for :class:`~.kalman.PoseKalman`'s error-state
filter. The rotation lives outside the filter's vector state (a nominal ``R`` per frame, the error a body
rotation vector), so each backward step first re-expresses the smoothed state of frame k+1 in the chart
of frame k+1's prediction (``dtheta = log(R_pred^T R_smooth)``, its covariance through that map's
Jacobian), applies the linear RTS gain ``C = P_f F^T P_pred^-1`` there and injects the rotation
correction into frame k's nominal with the filter's reset Jacobian (:func:`~.kalman.inject_rotation`). With no
rotation this is exactly the linear RTS smoother; filterpy's ``KalmanFilter.rts_smoother`` is that linear
one (one fixed chart for the whole run), so it cannot carry the per-frame rotation charts, and the
tests check this pass against it and against a brute-force batch solution on a linear case.

:class:`LagSmoother` applies it to a stream of tracked frames with a fixed delay: frames wait in a buffer
until ``lag`` newer frames exist, so each is smoothed with at least ``lag`` frames of future (for a
constant-velocity model a second of future holds nearly all the information a full pass would use) while
memory stays flat in the video's length. ``lag = 0`` passes frames through unchanged (causal). A step
that ``revises`` earlier frames (a track restarted in hindsight) replaces their buffered steps before the
next pass; frames already released keep what was written.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from surftrack.track.kalman import FilterStep, change_chart, inject_rotation


def rts_smooth(steps: Sequence[FilterStep | None]) -> list[FilterStep | None]:
    """Smoothed states of one part's consecutive frames (None where the part has no pose). A step
    whose ``prior`` is None starts a segment: no smoothing crosses it, nor a None. The smoothed steps
    keep their ``prior`` (the filter's, for chaining) and ``time``."""
    out: list[FilterStep | None] = list(steps)
    for k in range(len(steps) - 2, -1, -1):
        cur, nxt, s_nxt = steps[k], steps[k + 1], out[k + 1]
        if cur is None or nxt is None or nxt.prior is None or s_nxt is None:
            continue
        pr = nxt.prior
        d, P_nxt = change_chart(s_nxt.R, s_nxt.x, s_nxt.P, pr.R)  # smoothed k+1 in its prediction's chart
        C = np.linalg.solve(pr.P.T, (cur.P @ pr.F.T).T).T  # P_f F^T P_pred^-1 (P_pred symmetric)
        x = cur.x + C @ (d - pr.x)
        P = cur.P + C @ (P_nxt - pr.P) @ C.T
        R, x, P = inject_rotation(cur.R, x, P)
        out[k] = FilterStep(cur.time, R, x, P, cur.prior, revised=cur.revised)
    return out


class LagSmoother:
    """Fixed-lag smoothing of a stream of frames. ``push(item, steps)`` adds a frame: ``item`` is
    anything the caller wants back (the frame, its states), ``steps`` maps a key (a part's name) to its
    :class:`FilterStep` or None. Returns the frames that are ready, oldest first, as
    ``(item, smoothed steps)``; :meth:`flush` returns the rest at the end of a run (or when it stops).
    A frame is released once ``lag`` newer frames exist; the backward pass runs every ``chunk`` frames
    over the buffer (``lag + chunk`` frames at most), so each frame costs about ``(lag + chunk) / chunk``
    backward steps per part."""

    def __init__(self, lag: int, chunk: int | None = None):
        if lag < 0:
            raise ValueError(f"lag must be >= 0 frames, got {lag}")
        self.lag = int(lag)
        self.chunk = max(1, self.lag // 4) if chunk is None else max(1, int(chunk))
        self._buf: list[tuple[Any, dict[str, FilterStep | None]]] = []

    def __len__(self) -> int:
        return len(self._buf)

    def push(self, item: Any, steps: dict[str, FilterStep | None]) -> list[tuple[Any, dict[str, FilterStep | None]]]:
        steps = dict(steps)
        for key, step in steps.items():
            if step is not None and step.revises and self.lag:
                self._revise(key, step.revises)
                steps[key] = dataclasses.replace(step, revises=())  # done with: not kept, and not the causal step
        self._buf.append((item, steps))
        if len(self._buf) < self.lag + self.chunk:
            return []
        return self._release(len(self._buf) - self.lag)

    def _revise(self, key: str, revised: Sequence[FilterStep]) -> None:
        """Swap the buffered steps of ``key`` for the ``revised`` ones of the same frames (matched by
        time). Frames already released keep theirs, and the first revised frame still buffered then
        starts a segment: the revised run does not continue what was written."""
        by_time = {r.time: r for r in revised}
        first = True
        for _, st in self._buf:
            old = st.get(key)
            if old is not None and old.time in by_time:
                new = by_time[old.time]
                if first and new.time != revised[0].time:
                    new = dataclasses.replace(new, prior=None)
                st[key], first = new, False

    def flush(self) -> list[tuple[Any, dict[str, FilterStep | None]]]:
        return self._release(len(self._buf))

    def _release(self, n: int) -> list[tuple[Any, dict[str, FilterStep | None]]]:
        if n <= 0:
            return []
        keys = list(dict.fromkeys(k for _, st in self._buf for k in st))
        smoothed = {k: rts_smooth([st.get(k) for _, st in self._buf]) for k in keys} if self.lag else {}
        out = []
        for i, (item, st) in enumerate(self._buf[:n]):
            out.append((item, {k: smoothed[k][i] for k in st} if self.lag else st))
        # the released frames' successors keep their filtered steps: the next pass smooths them again from
        # newer data, and only needs the filtered state of each frame
        del self._buf[:n]
        return out

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
that ``revises`` earlier frames (a track restarted in hindsight), or a revision pushed with a frame (a
track that ended, no step of its own to carry it), replaces their buffered steps before the next pass;
frames already released keep what was written.

The smoother may assume another motion prior than the filter (:class:`SmootherPrior`): the filter's prior
serves its gate and keyframe decisions, where a stiff one lags real moves and refuses the keyframes that
follow them; the smoother only decides how far to believe each frame's measurements, and the
estimator's depth is the one that errs (2-3 mm along the line of sight, correlated over many frames,
against 0.2 mm across it), so a stiffer prior along the line of sight keeps its wander out of the speeds
and paths (docs/results/2026-12-06-smoother-prior.md). Its rotation prior is stiffer than the filter's
too: the tool tip, 10 mm out on the jaws, moves with every wobble of their rotation, and its speed is
read off the smoothed rotations (docs/results/2026-12-06-tip-rotation-prior.md). The filter is then run
again under that prior (:func:`refilter_under`), with each frame's measurement information recovered
from the filter's own prediction and posterior, and smoothed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from surftrack.track.kalman import (FilterPrior, FilterStep, change_chart, cut_pose_from_rates, inject_rotation,
                                    white_noise_q)


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


@dataclasses.dataclass(frozen=True)
class SmootherPrior:
    """The smoother's white-noise acceleration of a part's position, split across
    (``lateral_accel_std_mm_s2``) and along (``depth_accel_std_mm_s2``) the line of sight through it, in
    place of the filter's isotropic ``filter_accel_std_mm_s2`` (all mm/s^2); and of its rotation,
    ``ang_accel_std_rad_s2`` in place of the filter's ``filter_ang_accel_std_rad_s2`` (rad/s^2; both or
    neither: None keeps the filter's)."""

    filter_accel_std_mm_s2: float
    lateral_accel_std_mm_s2: float
    depth_accel_std_mm_s2: float
    filter_ang_accel_std_rad_s2: float | None = None
    ang_accel_std_rad_s2: float | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None and f.name.endswith("rad_s2"):
                continue
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{f.name} must be > 0, got {v!r}")
        if (self.filter_ang_accel_std_rad_s2 is None) != (self.ang_accel_std_rad_s2 is None):
            raise ValueError("filter_ang_accel_std_rad_s2 and ang_accel_std_rad_s2 come together")

    def rotation_q_change(self, dt: float) -> np.ndarray | None:
        """(6, 6): what this prior adds to the filter's process noise of ``[dtheta, omega]`` (rad, rad/s)
        over ``dt`` s, or None where the rotation keeps the filter's prior."""
        if self.ang_accel_std_rad_s2 is None:
            return None
        return white_noise_q(dt, self.ang_accel_std_rad_s2**2 - self.filter_ang_accel_std_rad_s2**2)

    def position_q_change(self, direction: np.ndarray, dt: float) -> np.ndarray:
        """(6, 6): what this prior adds to the filter's process noise of ``[t, v]`` (mm, mm/s) over ``dt``
        s for a part seen along ``direction`` (3,) from the camera."""
        u = np.asarray(direction, np.float64)
        u = u / max(float(np.linalg.norm(u)), 1e-9)
        uu = np.outer(u, u)
        q0 = self.filter_accel_std_mm_s2**2
        M = (self.lateral_accel_std_mm_s2**2 - q0) * (np.eye(3) - uu) + (self.depth_accel_std_mm_s2**2 - q0) * uu
        return np.kron(white_noise_q(dt, 1.0, axes=1), M)


def _sym_inv(P: np.ndarray) -> np.ndarray:
    M = np.linalg.inv(P)
    return 0.5 * (M + M.T)


def refilter_under(steps: Sequence[FilterStep | None], prior: SmootherPrior,
                   before: tuple[FilterStep, FilterStep] | None = None) -> list[FilterStep | None]:
    """One part's filtered steps (consecutive frames, None where it has no pose) as the filter would have
    given them under the smoother's ``prior``. Each frame's measurement information (everything it
    fused: keyframe, silhouette, flow) is the filter's posterior information less its prediction's, in
    the prediction's chart; the prediction is re-made about the same nominal trajectory (the filter's
    transition ``F``, its process noise with :meth:`SmootherPrior.position_q_change` and
    :meth:`SmootherPrior.rotation_q_change` added, a restart's widening and cut between pose and rates as
    the filter made them) and the information fused into it.
    An instrument's articulated state (:class:`~.instrument.InstrumentKalman`) is re-filtered alike, the
    prior applied to its root's pose (its first 12 entries; the joints keep the filter's). Its restart
    widens the state after whatever the frame fused before it (the trocar, the parts updated earlier),
    and is taken here as part of the prediction: exact where the frame fused nothing before the restart
    (and always under the filter's own prior), an approximation otherwise; so is a measurement the filter
    linearised at its own state. A segment start (no ``prior``) is kept as it is.
    ``before``: the (filtered, re-filtered) steps of the frame before ``steps[0]``, for a stream. The
    re-filtered steps stay in the filter's nominal rotations, so unlike a filter's their ``dtheta`` is not
    0 (it carries the rotation difference; :attr:`FilterStep.pose` includes it); their ``prior`` is the
    re-made prediction, for :func:`rts_smooth`."""
    out: list[FilterStep | None] = []
    prev = before
    for step in steps:
        if step is None:
            out.append(None)
            prev = None
            continue
        if step.prior is None or prev is None:
            out.append(step)
            prev = (step, step)
            continue
        old, new = prev
        pr = step.prior
        F = pr.F
        # the filter's process noise (and a restart's widening) as it entered this prediction
        Q = pr.P - F @ old.P @ F.T
        Q[0:6, 0:6] += prior.position_q_change(pr.x[0:3], step.time - old.time)
        dq = prior.rotation_q_change(step.time - old.time)
        if dq is not None:
            Q[6:12, 6:12] += dq
        P_pred = F @ new.P @ F.T + Q
        if pr.restarted:  # the restart's cut between pose and rates, as the filter made it
            P_pred = cut_pose_from_rates(P_pred)
        P_pred = 0.5 * (P_pred + P_pred.T)
        x_pred = pr.x + F @ (new.x - old.x)
        x_post, P_post = change_chart(step.R, step.x, step.P, pr.R)
        info_post, info_pr, info_pred = _sym_inv(P_post), _sym_inv(pr.P), _sym_inv(P_pred)
        P = _sym_inv(info_pred + info_post - info_pr)
        x = P @ (info_pred @ x_pred + info_post @ x_post - info_pr @ pr.x)
        x, P = change_chart(pr.R, x, P, step.R)
        fresh = FilterStep(step.time, step.R, x, P, FilterPrior(F, pr.R, x_pred, P_pred), revised=step.revised)
        out.append(fresh)
        prev = (step, fresh)
    return out


class LagSmoother:
    """Fixed-lag smoothing of a stream of frames. ``push(item, steps)`` adds a frame: ``item`` is
    anything the caller wants back (the frame, its states), ``steps`` maps a key (a part's name) to its
    :class:`FilterStep` or None. Returns the frames that are ready, oldest first, as
    ``(item, smoothed steps)``; :meth:`flush` returns the rest at the end of a run (or when it stops).
    A frame is released once ``lag`` newer frames exist; the backward pass runs every ``chunk`` frames
    over the buffer (``lag + chunk`` frames at most), so each frame costs about ``(lag + chunk) / chunk``
    backward steps per part. ``prior``: the smoother's own motion prior (:class:`SmootherPrior`; None:
    the filter's); the filter is run again under it over the buffer, continuing from the last released
    frame's re-filtered step. ``push(item, steps, revisions)``: revised steps of earlier frames by key,
    for a track that ended (:func:`~.state.ended_revisions`)."""

    def __init__(self, lag: int, chunk: int | None = None, prior: SmootherPrior | None = None):
        if lag < 0:
            raise ValueError(f"lag must be >= 0 frames, got {lag}")
        self.lag = int(lag)
        self.chunk = max(1, self.lag // 4) if chunk is None else max(1, int(chunk))
        # per buffered frame: the caller's item, its filtered steps and (with a prior) its re-filtered ones
        self._buf: list[tuple[Any, dict[str, FilterStep | None], dict[str, FilterStep | None]]] = []
        self.prior = prior
        # per key, the last released frame's (filtered, re-filtered) steps: where the next pass continues
        self._before: dict[str, tuple[FilterStep, FilterStep]] = {}

    def __len__(self) -> int:
        return len(self._buf)

    def push(self, item: Any, steps: dict[str, FilterStep | None],
             revisions: Mapping[str, Sequence[FilterStep]] | None = None
             ) -> list[tuple[Any, dict[str, FilterStep | None]]]:
        """``revisions``: per key, revised steps of earlier frames that no step of this frame carries (a
        track that ended, :func:`~.state.ended_revisions`)."""
        steps = dict(steps)
        if self.lag:
            for key, revised in (revisions or {}).items():
                self._revise(key, revised)
        for key, step in steps.items():
            if step is not None and step.revises and self.lag:
                self._revise(key, step.revises)
                steps[key] = dataclasses.replace(step, revises=())  # done with: not kept, and not the causal step
        self._buf.append((item, steps, {}))
        if len(self._buf) < self.lag + self.chunk:
            return []
        return self._release(len(self._buf) - self.lag)

    def _revise(self, key: str, revised: Sequence[FilterStep]) -> None:
        """Swap the buffered steps of ``key`` for the ``revised`` ones of the same frames (matched by
        time). Frames already released keep theirs, and the first revised frame still buffered then
        starts a segment: the revised run does not continue what was written."""
        by_time = {r.time: r for r in revised}
        first = True
        for _, st, fresh in self._buf:
            old = st.get(key)
            if old is not None and old.time in by_time:
                new = by_time[old.time]
                if first and new.time != revised[0].time:
                    new = dataclasses.replace(new, prior=None)
                st[key], first = new, False
            if not first:  # re-filtered again from the first revised frame on
                fresh.pop(key, None)

    def flush(self) -> list[tuple[Any, dict[str, FilterStep | None]]]:
        return self._release(len(self._buf))

    def _release(self, n: int) -> list[tuple[Any, dict[str, FilterStep | None]]]:
        if n <= 0:
            return []
        keys = list(dict.fromkeys(k for _, st, _ in self._buf for k in st))
        smoothed = {}
        if self.lag:
            for k in keys:
                steps = [st.get(k) for _, st, _ in self._buf]
                if self.prior is not None:
                    steps = self._refiltered(k, steps)
                smoothed[k] = rts_smooth(steps)
        out = []
        for i, (item, st, _) in enumerate(self._buf[:n]):
            out.append((item, {k: smoothed[k][i] for k in st} if self.lag else st))
        _, last, fresh = self._buf[n - 1]
        self._before = {k: (last[k], fresh[k]) for k in keys if fresh.get(k) is not None}
        # the released frames' successors keep their filtered steps: the next pass smooths them again from
        # newer data, and only needs the filtered state of each frame
        del self._buf[:n]
        return out

    def _refiltered(self, key: str, steps: list[FilterStep | None]) -> list[FilterStep | None]:
        """``key``'s buffered ``steps`` re-filtered under the smoother's prior: from the first frame not
        re-filtered yet (new, or revised), continuing the frame before it."""
        cache = [fresh for _, _, fresh in self._buf]
        start = next((i for i, fresh in enumerate(cache) if key not in fresh), len(steps))
        if start < len(steps):
            if start == 0:
                before = self._before.get(key)
            else:
                prev = cache[start - 1][key]
                before = (steps[start - 1], prev) if prev is not None else None
            for fresh, step in zip(cache[start:], refilter_under(steps[start:], self.prior, before)):
                fresh[key] = step
        return [fresh[key] for fresh in cache]

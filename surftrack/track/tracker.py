"""Per-part tracking state machine: the estimator initialises and recovers, silhouettes (or flow) and a
Kalman filter carry the parts between keyframes.

Every part has a :class:`~.status.Status` on every frame.

The estimator runs for a part when it has a box and no track, and for a tracked part on the keyframe
cadence, after ``max_predicted`` frames without a measurement or when a detection box disagrees with
the part's projected box. A tracked part hands its pose to the estimator as a prior, so a keyframe never
replaces a pose that explains the image better. Boxes may be sparse: without a detection the part's own projected box is used, so one box per
appearance is enough. All parts needing the estimator in a frame share one batched call, and the poses
it returns for the parts of one instrument are made consistent with the instrument's kinematics
(``TrackConfig.kinematic``; :mod:`surftrack.pose.kinematic`). An estimator pose is a measurement of the
part's filter, gated like any other: a single disagreement is more often the estimator's outlier than a
real jump and is left out; ``kalman.max_rejections`` in a row restart the track: by default in hindsight,
from the first refused estimate the last one continues (``TrackConfig.retro_restart``: the smoother takes
the new track for the frames the old one was wrong on), else at the last estimate alone (widening the
prediction, so a smoothed run keeps the track in one piece, :meth:`PoseKalman.restart`). A track that
ends while its estimates are refused is revised the same way for the smoother, or, where the part
leaves the view, from the latest refused estimate that earlier ones continue
(:meth:`_Track.ended_in_hindsight`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence

import cv2
import numpy as np
import trimesh

from surftrack.geometry import Box, box_iou, projected_box, rotation_angle_deg, se3
from surftrack.instruments import BUILTIN, HALF_TURN, Instrument, InstrumentRegistry, JointState, joints_from_poses
from surftrack.pose import PartPose, PoseEstimator
from surftrack.pose.kinematic import apply_kinematics, check_anchor, described_instrument, instrument_parts
from surftrack.track.config import TrackConfig, TrackConfigError
from surftrack.track.flow import (SurfaceSamples, TrackPoints, pnp_measurement, pose_distance, track_points,
                                  visible_points)
from surftrack.track.instrument import InstrumentKalman, PartFilter
from surftrack.track.kalman import FilterStep, KalmanConfig, PoseKalman, refilter
from surftrack.track.region import ArticulatedModel, PoseModel, RegionConfig, RegionTracker, observed_directions
from surftrack.track.state import PartSpec, PartState
from surftrack.track.status import POSED, Diagnostics, Status
from surftrack.track.trocar import Trocar


# estimator runs the tracker scheduled itself (not asked for by a failing measurement)
SCHEDULED = ("cadence", "instrument keyframe", "box disagreement")
# vertices projected for a part's predicted box (a random subset: a CAD mesh's tens of thousands would be
# projected for every part on every frame, for a box that only gates and crops)
BOX_VERTICES = 600
# surface points flow picks its visible points from (dense, so that the visibility test and the image's
# corners, not the sampling, decide which max_points are followed)
FLOW_SURFACE_SAMPLES = 12000
# a single measurement's d2 / dof counts at most this much in the running NIS: one wild outlier raises
# it (the confidence falls) without zeroing the confidence for the frames the NIS takes to forget it
NIS_CAP = 100.0
# an estimate the track keeps disbelieving replaces the prediction with this many times the estimator's
# covariance (10x its standard deviations) on top: wide enough to take the estimate, without cutting the
# track in two for the smoother
RESTART_WIDEN = 100.0
# a restart in hindsight goes back at most this far (s: the default smoothing lag; frames before it are
# written already) and takes no refused estimate turned further than this (deg) from the restarted
# track's (a flipped jaw or shaft roll, ~180 deg, which a fresh filter's rate uncertainty can let pass)
RETRO_MAX_S = 1.0
RETRO_MAX_TURN_DEG = 90.0
# an inconclusive estimate (too few inliers, a false box) asked for because the measurements failed keeps
# the track until this many times max_predicted frames have passed without a measurement
INCONCLUSIVE_PATIENCE = 3
# a part without a track that starts (first seen, or seen again after a drop) while other parts of its
# instrument are measured must lie within the chain's reach of one of them (KinematicChain.origin_reach) plus
# this much (mm: those tracks' and the estimate's own errors): an estimate from a sliver of a shaft at the
# image's edge once placed it a metre off, and the track took 8 frames of refusals to restart
REACH_TOLERANCE_MM = 20.0


def estimator_cov(t: np.ndarray, cfg: TrackConfig) -> np.ndarray:
    """The estimator's pose covariance (6x6: mm^2 for the position, rad^2 for the body rotation) for a
    part estimated at ``t`` (3,) mm in the camera: ``est_pos_std_mm`` along the line of sight through
    ``t``, ``est_lateral_std_mm`` across it (a monocular pose pins the image position far better than
    the depth: docs/results/2026-12-04-paths.md), ``est_rot_std_deg`` about each axis."""
    cov = np.diag([cfg.est_pos_std_mm**2] * 3 + [np.radians(cfg.est_rot_std_deg)**2] * 3)
    n = float(np.linalg.norm(t))
    if n > 0 and np.isfinite(n):
        u = np.asarray(t, np.float64) / n
        lat, depth = cfg.est_lateral_std_mm**2, cfg.est_pos_std_mm**2
        cov[:3, :3] = lat * np.eye(3) + (depth - lat) * np.outer(u, u)
    return cov


def agreeing_start(streak: Sequence[tuple[float, tuple | None]], R: np.ndarray, t: np.ndarray, cov: np.ndarray,
                   time_s: float, config: KalmanConfig) -> int | None:
    """Index in ``streak`` (frames of refused estimates in a row: ``(time s, (R, t, covariance) or
    None)``, oldest first) of the earliest refused estimate that the estimate ``R``, ``t`` (mm), ``cov``
    at ``time_s`` continues, or None. A filter run backward in time from it (the time negated; a
    constant-velocity model runs either way) takes them while they pass its gate; the first it refuses
    (another tool), one turned more than ``RETRO_MAX_TURN_DEG`` from it (a flipped jaw) or one older than
    ``RETRO_MAX_S`` ends the run."""
    back = PoseKalman(config)
    back.init(R, t, -time_s, cov)
    first, measured = None, True
    for k in range(len(streak) - 1, -1, -1):
        ts, meas = streak[k]
        if ts < time_s - RETRO_MAX_S:
            break
        back.predict(-ts, coast=not measured)
        measured = (meas is not None and rotation_angle_deg(meas[0], back.pose[0]) <= RETRO_MAX_TURN_DEG
                    and back.update(*meas))
        if meas is not None and not measured:
            break
        if measured:
            first = k
    return first


class _Track:
    """Mutable per-part state."""

    def __init__(self, spec: PartSpec, cfg: TrackConfig, shared: InstrumentKalman | None = None,
                 widen: np.ndarray | None = None):
        self.spec, self.cfg, self.shared, self.widen = spec, cfg, shared, widen
        self.kf = self.new_filter()
        self.status = Status.INIT
        self.points = TrackPoints(np.zeros((0, 2)), np.zeros((0, 3)))
        self.n_points_fresh = 0
        self.lift_cov = np.zeros((6, 6))  # pose covariance when the flow points were lifted to 3D
        self.since_keyframe = 0
        self.since_refresh = 0
        self.since_meas = 0
        self.seeded = False
        self.unseen = 0  # estimator runs in a row that saw nothing of a tracked part
        self.occluded = 0  # frames held (predicted) while unseen and the rest of its instrument was measured
        self.nis = 1.0  # running mean of the measurements' normalised innovation (d2 / dof; 1 when consistent)
        # frames since the first of the estimates in a row the filter refused: (time s, the refused
        # estimate (R, t, covariance) or None), for restarting in hindsight (retro_restart)
        self.streak: list[tuple[float, tuple | None]] = []
        self.refused: tuple | None = None  # this frame's refused estimate
        # earlier frames' steps that a restart in hindsight, or the track's end (ended_in_hindsight), replaced
        self.revision: tuple[FilterStep, ...] = ()
        self.info = Diagnostics()
        rng = np.random.default_rng(spec.obj_id)
        v = spec.vertices
        self.box_vertices = v if len(v) <= BOX_VERTICES else v[rng.choice(len(v), BOX_VERTICES, replace=False)]

    @property
    def has_pose(self) -> bool:
        return self.status in POSED

    def new_filter(self) -> PoseKalman | PartFilter:
        """A filter for a new track: a view of the instrument's state, or the part's own."""
        if self.shared is not None:
            return PartFilter(self.shared, self.spec.name, self.widen)
        return PoseKalman(self.cfg.kalman)

    def note_d2(self, d2: float | None, dof: int, weight: float, accepted: bool = True) -> None:
        """Record a measurement's squared Mahalanobis distance ``d2`` to the track (``dof`` its
        dimension; ``accepted`` False for one the gate kept out) in the info and in the running NIS."""
        if d2 is None or math.isnan(d2):
            return
        if accepted:
            self.info.d2 = d2
        else:
            self.info.rejected_d2 = d2
        # a gated-out estimate counts too (capped, NIS_CAP)
        self.nis = (1.0 - weight) * self.nis + weight * min(d2 / max(dof, 1), NIS_CAP)

    def forget_refusals(self) -> None:
        """Clear what a restart in hindsight reads: a new track owns none of the old one's refusals."""
        self.streak, self.refused, self.revision = [], None, ()

    def note_refusals(self, time_s: float) -> None:
        """At the end of the frame at ``time_s``: while the filter's refusals in a row last, the frame (and
        its refused estimate, if any) joins the streak, of which only the last ``RETRO_MAX_S`` is kept;
        else the streak is cleared."""
        if self.has_pose and isinstance(self.kf, PoseKalman) and self.kf.rejections_in_a_row > 0:
            self.streak = [f for f in self.streak if f[0] >= time_s - RETRO_MAX_S] + [(time_s, self.refused)]
        else:
            self.streak = []
        self.refused = None

    def ended_in_hindsight(self, out_of_view: Callable[[np.ndarray, np.ndarray], bool] | None = None
                           ) -> tuple[FilterStep, ...]:
        """The steps of this track's last frames as a track restarted from the estimates it refused there
        (revised, for the smoother), or none. For a track that ends while the estimator disagrees with it
        (a fast move out of the view, which a constant-velocity track lags behind and its gate then
        refuses): the last refused estimate and the earlier ones it continues (:func:`agreeing_start`, at
        least one) start a filter run, carried over the frames after the last of them as the filter would
        (coasting after the first). The causal run is not changed; the smoother writes these frames from
        that run. A run that stops while the estimates are refused keeps the track: only the track's loss
        says that it, not the estimates, was wrong.

        A part cut by the image's edge as it leaves is often estimated wrongly on its last frames: when
        the last refused estimate continues none before it, the latest one that earlier ones continue
        starts the run instead, but only where that run, carried to the frame of the loss, has the part
        out of the view (``out_of_view(R, t)``, the model-to-camera pose in mm: the run explains the loss);
        elsewhere such a run is more often estimates that agree while the part hides."""
        if not (self.cfg.retro_restart and self.has_pose and isinstance(self.kf, PoseKalman)):
            return ()
        refused = [k for k in range(len(self.streak) - 1, -1, -1) if self.streak[k][1] is not None]
        for last in refused:
            time_s, (R, t, cov) = self.streak[last]
            first = agreeing_start(self.streak[:last], R, t, cov, time_s, self.kf.config)
            if first is not None:
                break
        else:
            return ()
        kf, steps = refilter(self.kf.config, self.streak[first:last + 1], last_ungated=True)
        for k, (ts, _) in enumerate(self.streak[last + 1:]):
            kf.predict(ts, coast=k > 0)
            steps.append(kf.snapshot())
        if last != refused[0]:
            if out_of_view is None or self.kf.time is None:
                return ()
            if self.kf.time > kf.time:  # the frame of the loss (the streak holds the frames before it)
                kf.predict(self.kf.time, coast=True)
            if not out_of_view(*kf.pose):
                return ()
        return tuple(dataclasses.replace(s, revised=True) for s in steps)

    def drop(self, out_of_view: Callable[[np.ndarray, np.ndarray], bool] | None = None) -> None:
        """End the track (the part is lost); its last frames may be revised in hindsight
        (:meth:`ended_in_hindsight`, with ``out_of_view``, in ``revision`` for this frame's state). A track
        dropped again in the same frame (a reappearance that failed) keeps the revision its first drop made."""
        ended = self.ended_in_hindsight(out_of_view) if self.has_pose else self.revision
        if isinstance(self.kf, PartFilter):
            self.kf.deactivate()
        self.kf = self.new_filter()
        self.unseen = self.occluded = 0
        self.nis = 1.0
        self.forget_refusals()
        self.revision = ended
        self.status = Status.LOST
        self.points = TrackPoints(np.zeros((0, 2)), np.zeros((0, 3)))


class Tracker:
    """Tracks the parts ``specs`` through a video, one :meth:`step` per frame.

    ``estimator``: a :class:`PoseEstimator` whose model knows every spec's ``obj_id``. ``K``: the
    intrinsics (undistorted frames), ``image_size``: (W, H). ``instruments``: where the kinematic fit
    finds the instruments' descriptions.
    """

    def __init__(self, estimator: PoseEstimator, K: np.ndarray, image_size: tuple[int, int],
                 specs: Sequence[PartSpec], cfg: TrackConfig | None = None,
                 instruments: InstrumentRegistry = BUILTIN):
        self.estimator, self.cfg, self.instruments = estimator, cfg or TrackConfig(), instruments
        self.K = np.asarray(K, np.float64)
        self.size = (int(image_size[0]), int(image_size[1]))
        self._described: dict[str, Instrument | None] = {}  # instrument key -> its description, if any
        by_instrument = instrument_parts(estimator.model.parts)
        for s in specs:
            self._described[f"{s.instrument}.{s.instance}"] = described_instrument(
                s.instrument, by_instrument.get(s.instrument), registry=instruments)[0]
        self.shared: dict[str, InstrumentKalman] = {}  # instrument key -> its articulated state
        if self.cfg.articulated:
            for key, inst in self._described.items():
                names = {s.part: s.name for s in specs if f"{s.instrument}.{s.instance}" == key}
                if inst is not None and inst.chain.order[0] in names:
                    trocar = (Trocar(self.cfg.trocar_after, axis_std_mm=self.cfg.est_pos_std_mm,
                                     axis_std_deg=self.cfg.est_rot_std_deg, floor_mm=self.cfg.trocar_floor_mm)
                              if self.cfg.trocar else None)
                    self.shared[key] = InstrumentKalman(inst, names, self.cfg.kalman, self.cfg.joint_accel_std_rad_s2,
                                                        trocar=trocar)
        self.samples: dict[str, SurfaceSamples] = {}
        for s in specs:
            mesh = trimesh.Trimesh(s.vertices, s.faces, process=False)
            self.samples[s.name] = SurfaceSamples.of_mesh(mesh, FLOW_SURFACE_SAMPLES, seed=s.obj_id)
        self.prev_gray: np.ndarray | None = None
        self._est_cov = np.diag([self.cfg.est_pos_std_mm**2] * 3 + [np.radians(self.cfg.est_rot_std_deg)**2] * 3)
        self._kinematic = self.cfg.kinematic_config()
        if self._kinematic is not None:
            try:
                check_anchor(self._kinematic, estimator.model.parts)
            except ValueError as e:
                raise TrackConfigError(str(e)) from None
        self._widen = RESTART_WIDEN * self._est_cov
        self.tracks = [_Track(s, self.cfg, self.shared.get(f"{s.instrument}.{s.instance}"), self._widen)
                       for s in specs]
        self._floor = np.diag([self.cfg.flow_floor_mm**2] * 3 + [np.radians(self.cfg.flow_floor_deg)**2] * 3)
        self._region_floor = np.diag([self.cfg.region_floor_mm**2] * 3 + [np.radians(self.cfg.region_floor_deg)**2] * 3)
        self._region: RegionTracker | None = None
        self._mask_colors: set[str] = set()  # instruments (region groups) the network's masks have taught colours
        self._region_specs = list(specs)
        self._joints: dict[str, JointState] = {}  # instrument key -> the joints its last accepted fit found
        self._set_poses: dict[str, tuple[float, dict]] = {}  # instrument key -> (time, poses given by set_pose)

    def _region_tracker(self) -> RegionTracker:
        """The region measurement's renderer and colour models, made on first use (a GL context)."""
        if self._region is None:
            meshes, groups, attachments = {}, {}, {}
            for s in self._region_specs:
                meshes[s.name] = trimesh.Trimesh(s.vertices, s.faces, process=False)
                groups[s.name] = f"{s.instrument}.{s.instance}"
                inst = self._described[groups[s.name]]
                # the long shaft tube the model does not track is still part of the silhouette
                attachments[s.name] = [a.mesh for a in inst.attachments if a.part == s.part] if inst else []
            self._region = RegionTracker(self.K, self.size, meshes, groups, attachments,
                                         RegionConfig(max_points=self.cfg.region_points,
                                                      max_std_mm=self.cfg.region_max_std_mm,
                                                      max_std_deg=self.cfg.region_max_std_deg))
        return self._region

    def close(self) -> None:
        """Free the region measurement's renderer (GL objects), if one was made."""
        if self._region is not None:
            self._region.release()
            self._region = None
            self._mask_colors.clear()

    # ------------------------------------------------------------------ helpers
    def _pick_box(self, tr: _Track, boxes: Sequence[tuple[Box, float]], pbox: Box | None) -> Box | None:
        cands = [(b, s) for b, s in boxes if s >= self.cfg.min_box_score and b[2] >= 2.0 and b[3] >= 2.0]
        if not cands:
            return None
        if pbox is not None:
            best = max(cands, key=lambda bs: (box_iou(bs[0], pbox), bs[1]))
            if box_iou(best[0], pbox) > 0.0:
                return best[0]
        return max(cands, key=lambda bs: bs[1])[0]

    def _moved(self, res, prior: tuple[np.ndarray, np.ndarray]) -> bool:
        """Whether the kinematic fit moved the part away from its tracked pose ``prior`` by more than the
        estimator's noise (then a keyframe whose prior won is fused as a measurement, not taken as a
        confirmation)."""
        if not res.kinematic:
            return False
        dr, dt = pose_distance(res.R, res.t, *prior)
        return dr > self.cfg.est_rot_std_deg or dt > self.cfg.est_pos_std_mm

    def _posed(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Poses of every part with one (all instruments: a crossing tool hides what is behind it)."""
        return {o.spec.name: o.kf.pose for o in self.tracks if o.has_pose}

    def _refresh(self, tr: _Track, gray: np.ndarray) -> None:
        tr.points = visible_points(gray, self.K, self.samples, self._posed(), tr.spec.name,
                                   max_points=self.cfg.max_points)
        tr.n_points_fresh = len(tr.points)
        tr.lift_cov = tr.kf.pose_cov
        tr.since_refresh = 0

    def set_pose(self, track_id: int, R: np.ndarray, t: np.ndarray, time_s: float) -> None:
        """(Re-)initialise a part from a pose known from elsewhere (e.g. a human annotation) at
        ``time_s``, the time of the frame about to be stepped or of the last one; flow points are picked
        on the next :meth:`step`'s frame. The parts of an instrument with one state that are set at the
        same time start that state together (it holds every given pose, not a blend of them)."""
        tr = next((x for x in self.tracks if x.spec.track_id == track_id), None)
        if tr is None:
            raise KeyError(f"no part with track id {track_id}")
        R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
        if isinstance(tr.kf, PartFilter):
            tr.kf.deactivate()
            key = f"{tr.spec.instrument}.{tr.spec.instance}"
            when, poses = self._set_poses.get(key, (None, {}))
            poses = {**poses, tr.spec.name: (R, t)} if when == time_s else {tr.spec.name: (R, t)}
            self._set_poses[key] = (time_s, poses)
            tr.kf = tr.new_filter()
            tr.kf.shared.init(poses, time_s - 1e-6, self._est_cov)
            # the instrument's other tracked parts stay on it, now placed by the state that holds this pose
            tr.kf.shared.active |= {o.spec.name for o in self.tracks if o.has_pose and isinstance(o.kf, PartFilter)
                                    and o.kf.shared is tr.kf.shared}
        else:
            tr.kf = tr.new_filter()
            tr.kf.init(R, t, time_s - 1e-6, self._est_cov)
        tr.status, tr.nis = Status.KEYFRAME, 1.0
        tr.forget_refusals()
        tr.since_keyframe = tr.since_meas = 0
        tr.points = TrackPoints(np.zeros((0, 2)), np.zeros((0, 3)))
        tr.n_points_fresh = 0
        tr.seeded = True
        tr.unseen = tr.occluded = tr.since_refresh = 0

    # ------------------------------------------------------------------ the frame step
    def step(self, frame_rgb: np.ndarray, time_s: float,
             boxes: Mapping[int, Sequence[tuple[Box, float]]] | None = None) -> list[PartState]:
        """Advance to the frame ``frame_rgb`` (H, W, 3 uint8, undistorted) at ``time_s`` seconds;
        ``boxes`` maps track id -> [(box, score), ...] detected in this frame (missing = none)."""
        gray = cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2GRAY)
        self._propagate(gray, time_s)
        if self.cfg.region:
            self._measure_regions(frame_rgb)
        requests, out_boxes = self._schedule(boxes or {})
        if requests:
            self._estimate(frame_rgb, time_s, requests)
        self._refresh_points(gray)
        self.prev_gray = gray
        states = []
        snaps: dict[str, FilterStep] = {}  # instrument key -> its state this frame
        for tr in self.tracks:
            if tr.has_pose:
                tr.info.nis = tr.nis
                R, t = tr.kf.pose
                shared = None
                if isinstance(tr.kf, PartFilter):
                    key = f"{tr.spec.instrument}.{tr.spec.instance}"
                    if key not in snaps:
                        snaps[key] = tr.kf.shared.snapshot()
                    snap = snaps[key]
                    shared, step = (key, tr.kf.shared, snap), tr.kf.shared.part_step(snap, tr.spec.name)
                else:
                    step = tr.kf.snapshot()
                    if tr.revision:
                        step, tr.revision = dataclasses.replace(step, revises=tr.revision), ()
                state = PartState(tr.spec, tr.status, 0.0, R, t, out_boxes.get(tr.spec.track_id),
                                  dataclasses.replace(tr.info), step, shared)
                states.append(state.settled(step, self.cfg))  # the causal confidence
            else:
                states.append(PartState(tr.spec, tr.status, 0.0, None, None, out_boxes.get(tr.spec.track_id),
                                        dataclasses.replace(tr.info), revises=tr.revision))
                tr.revision = ()
            tr.note_refusals(time_s)
        return states

    # ------------------------------------------------------------------ the phases of a step
    def _propagate(self, gray: np.ndarray, time_s: float) -> None:
        """Predict every tracked part to ``time_s``; between keyframes, measure it by flow (LK + PnP)."""
        cfg, K = self.cfg, self.K
        # LK runs once for the points of all parts (one image pyramid per frame), its time shared out by
        # point count. A part the estimator measures this frame anyway (its cadence is due) gets no flow
        # measurement: flow's error repeats the pose its points were lifted at, and fused next to the
        # estimator it pulls the track back towards its own drift.
        for tr in self.tracks:
            if tr.has_pose and (not cfg.flow or tr.since_keyframe + 1 >= cfg.keyframe_every):
                tr.points = TrackPoints(np.zeros((0, 2)), np.zeros((0, 3)))
        moving = [tr for tr in self.tracks if tr.has_pose and not tr.seeded and len(tr.points)]
        lk_ms = {}
        if self.prev_gray is not None and moving:
            t_lk = time.perf_counter()
            merged = TrackPoints(np.concatenate([tr.points.uv for tr in moving]),
                                 np.concatenate([tr.points.xyz for tr in moving]))
            owner = np.concatenate([np.full(len(tr.points), k) for k, tr in enumerate(moving)])
            merged.xyz = np.c_[merged.xyz, owner]  # carry the owner through the filtering
            followed = track_points(self.prev_gray, gray, merged)
            total = 1e3 * (time.perf_counter() - t_lk)
            for k, tr in enumerate(moving):
                sel = followed.xyz[:, 3] == k
                tr.points = TrackPoints(followed.uv[sel], followed.xyz[sel, :3])
                lk_ms[id(tr)] = total * len(tr.points) / max(len(followed), 1)
        for tr in self.tracks:
            tr.info = Diagnostics()
            if not tr.has_pose:
                continue
            t_flow = time.perf_counter()
            tr.kf.predict(time_s, coast=tr.since_meas > 0)
            if tr.seeded:  # set_pose just before this frame: the pose stands, flow starts here
                tr.seeded = False
                tr.kf.prior = None  # a new segment: the smoother does not link it to the old track
                tr.info.source = "set_pose"
                continue
            tr.since_keyframe += 1
            tr.since_refresh += 1
            meas = None
            if self.prev_gray is not None and len(tr.points):
                R0, t0 = tr.kf.pose
                meas = pnp_measurement(tr.points, K, R0, t0, cfg.inlier_px, cfg.min_points)
            tr.info.points = len(tr.points)
            accepted = False
            if meas is not None:
                tr.info.inliers, tr.info.inlier_ratio = int(meas.inliers.sum()), float(meas.inlier_ratio)
                tr.info.rms_px = float(meas.rms_px)
                tr.points = tr.points.subset(meas.inliers)
                if meas.inlier_ratio >= cfg.min_inlier_ratio and meas.rms_px <= cfg.max_rms_px:
                    # the points' 3D positions came from the pose at lifting time, errors included: a
                    # measurement claiming only its PnP precision would lock the filter onto that error and
                    # keyframes could hardly pull it back
                    accepted = tr.kf.update(meas.R, meas.t, meas.cov + self._floor + tr.lift_cov, counts=False)
                    tr.note_d2(tr.kf.last_d2, 6, self.cfg.confidence_nis_weight, accepted)
            if accepted:
                tr.status, tr.since_meas = Status.TRACKING, 0
            else:
                tr.status, tr.since_meas = Status.PREDICTED, tr.since_meas + 1
            tr.info.flow_ms = 1e3 * (time.perf_counter() - t_flow) + lk_ms.get(id(tr), 0.0)

    def _measure_regions(self, frame_rgb: np.ndarray) -> None:
        """Between keyframes, measure every predicted part against the frame's colours along its
        silhouette (:mod:`.region`); all posed parts are rendered together, so tools hide each other."""
        cfg = self.cfg
        due = [tr for tr in self.tracks if tr.has_pose and tr.status == Status.PREDICTED
               and tr.info.source is None and tr.since_keyframe < cfg.keyframe_every]
        if not due:
            return
        t0 = time.perf_counter()
        rt = self._region_tracker()
        posed = {tr.spec.name: tr.kf.pose for tr in self.tracks if tr.has_pose}
        contours, masks = rt.contours(posed)
        for group, mask in masks.items():
            if cfg.region_colors == "network" and rt.colors[group].ready:
                continue  # learnt on keyframes (_learn_colors); the predicted silhouette only starts them
            # colours from the predicted silhouette, its edge left out (learn's margins): learning instead
            # from the line pixels next to each accepted outline (as ICG does) mixed the far side of thin
            # jaws into the foreground and held the seeded wrist of tests/test_track.py 8 deg off, not 2.4
            rt.learn(frame_rgb, group, mask, rate=cfg.region_learn_rate)
        share = 1e3 * (time.perf_counter() - t0) / len(due)
        groups: dict[str, list[_Track]] = {}
        for tr in due:
            groups.setdefault(f"{tr.spec.instrument}.{tr.spec.instance}", []).append(tr)
        for key, trs in groups.items():
            t1 = time.perf_counter()
            if key in self.shared and isinstance(trs[0].kf, PartFilter):
                self._measure_shared(frame_rgb, contours, key, trs)
                for tr in trs:
                    tr.info.region_ms = share + 1e3 * (time.perf_counter() - t1) / len(trs)
                continue
            results = {}
            models = self._region_models(key, trs)
            for model, prior in models:
                results.update(rt.measure(frame_rgb, contours, model, prior))
            accepted = set()
            for tr in trs:
                res = results.get(tr.spec.name)
                if res is None:
                    continue
                tr.info.region_lines, tr.info.agreement = int(res.lines), float(res.agreement)
                basis, cov = res.observed(cfg.region_max_std_mm, cfg.region_max_std_deg)
                if res.agreement < cfg.region_min_agreement or not len(basis):
                    continue
                if tr.kf.update(res.R, res.t, cov + basis @ self._region_floor @ basis.T, basis=basis, counts=False):
                    tr.status, tr.since_meas = Status.TRACKING, 0
                    tr.note_d2(tr.kf.last_d2, len(basis), cfg.confidence_nis_weight)
                    accepted.add(tr.spec.name)
                else:  # a silhouette the filter refuses says the track may be off: the confidence hears it
                    tr.note_d2(tr.kf.last_d2, len(basis), cfg.confidence_nis_weight, accepted=False)
            for model, _ in models:  # the joints a fit found seed the next frame's, once its root was taken
                if isinstance(model, ArticulatedModel) and model.solution is not None and model.parts[0] in accepted:
                    self._joints[key] = model.joint_state(model.solution)
            for tr in trs:
                tr.info.region_ms = share + 1e3 * (time.perf_counter() - t1) / len(trs)

    def _learn_colors(self, frame_rgb: np.ndarray, estimated: Sequence[tuple[_Track, PartPose]]) -> None:
        """Learn each instrument's colour models from the network's masks of its parts on a keyframe
        (``region_colors`` "network"; ``estimated``: (track, :class:`~surftrack.pose.PartPose` with its
        mask) per crop of the keyframe): a segmentation independent of the track's pose, so
        the silhouette's depth does not repeat the track's (colours learnt at the predicted silhouette put
        its outline where the track's depth error puts it). The foreground is the union of the parts'
        masks, the background a band around it where the crops saw the frame; the pixels another
        instrument's masks claim are left out of both. The masks are the model's (amodal: an occluder's
        pixels inside a part count as foreground), and a part of the instrument not estimated on this
        frame lies in the background band where it touches the others."""
        rt = self._region_tracker()
        size = (frame_rgb.shape[1], frame_rgb.shape[0])
        prob: dict[str, np.ndarray] = {}
        seen: dict[str, np.ndarray] = {}
        for tr, res in estimated:
            if res.mask is None:
                continue
            p, covered = res.image_mask(size)
            g = rt.groups[tr.spec.name]
            prob[g] = np.maximum(prob[g], p) if g in prob else p
            seen[g] = seen[g] | covered if g in seen else covered
        fg = {g: p > 0.5 for g, p in prob.items()}
        for g, mask in fg.items():
            others = functools.reduce(np.logical_or, [m for h, m in fg.items() if h != g], np.zeros_like(mask))
            # the first masks replace what the predicted silhouette started
            rate = self.cfg.region_mask_rate if g in self._mask_colors else 1.0
            if rt.learn(frame_rgb, g, mask & ~others, rate=rate, within=seen[g] & ~others):
                self._mask_colors.add(g)

    def _measure_shared(self, frame_rgb: np.ndarray, contours: Mapping, key: str, trs: list[_Track]) -> None:
        """The region measurement of an instrument with one articulated state: one fit of the whole
        instrument from the state (its covariance the fit's prior), fused as one measurement of the state
        in the directions the lines pin; parts whose own outline agrees count as measured."""
        cfg, shared = self.cfg, self.shared[key]
        model = shared.model()
        E = shared.expand(np.eye(model.size), model)  # model parameters -> state error coordinates
        results = self._region_tracker().measure(frame_rgb, contours, model, E @ shared.kf.P @ E.T)
        if not results or model.solution_cov is None:
            return
        lines = sum(r.lines for r in results.values())
        agreement = sum(r.agreement * r.lines for r in results.values()) / max(lines, 1)
        for tr in trs:
            res = results.get(tr.spec.name)
            if res is not None:
                tr.info.region_lines, tr.info.agreement = int(res.lines), float(res.agreement)
        if agreement < cfg.region_min_agreement:
            return
        basis, cov = observed_directions(model.solution_cov, cfg.region_max_std_mm, cfg.region_max_std_deg)
        floor = np.diag(np.r_[np.full(3, cfg.region_floor_mm ** 2),
                              np.full(model.size - 3, np.radians(cfg.region_floor_deg) ** 2)])
        ok, d2 = shared.update_model(model, model.solution, basis, cov + basis @ floor @ basis.T)
        if not ok:
            return
        for tr in trs:
            res = results.get(tr.spec.name)
            if res is not None and res.agreement >= cfg.region_min_agreement:
                tr.status, tr.since_meas = Status.TRACKING, 0
                tr.note_d2(d2, len(basis), cfg.confidence_nis_weight)

    def _region_models(self, key: str, trs: list[_Track]) -> list[tuple[PoseModel, np.ndarray]]:
        """How the region measurement moves one instrument's due parts, with each model's prior
        covariance: through the instrument's kinematics from its root part (the shaft) when the instrument
        is described and its root is among them, else each part as a free rigid body."""
        inst = self._described.get(key)
        by_part = {tr.spec.part: tr for tr in trs}
        pose_cov = lambda tr: PoseKalman.H @ tr.kf.covariance @ PoseKalman.H.T  # noqa: E731
        if inst is not None and inst.chain.order[0] in by_part:
            root = by_part[inst.chain.order[0]]
            posed = {p: se3(*tr.kf.pose) for p, tr in by_part.items()}
            q0 = joints_from_poses(inst, posed, self._joints.get(key, JointState()))
            model = ArticulatedModel(inst, {p: tr.spec.name for p, tr in by_part.items()}, *root.kf.pose, q0)
            prior = np.zeros((model.size, model.size))
            prior[:6, :6] = pose_cov(root)
            prior[6:, 6:] = np.eye(model.size - 6) * np.radians(self.cfg.region_joint_std_deg) ** 2
            return [(model, prior)]
        return [(PoseModel(tr.spec.name, *tr.kf.pose), pose_cov(tr)) for tr in trs]

    def _match_twin_boxes(self, boxes: Mapping[int, Sequence[tuple[Box, float]]]
                          ) -> Mapping[int, Sequence[tuple[Box, float]]]:
        """``boxes`` with the detections of a twin grasper's two jaws exchanged where each fits the other
        jaw's tracked projection better (summed IoU by more than ``twin_match_margin``): detections name
        the jaws as the image shows them, the state the model gives beyond a quarter turn of roll is the
        roll twin, whose jaw_left is the other jaw. Without the exchange each jaw's keyframe reads the other
        jaw's crop and its box disagrees with the track on every frame."""
        cfg = self.cfg
        if not cfg.twin_match:
            return boxes
        by_key: dict[str, dict[str, _Track]] = {}
        for tr in self.tracks:
            by_key.setdefault(f"{tr.spec.instrument}.{tr.spec.instance}", {})[tr.spec.part] = tr

        def fit(tr: _Track, cands: Sequence[tuple[Box, float]], pbox: Box) -> float:
            det = self._pick_box(tr, cands, pbox)
            return box_iou(det, pbox) if det is not None else 0.0

        out = dict(boxes)
        for key, parts in by_key.items():
            inst = self._described.get(key)
            twin = inst.roll_twin if inst is not None else None
            if twin is None:
                continue
            for p, q in twin.partner.items():
                if not (p < q and p in parts and q in parts and parts[p].has_pose and parts[q].has_pose):
                    continue
                a, b = parts[p], parts[q]
                pa = projected_box(self.K, *a.kf.pose, a.box_vertices, self.size)[0]
                pb = projected_box(self.K, *b.kf.pose, b.box_vertices, self.size)[0]
                if pa is None or pb is None:
                    continue
                own_a, own_b = boxes.get(a.spec.track_id, ()), boxes.get(b.spec.track_id, ())
                if fit(a, own_b, pa) + fit(b, own_a, pb) > fit(a, own_a, pa) + fit(b, own_b, pb) + cfg.twin_match_margin:
                    out[a.spec.track_id], out[b.spec.track_id] = own_b, own_a
        return out

    def _by_instrument(self, requests: list[tuple[_Track, Box, tuple | None, str]], keep) -> dict[str, dict[str, int]]:
        """Request indices per instrument key and part, of the requests ``keep(k)`` accepts."""
        out: dict[str, dict[str, int]] = {}
        for k, (tr, _, _, _) in enumerate(requests):
            if keep(k):
                out.setdefault(f"{tr.spec.instrument}.{tr.spec.instance}", {})[tr.spec.part] = k
        return out

    def _model_labels(self, requests: list[tuple[_Track, Box, tuple | None, str]]
                      ) -> tuple[list[Box], list[tuple | None]]:
        """The boxes and priors to hand the estimator for ``requests``, in the model's labels
        (``twin_align``): a model trained on one roll twin's labels (:mod:`surftrack.data.twin_labels`)
        names a grasper whose shaft x axis points towards the camera as its twin, so for such a tracked
        instrument each part is asked on its partner's box (the jaws exchange boxes) with its partner's
        prior turned half a turn; :meth:`_nearer_twins` turns the answers back to the tracks."""
        boxes, priors = [b for _, b, _, _ in requests], [p for _, _, p, _ in requests]
        if not self.cfg.twin_align:
            return boxes, priors
        for key, parts in self._by_instrument(requests, lambda k: True).items():
            inst = self._described.get(key)
            twin = inst.roll_twin if inst is not None else None
            root = inst.chain.order[0] if inst is not None else None
            if twin is None or root not in parts or not requests[parts[root]][0].has_pose:
                continue
            R, t = requests[parts[root]][0].kf.pose
            if float(R[:, 0] @ t) >= 0.0:  # the model's own labels
                continue
            for p, k in parts.items():
                q = parts.get(twin.partner.get(p))
                if q is None:
                    continue
                boxes[k] = requests[q][1]
                prior = requests[q][2]
                priors[k] = (prior[0] @ HALF_TURN, prior[1]) if prior is not None else None
        return boxes, priors

    def _nearer_twins(self, requests: list[tuple[_Track, Box, tuple | None, str]], results: list) -> list:
        """``results`` (:class:`~surftrack.pose.PartPose` per request) with the tracked parts of a grasper
        with a roll twin turned to that twin where it lies nearer their tracks (``twin_align``). The twins
        give the same image, so the model answers with one of them, the one its training labels put on
        that side of a quarter turn of roll; a tool rolled through the switch would jump half a turn, be
        gated out and restart. The tracks' motion decides instead, for all of the instrument's solved parts
        whose partners are solved too (the jaws exchange poses; a re-appearing part turned with the rest),
        where the twin lies within ``twin_align_max_deg`` of the root's track (a track already far off is
        left to the gate and its restart, not turned further)."""
        cfg = self.cfg
        if not cfg.twin_align:
            return results
        results = list(results)
        for key, parts in self._by_instrument(requests, lambda k: results[k].ok).items():
            inst = self._described.get(key)
            twin = inst.roll_twin if inst is not None else None
            if twin is None:
                continue
            parts = {p: k for p, k in parts.items() if twin.partner.get(p) in parts}
            tracked = {p: k for p, k in parts.items() if requests[k][0].has_pose}
            if not tracked:
                continue
            est = {p: (results[k].R, results[k].t) for p, k in parts.items()}
            turned = twin.poses(est)

            def cost(poses: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> float:
                return sum(dr / cfg.est_rot_std_deg + dt / cfg.est_pos_std_mm for dr, dt in
                           (pose_distance(*poses[p], *requests[k][0].kf.pose) for p, k in tracked.items()))

            root = inst.chain.order[0]
            near = [pose_distance(*turned[p], *requests[k][0].kf.pose)[0] for p, k in tracked.items()
                    if p == root or root not in tracked]
            if cost(turned) < cost(est) and float(np.median(near)) <= cfg.twin_align_max_deg:
                was = list(results)
                for p, k in parts.items():
                    src = was[parts[twin.partner[p]]]  # the partner's evidence placed this part's twin pose
                    results[k] = dataclasses.replace(was[k], R=turned[p][0], t=turned[p][1], score=src.score,
                                                     n_inliers=src.n_inliers)
        return results

    def _schedule(self, boxes: Mapping[int, Sequence[tuple[Box, float]]]
                  ) -> tuple[list[tuple[_Track, Box, tuple | None, str]], dict[int, Box | None]]:
        """Drop parts that left the image, pick each part's box, and list who needs the estimator and
        why: (track, box, prior pose or None, reason). Also the box reported per track id."""
        cfg, K = self.cfg, self.K
        boxes = self._match_twin_boxes(boxes)
        requests: list[tuple[_Track, Box, tuple | None, str]] = []
        out_boxes: dict[int, Box | None] = {}
        for tr in self.tracks:
            sid = tr.spec.track_id
            pbox, det = None, None
            if tr.has_pose:
                R, t = tr.kf.pose
                pbox, inside = projected_box(K, R, t, tr.box_vertices, self.size)
                det = self._pick_box(tr, boxes.get(sid, ()), pbox)
                # a long part (the shaft) keeps a small share of its box in view while it still fills
                # the image's edge: a detection that agrees with the part where the track puts it says
                # it is still there (dropping it would restart its filter on every such frame)
                seen = det is not None and pbox is not None and box_iou(det, pbox) >= cfg.min_iou
                if pbox is None or (inside < cfg.min_visible and not seen):
                    tr.drop(self._out_of_view(tr))
                    tr.info.why_lost = "left the image"
                    pbox = None
            if pbox is None:
                det = self._pick_box(tr, boxes.get(sid, ()), None)
            out_boxes[sid] = det if det is not None else pbox
            if tr.has_pose:
                why = None
                if det is not None and box_iou(det, pbox) < cfg.min_iou:
                    why = "box disagreement"
                elif (cfg.flow or cfg.region) and tr.since_meas >= cfg.max_predicted:
                    why = "no measurement"
                elif tr.since_keyframe >= cfg.keyframe_every:
                    why = "cadence"
                if why is not None:
                    requests.append((tr, det if det is not None else pbox, tr.kf.pose, why))
            elif det is not None:
                requests.append((tr, det, None, "init" if tr.status == Status.INIT else "reappearance"))
        if self._kinematic is not None and requests:
            # the instrument fit places each part from the others estimated in the same call (the wrist
            # anchors the shaft's roll): an instrument's tracked parts get their keyframes together
            due = {(tr.spec.instrument, tr.spec.instance) for tr, _, _, _ in requests}
            asked = {id(tr) for tr, _, _, _ in requests}
            for tr in self.tracks:
                box = out_boxes.get(tr.spec.track_id)
                if (tr.has_pose and id(tr) not in asked and box is not None
                        and (tr.spec.instrument, tr.spec.instance) in due):
                    requests.append((tr, box, tr.kf.pose, "instrument keyframe"))
        return requests, out_boxes

    def _estimate(self, frame_rgb: np.ndarray, time_s: float,
                  requests: list[tuple[_Track, Box, tuple | None, str]]) -> None:
        """One batched estimator call for ``requests``, made instrument-consistent, and its results
        fused, restarted, held or dropped."""
        cfg, K = self.cfg, self.K
        t_est = time.perf_counter()
        groups = [tr.spec.instance for tr, _, _, _ in requests]
        boxes, priors = self._model_labels(requests)
        network_colors = cfg.region and cfg.region_colors == "network"
        results = self.estimator.estimate(frame_rgb, [(tr.spec.obj_id, b) for (tr, _, _, _), b in zip(requests, boxes)],
                                          K, priors=priors, groups=groups if cfg.twin_boxes else None,
                                          masks=network_colors)
        if self._kinematic is not None:
            results = apply_kinematics(results, groups, self.estimator.model.parts, self._kinematic,
                                       self.instruments)
        results = self._nearer_twins(requests, results)
        est_ms = 1e3 * (time.perf_counter() - t_est) / len(requests)
        # a pose from the instrument fit (made only when its anchor was seen) is a measurement even where the
        # part's own estimate saw nothing: the wrist and jaws place a shaft cut by the image's edge or hidden
        # behind the other tool (a tracked part's filter still gates it)
        good_results = [res.ok and (res.kinematic or (res.n_inliers >= cfg.init_min_inliers
                                                      and res.score >= cfg.init_min_score))
                        for res in results]
        if network_colors:
            # every crop's mask, whatever its pose scored: the score judges the pose, not the segmentation
            # (on the test clip's small parts, crops with 100-300 inliers score just below 0); a crop that
            # shows no part has an empty mask
            self._learn_colors(frame_rgb, [(tr, res) for (tr, _, _, _), res in zip(requests, results)])
        # with the kinematic fit, the poses of one instrument's parts on a keyframe come from one joint fit:
        # one measurement of its state, not one per part, so each part's share of it is that much weaker
        share = Counter(id(tr.kf.shared) for (tr, _, _, _), res, good in zip(requests, results, good_results)
                        if isinstance(tr.kf, PartFilter) and good and res.kinematic)

        def est_cov_of(tr: _Track, res) -> np.ndarray:
            k = share[id(tr.kf.shared)] if isinstance(tr.kf, PartFilter) else 0
            cov = estimator_cov(res.t, cfg)
            return cov * k if k > 1 else cov

        # an instrument none of whose parts is tracked starts its state from all of them at once (the
        # joints from their relative rotations), not from the first one's pose alone
        starts: dict[int, tuple[InstrumentKalman, dict, np.ndarray]] = {}
        for (tr, _, _, _), res, good in zip(requests, results, good_results):
            if isinstance(tr.kf, PartFilter) and not tr.kf.shared.active and good:
                starts.setdefault(id(tr.kf.shared), (tr.kf.shared, {}, est_cov_of(tr, res)))[1][tr.spec.name] = (res.R, res.t)
        for shared, poses, cov in starts.values():
            shared.init(poses, time_s, cov)
        # the parts measured within the last few frames (their poses as this call has fused them so far):
        # where another part of their instrument that starts now may lie
        recent = [o for o in self.tracks if o.has_pose and o.since_meas <= cfg.max_predicted]
        unseen: list[tuple[_Track, str]] = []
        for (tr, box, prior, why), res, good in zip(requests, results, good_results):
            est_cov = est_cov_of(tr, res)
            tr.info.estimator, tr.info.estimator_ms = why, est_ms
            tr.info.score, tr.info.est_inliers = float(res.score), int(res.n_inliers)
            tr.info.prior_won, tr.info.kinematic = bool(res.prior_won), res.kinematic
            if good:
                tr.unseen = tr.occluded = 0
            if tr.has_pose and good:
                if res.prior_won and not self._moved(res, prior):
                    # the tracked pose explains the image best: a confirmation, not a new measurement
                    # (fusing the filter's own pose again would shrink its covariance for nothing), and
                    # the end of a run of disagreements
                    tr.status, tr.since_meas = Status.KEYFRAME, 0
                    tr.kf.rejections_in_a_row = 0
                elif tr.kf.update(res.R, res.t, est_cov):
                    tr.status, tr.since_meas = Status.KEYFRAME, 0
                    tr.note_d2(tr.kf.last_d2, 6, cfg.confidence_nis_weight)
                    if isinstance(tr.kf, PartFilter) and tr.kf.is_root:
                        tr.kf.shared.note_root_pose(res.R, res.t)  # an independent shaft axis for the trocar
                elif tr.kf.lost:
                    # the estimator has disagreed with the track on max_rejections frames in a row:
                    # the track is what is wrong (and so were its disagreements: the NIS starts afresh)
                    if not (cfg.retro_restart and self._restart_in_hindsight(tr, res.R, res.t, est_cov, time_s)):
                        tr.kf.restart(res.R, res.t, est_cov, self._widen)
                    tr.status, tr.since_meas, tr.nis = Status.KEYFRAME, 0, 1.0
                    tr.info.restarted = True
                else:
                    # one disagreement is as often the estimator's outlier (a flipped jaw, a shaft's
                    # roll) as a fast move: the filter carries the pose and the next frames decide
                    tr.note_d2(tr.kf.last_d2, 6, cfg.confidence_nis_weight, accepted=False)
                    tr.refused = (res.R, res.t, est_cov)
                tr.since_keyframe = 0
            elif good and self._beyond_reach(tr, res.t, recent):
                tr.info.why_lost = "estimate beyond its instrument's reach"
            elif good:
                tr.kf.init(res.R, res.t, time_s, est_cov)
                tr.status = Status.KEYFRAME
                tr.since_keyframe, tr.since_meas = 0, 0
            elif tr.has_pose and res.ok and res.score > 0.0 and (
                    why in SCHEDULED or tr.since_meas < INCONCLUSIVE_PATIENCE * cfg.max_predicted):
                # inconclusive (too few inliers, or a false box): keep the track on the filter
                tr.since_keyframe = 0
                tr.unseen = 0  # the network saw something: a later "sees nothing" gets its retry
            elif tr.has_pose and why in SCHEDULED and tr.unseen == 0:
                # flow still supports the track but the network sees nothing (an occluder, a poor
                # crop): ask again on the next frame before giving the part up
                tr.unseen += 1
                tr.since_keyframe = cfg.keyframe_every
            else:
                # the network sees nothing of the part where it should be (score <= 0: no pixel agrees
                # with any pose, not even the tracked one), or recovery failed
                unseen.append((tr, "not seen by the estimator" if res.score <= 0.0 else "estimator failed"))
        for tr, why_lost in unseen:
            inst = (tr.spec.instrument, tr.spec.instance)
            measured = any(o is not tr and (o.spec.instrument, o.spec.instance) == inst
                           and o.status in (Status.KEYFRAME, Status.TRACKING) for o in self.tracks)
            if tr.has_pose and measured and tr.occluded < cfg.max_occluded:
                # the rest of its instrument is seen: most likely hidden behind the other tool. The filter
                # carries it (its covariance growing) and the smoother bridges the gap when it is back
                tr.occluded += 1
                tr.status = Status.PREDICTED
                tr.info.occluded = tr.occluded
            else:
                tr.drop(self._out_of_view(tr))
                tr.info.why_lost = why_lost

    def _out_of_view(self, tr: _Track) -> Callable[[np.ndarray, np.ndarray], bool]:
        """Whether ``tr``'s part at a pose (R, t mm) is out of the view: in front of the camera with less
        than ``min_visible`` of its projected box inside the image, as a track is dropped for leaving it (a
        pose behind the camera explains no loss)."""
        def out(R: np.ndarray, t: np.ndarray) -> bool:
            return bool(t[2] > 0.0 and projected_box(self.K, R, t, tr.box_vertices, self.size)[1] < self.cfg.min_visible)

        return out

    def _beyond_reach(self, tr: _Track, t: np.ndarray, measured: Sequence[_Track]) -> bool:
        """Whether a part without a track, starting at ``t`` (mm), lies farther from every one of the
        ``measured`` parts of its instrument than the chain lets it (:meth:`KinematicChain.origin_reach`
        plus :data:`REACH_TOLERANCE_MM`); False where none of them is measured or the instrument has no
        description."""
        key = f"{tr.spec.instrument}.{tr.spec.instance}"
        inst = self._described.get(key)
        if inst is None or tr.spec.part not in inst.chain.joints:
            return False
        reach = [(o, inst.chain.origin_reach(tr.spec.part, o.spec.part)) for o in measured
                 if f"{o.spec.instrument}.{o.spec.instance}" == key
                 and o.spec.part in inst.chain.joints]
        return bool(reach) and all(np.linalg.norm(t - o.kf.pose[1]) > r + REACH_TOLERANCE_MM for o, r in reach)

    @staticmethod
    def _restart_in_hindsight(tr: _Track, R: np.ndarray, t: np.ndarray, cov: np.ndarray, time_s: float) -> bool:
        """Restart ``tr``'s filter from the estimates it refused in a row before this one (``R``, ``t``,
        ``cov``), as if they had started a new track: the frames since the first of them get the steps of
        that run (``tr.revision``, for the smoother), the filter goes on from it. Offline, the frames the
        track was wrong on before the estimator had disagreed often enough are then right too, and the
        jump moves to the first of them. Only the refused estimates this one continues count
        (:func:`agreeing_start`). Region and flow measurements of those frames are left out (they measured
        the old track's pose). False where there is nothing to restart from (no such estimate, or an
        instrument's articulated state)."""
        if not isinstance(tr.kf, PoseKalman):
            return False
        first = agreeing_start(tr.streak, R, t, cov, time_s, tr.kf.config)
        if first is None:
            return False
        kf, steps = refilter(tr.kf.config, tr.streak[first:] + [(time_s, (R, t, cov))], last_ungated=True)
        tr.kf, tr.revision = kf, tuple(dataclasses.replace(s, revised=True) for s in steps[:-1])
        return True

    def _refresh_points(self, gray: np.ndarray) -> None:
        """Pick fresh flow points where needed (after all poses of the frame are settled)."""
        cfg = self.cfg
        for tr in self.tracks:
            if tr.status not in (Status.KEYFRAME, Status.TRACKING):
                continue  # never pick points at an unconfirmed (predicted) pose: they may lie on the background
            if not cfg.flow or tr.since_keyframe + 1 >= cfg.keyframe_every:
                continue  # the estimator measures it on the next frame, which takes no flow measurement
            stale = (tr.status == Status.KEYFRAME or tr.since_refresh >= cfg.refresh_every
                     or len(tr.points) < cfg.refresh_below * max(tr.n_points_fresh, 1))
            if stale:
                t_ref = time.perf_counter()
                self._refresh(tr, gray)
                tr.info.refresh_ms = 1e3 * (time.perf_counter() - t_ref)

"""Tracking configuration (``configs/track/*.yaml``): when the estimator runs, how flow is checked, and the
Kalman filter's noise. Defaults are the values of ``configs/track/default.yaml``."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from surftrack.configio import build_dataclass, read_config_yaml
from surftrack.pose.kinematic import KinematicConfig
from surftrack.pose.preset import PRESETS, Preset
from surftrack.track.kalman import KalmanConfig
from surftrack.track.smoother import SmootherPrior

# where the silhouette measurement's colour models are learnt from (TrackConfig.region_colors)
REGION_COLORS = ("network", "track")


class TrackConfigError(ValueError):
    """A malformed tracking configuration; the message names the file and the key."""


@dataclass(frozen=True)
class TrackConfig:
    """``preset``: the estimator preset for keyframes; ``views``: crop views per box there (1-9,
    :mod:`surftrack.pose.views`; 0 keeps the preset's); ``solver_seed``: the seed of its RANSAC draws
    (a track's keyframes choose among near-tied hypotheses, so a run's figures move with it: compare
    configurations over seeds, as for still images). ``keyframe_every``: frames between estimator runs
    on a tracked part (the tracked pose is offered as a prior, so a keyframe replaces it only when the
    estimator finds a pose that explains the image better); ``keyframe_max_s``: the same bound in seconds
    of video, whichever is tighter (:meth:`for_fps`; 0 = frames only): the parts move between keyframes
    by time, not frames (the demo at 15 fps scored 79.4 / 35.7 / 35.2 / 32.4 % with a keyframe every 10
    frames, 86.8 / 48.6 / 49.3 / 43.7 % every 5, that is every 0.33 s as at 30 fps). ``min_box_score``: detections below are
    ignored. ``min_iou``: a detection box overlapping the part's projected box less than this triggers a
    re-initialisation (the track has drifted or jumped to another tool). ``max_predicted``: frames in a
    row without an accepted silhouette or flow measurement before the estimator is asked again. ``min_visible``: a
    part whose projected box keeps less than this fraction inside the image is lost, unless a detection
    agrees with it (IoU >= ``min_iou``: a long shaft keeps a small share of its box in view).
    ``max_occluded``: frames a tracked part the estimator does not see keeps its predicted pose while
    another part of its instrument is measured (hidden behind the other tool; the smoother bridges the
    gap when it is back).

    ``flow``: measure parts between keyframes by model-based optical flow (off: the filter carries them and
    the smoother interpolates between keyframes; LK follows highlights and edges on textureless metal:
    with a keyframe every 6 frames, flow on scored 28 / 14 / 9 / 11 % ADD-10 against 42 / 40 / 27 / 22 %
    off on the tuning clip, docs/decisions.md). Up to ``max_points`` points per part; refreshed from the
    current pose on keyframes, every ``refresh_every`` frames and when fewer than ``refresh_below`` of them survive. A flow measurement
    needs ``min_points`` PnP inliers within ``inlier_px``, an inlier ratio >= ``min_inlier_ratio`` and an
    RMS error <= ``max_rms_px``. Its covariance (from the PnP Jacobian) gets ``flow_floor_mm`` /
    ``flow_floor_deg`` added (model error) and the filter's pose covariance when the points were lifted to
    3D: they were lifted from that pose and repeat its error. (Fusing that shared error as if it were
    independent still shrinks the covariance each frame; this bounds the overconfidence, it does not
    remove it.) Estimator poses are fused with ``est_pos_std_mm`` along the line of sight,
    ``est_lateral_std_mm`` across it and ``est_rot_std_deg``; a part's own estimate counts (as a
    measurement or an initialisation) with ``init_min_inliers`` and a score >= ``init_min_score``, a pose
    from the instrument fit (``kinematic``; made only when the anchor was seen) without them.

    ``region``: measure parts between keyframes by their silhouettes (:mod:`surftrack.track.region`:
    colour statistics along lines normal to the rendered outline, one fit per instrument through its
    kinematics). Up to ``region_points`` contour points per part; a fit whose lines agree with its
    outline less than ``region_min_agreement`` (share of line pixels on the right side) is not used. The
    colour histograms (``region_colors``) are learnt on keyframes from the network's masks of the parts
    ("network", at ``region_mask_rate`` per keyframe; before an instrument's first keyframe, e.g. a track
    seeded by ``set_pose``, from its predicted silhouette at ``region_learn_rate``), or on every frame from
    the track's predicted silhouette ("track", at ``region_learn_rate`` per frame). Learnt at the track's
    pose, the silhouette's depth repeated 60 % to all of the track's depth error; with the network's masks
    the tracks scored +5.4 +- 2.1 points of ADD-10 on 15 held-out runs, paths and speed error as before
    (docs/results/2026-12-05-network-colors.md). The instrument's joints may move
    ``region_joint_std_deg`` per frame (the fit's prior). Only the pose directions the fit pins better
    than ``region_max_std_mm`` / ``region_max_std_deg`` are fused (a silhouette sees the lateral position,
    not the depth), with ``region_floor_mm`` / ``region_floor_deg`` added. With a keyframe at least every
    10 frames it is the default: on five held-out clips it scored above the estimator on every frame on
    average for every part, at 1.1-1.8x its speed, and below it on two of them (``configs/track/
    every_frame.yaml`` keeps that mode; docs/results/2026-12-03-region.md). It needs a keyframe cadence
    above 1: a part due for the estimator is not measured by its silhouette on that frame.

    ``articulated`` (``configs/track/articulated.yaml``; off by default): one filter state per described
    instrument whose root part (the shaft) is tracked (:mod:`surftrack.track.instrument`: the root's pose
    and the joints, each with its rate); its parts are views of it through the forward kinematics, so
    every measurement of one part (keyframe, silhouette) moves the others consistently, a hidden part
    keeps the pose the rest implies and the joints are read off the state (its rates do not decay:
    ``kalman.coast_tau_s`` is a per-part filter's, and ``region_joint_std_deg`` gives way to the state's
    own joint covariance as the silhouette fit's prior). On eight held-out clips it
    scored +6.0 / -1.8 / +6.2 / +1.0 points of ADD-10 against a filter per part, within the clips'
    spread; on the 15 fps demo clip its wrist and jaws lose 20-28 points and their confidence does
    not rank their errors (docs/results/2026-12-03-articulated.md, 2026-12-03-confidence.md), so it is
    not the default yet. The joints' white-noise acceleration is ``joint_accel_std_rad_s2`` (8 let the jaws jitter 1.1-1.2
    deg a frame on the tuning clip, 2 kept them at 0.5). On a keyframe with the kinematic fit, the instrument's parts'
    poses come from one joint fit: each is fused with the estimator's covariance times the number of
    them (one measurement of the state, not one per part).

    ``trocar`` (with ``articulated``): the shaft axes of the estimator's shaft poses locate the
    instrument's trocar (:mod:`surftrack.track.trocar`; after ``trocar_after`` of them, while the camera
    holds still) and each frame's state is held to pass its shaft through it, within ``trocar_floor_mm``
    (the trocar's play) on top of the point's own uncertainty. Off: on the development clips 3 and 12
    the tools pivot a few degrees and the estimator's axes scatter as much, so the point is pinned
    across the shaft but not along it, and holding the state to it cost 5-10 points of ADD-10 on the
    wrist and jaws; even the clips' true trocar gained nothing clear (docs/decisions.md).

    ``smooth_lag_s``: offline smoothing: each frame's pose is written once this many seconds of later
    frames have been filtered, smoothed backward from them (:mod:`surftrack.track.smoother`; the run's
    memory holds that many frames); 0 writes the causal filter's poses as they come (``--causal``).
    ``smooth_lateral_accel_std_mm_s2``, ``smooth_depth_accel_std_mm_s2``: the smoother's own white-noise
    acceleration of each part's position across and along its line of sight (mm/s^2;
    :class:`~surftrack.track.smoother.SmootherPrior`); the filter keeps ``kalman.accel_std_mm_s2`` in every
    direction, because a stiff prior there lags the moves its gate then refuses (docs/decisions.md). The
    estimator's depth errs by 2-3 mm, correlated over many frames, its image position by 0.2 mm: the
    smoother believes depth changes less and lateral moves more. 10 / 120 against the filter's 30: on
    ten fresh runs (clips 76-80) the median speed error 26 -> 20 %, ADD-10 -0.2 +- 0.5 points
    (docs/results/2026-12-06-smoother-prior.md; with the estimator on every frame, seven development
    runs: 32 -> 23 %, ADD-10 +0.8 +- 1.4). ``smooth_ang_accel_std_rad_s2``: the smoother's white-noise
    angular acceleration of each part (rad/s^2) in place of ``kalman.ang_accel_std_rad_s2``: the tool tip,
    10 mm out on the jaws, moves with every wobble of their rotation. 1.5 against the filter's 3: the
    tip's median speed error 25 -> 22 % on the fresh runs, 26 -> 20 % on 15 held-out ones, ADD-10 -0.2 +-
    0.2 and -0.1 +- 0.2 (docs/results/2026-12-06-tip-rotation-prior.md). With ``articulated`` both act on
    the instrument's root pose (the joints keep ``joint_accel_std_rad_s2``;
    docs/results/2026-12-06-articulated-prior.md).
    ``retro_restart``: a track the estimator has disagreed with ``kalman.max_rejections`` times in a row
    starts again from those refused estimates (as far back as they continue the last one), from the
    first of them on, instead of from the last one alone: the frames in between, wrong in the old track,
    take the new one's poses once smoothed (a causal run only gains the better-founded restart). A track
    that ends (the part lost) while the estimator disagrees with it, fewer times than that, has its last
    frames taken from those refused estimates in the same way, where at least two agree (a fast move out
    of the view, which the track lags behind and its gate refuses; the causal run is not changed).

    ``confidence_add``, ``confidence_scale``, ``confidence_nis_weight``: a written pose's confidence
    (:func:`~surftrack.track.state.confidence`) is the probability that its position error is within
    ``confidence_add`` times the part's diameter (0.1: ADD-10's threshold), the error's covariance the
    filter's, scaled by the track's running normalised innovation (each measurement's d2 / dof entering
    with weight ``confidence_nis_weight``), plus how far smoothing moved the pose, times
    ``confidence_scale`` (1.5 split ADD-10 best at confidence 0.5 on the development clips 3, 12 and 22;
    the filter's covariance alone is overconfident).

    ``twin_boxes``: the jaws of a grasper with a roll twin are also estimated on each other's boxes and the
    better-scoring assignment kept (:meth:`surftrack.pose.PoseEstimator.estimate`'s ``groups``): beyond a
    quarter turn of roll a box's label names the other jaw to the model. Off by default: two more crops
    per such keyframe made tracking 20 % slower on clips in the view's roll range, where it changed
    nothing beyond the runs' spread; on tools rolled away the jaws gain (docs/results/2026-12-05-stage7.md).

    ``twin_match``: the detections of a twin grasper's tracked jaws are exchanged when each fits the other
    jaw's tracked projection better by ``twin_match_margin`` (summed IoU), so that the jaws' keyframes read
    the boxes of the jaws the state holds (no extra crops; :meth:`~surftrack.track.tracker.Tracker._match_twin_boxes`).

    ``twin_align``: a keyframe's estimates of a twin grasper's tracked parts are turned to the roll twin
    where that lies nearer the tracks (:meth:`~surftrack.track.tracker.Tracker._nearer_twins`): both give
    the same image, and the track's motion, not the model's side of a quarter turn, decides which; only
    where the twin lies within ``twin_align_max_deg`` of the root part's track (turning a track already
    ~90 deg off made it worse: docs/decisions.md, "Keeping the roll twin that continues the track").

    ``kinematic``: the estimator's poses of the parts of one instrument estimated on the same frame are
    replaced by the instrument-consistent ones (:mod:`surftrack.pose.kinematic`), with ``kinematic_anchor``'s
    rotation weighted ``kinematic_anchor_weight`` times its score and its translation
    ``kinematic_anchor_translation_weight`` times. ``anchor_views``: crop views per box of the anchor
    part (0: as the others' ``views``); with the fit, the anchor's depth places the whole instrument.
    """

    preset: str = "fast"
    views: int = 0
    solver_seed: int = 0
    keyframe_every: int = 10
    keyframe_max_s: float = 0.34
    flow: bool = False
    region: bool = True
    twin_boxes: bool = False
    twin_match: bool = True
    twin_align: bool = True
    twin_align_max_deg: float = 45.0
    twin_match_margin: float = 0.2
    region_points: int = 100
    region_min_agreement: float = 0.7
    region_colors: str = "network"
    region_learn_rate: float = 0.2
    region_mask_rate: float = 0.5
    region_floor_mm: float = 0.3
    region_floor_deg: float = 1.0
    region_joint_std_deg: float = 10.0
    region_max_std_mm: float = 1.0
    region_max_std_deg: float = 3.0
    articulated: bool = False
    joint_accel_std_rad_s2: float = 2.0
    trocar: bool = False
    trocar_after: int = 8
    trocar_floor_mm: float = 2.0
    min_box_score: float = 0.3
    min_iou: float = 0.2
    max_predicted: int = 3
    max_occluded: int = 30
    min_visible: float = 0.15
    max_points: int = 80
    refresh_every: int = 10
    refresh_below: float = 0.6
    min_points: int = 6
    inlier_px: float = 3.0
    min_inlier_ratio: float = 0.5
    max_rms_px: float = 2.0
    flow_floor_mm: float = 0.3
    flow_floor_deg: float = 0.3
    est_pos_std_mm: float = 3.0
    est_lateral_std_mm: float = 3.0
    est_rot_std_deg: float = 5.0
    init_min_inliers: int = 6
    init_min_score: float = 0.0
    smooth_lag_s: float = 1.0
    smooth_lateral_accel_std_mm_s2: float = 120.0
    smooth_depth_accel_std_mm_s2: float = 10.0
    smooth_ang_accel_std_rad_s2: float = 1.5
    retro_restart: bool = True
    confidence_add: float = 0.1
    confidence_scale: float = 1.5
    confidence_nis_weight: float = 0.3
    kinematic: bool = True
    kinematic_anchor: str = "wrist"
    kinematic_anchor_weight: float = 10.0
    kinematic_anchor_translation_weight: float = 3.0
    anchor_views: int = 0
    kalman: KalmanConfig = field(default_factory=KalmanConfig)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v, kind = getattr(self, f.name), type(f.default) if f.default is not dataclasses.MISSING else None
            if kind in (int, float):
                ok = isinstance(v, (int, float)) and not isinstance(v, bool) and (kind is float or float(v).is_integer())
                if not ok:
                    raise ValueError(f"{f.name} must be {'an integer' if kind is int else 'a number'}, got {v!r}")
                object.__setattr__(self, f.name, kind(v))
            elif kind is str and not isinstance(v, str):
                raise ValueError(f"{f.name} must be a string, got {v!r}")
            elif kind is bool and not isinstance(v, bool):
                raise ValueError(f"{f.name} must be true or false, got {v!r}")
        if self.preset not in PRESETS:
            raise ValueError(f"preset must be one of {', '.join(sorted(PRESETS))}, got {self.preset!r}")
        if not 0 <= self.views <= 9:
            raise ValueError(f"views must be 0 (the preset's) or 1-9, got {self.views}")
        if not 0 <= self.anchor_views <= 9:
            raise ValueError(f"anchor_views must be 0 (as the other parts) or 1-9, got {self.anchor_views}")
        if self.solver_seed < 0:
            raise ValueError(f"solver_seed must be >= 0, got {self.solver_seed}")
        if self.region_colors not in REGION_COLORS:
            raise ValueError(f"region_colors must be one of {', '.join(REGION_COLORS)}, got {self.region_colors!r}")
        if self.keyframe_every < 1:
            raise ValueError(f"keyframe_every must be >= 1, got {self.keyframe_every}")
        for name in ("min_box_score", "min_iou", "min_visible", "refresh_below", "min_inlier_ratio",
                     "confidence_nis_weight", "region_min_agreement", "region_learn_rate", "region_mask_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.max_occluded < 0:
            raise ValueError(f"max_occluded must be >= 0, got {self.max_occluded}")
        for name in ("max_points", "refresh_every", "max_predicted", "region_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("kinematic_anchor_weight", "kinematic_anchor_translation_weight"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.trocar_after < 2:
            raise ValueError(f"trocar_after must be >= 2 (axes to meet), got {self.trocar_after}")
        if self.trocar and not self.articulated:
            raise ValueError("trocar needs articulated: true (it constrains an instrument's state)")
        if self.min_points < 4:
            raise ValueError(f"min_points must be >= 4 (PnP), got {self.min_points}")
        for name in ("inlier_px", "max_rms_px", "est_pos_std_mm", "est_lateral_std_mm", "est_rot_std_deg",
                     "confidence_add", "confidence_scale", "region_joint_std_deg", "region_max_std_mm",
                     "region_max_std_deg", "joint_accel_std_rad_s2", "smooth_lateral_accel_std_mm_s2",
                     "smooth_depth_accel_std_mm_s2", "smooth_ang_accel_std_rad_s2"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("flow_floor_mm", "flow_floor_deg", "region_floor_mm", "region_floor_deg", "trocar_floor_mm",
                     "twin_match_margin", "twin_align_max_deg"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {getattr(self, name)}")
        if not (math.isfinite(self.keyframe_max_s) and self.keyframe_max_s >= 0):
            raise ValueError(f"keyframe_max_s must be a finite number >= 0, got {self.keyframe_max_s}")
        if not (math.isfinite(self.smooth_lag_s) and self.smooth_lag_s >= 0):
            raise ValueError(f"smooth_lag_s must be a finite number >= 0, got {self.smooth_lag_s}")
        if not math.isfinite(self.init_min_score):
            raise ValueError(f"init_min_score must be a finite number, got {self.init_min_score}")

    def kinematic_config(self) -> KinematicConfig | None:
        """The instrument-consistency settings for :func:`surftrack.pose.kinematic.apply_kinematics`, or
        None when ``kinematic`` is off."""
        if not self.kinematic:
            return None
        return KinematicConfig(self.kinematic_anchor, self.kinematic_anchor_weight,
                               anchor_translation_weight=self.kinematic_anchor_translation_weight)

    def smoother_prior(self) -> SmootherPrior | None:
        """The smoother's motion prior, or None where it is the filter's own (with ``articulated``, of the
        instrument's root pose)."""
        a, w = self.kalman.accel_std_mm_s2, self.kalman.ang_accel_std_rad_s2
        lateral, depth = self.smooth_lateral_accel_std_mm_s2, self.smooth_depth_accel_std_mm_s2
        if lateral == depth == a and self.smooth_ang_accel_std_rad_s2 == w:
            return None
        return SmootherPrior(a, lateral, depth, w, self.smooth_ang_accel_std_rad_s2)

    def for_fps(self, fps: float) -> TrackConfig:
        """This config for a video at ``fps`` frames/s: ``keyframe_every`` lowered to ``keyframe_max_s``
        of video where that is tighter (at least 1 frame)."""
        if self.keyframe_max_s <= 0 or not (fps and math.isfinite(fps) and fps > 0):
            return self
        # floor: the bound in seconds is a bound, not a target (the hair keeps 0.7 s x 90 fps at 63)
        frames = math.floor(self.keyframe_max_s * fps + 1e-9)
        return self.replace(keyframe_every=min(self.keyframe_every, max(1, frames)))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def estimator_preset(self) -> Preset:
        """The keyframes' estimator preset: ``preset`` with ``views`` where given, ``anchor_views`` for the
        instrument fit's anchor part where given (with ``kinematic``) and ``solver_seed``."""
        preset = PRESETS[self.preset] if self.views == 0 else PRESETS[self.preset].replace(views=self.views)
        if self.kinematic and self.anchor_views:
            preset = preset.replace(part_views=((self.kinematic_anchor, self.anchor_views),))
        return preset.replace(seed=self.solver_seed)

    def replace(self, **changes) -> TrackConfig:
        return dataclasses.replace(self, **changes)


def load_track_config(path: str | Path | None = None) -> TrackConfig:
    """Load ``path`` (YAML; a bare name like ``default`` means ``configs/track/default.yaml``; None = the
    default file)."""
    p, data = read_config_yaml(path if path is not None else "default", "track", "tracking config",
                               TrackConfigError)
    return build_dataclass(TrackConfig, data, str(p), TrackConfigError)

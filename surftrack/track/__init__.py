"""Temporal tracking of per-part poses.

:class:`Tracker` runs the per-part state machine (:mod:`.tracker`): the pose estimator initialises,
recovers and re-measures parts on keyframes; between them each instrument's silhouette, by colour
statistics along lines normal to its rendered outline (:mod:`.region`), measures it (pyramidal LK on
model points plus PnP, :mod:`.flow`, is the option); :class:`PoseKalman` (:mod:`.kalman`, 12-state
error-state constant velocity, gated before update) fuses them, one per part, or the parts of a
described instrument share one articulated state (:mod:`.instrument`, ``articulated``). :mod:`.state`
holds what the tracker reports per part and frame (:class:`PartState`); :mod:`.inputs` validates the inputs of a
run (video, intrinsics, det.json / COCO boxes); :mod:`.config` holds the settings
(``configs/track/default.yaml``); :mod:`.smoother` smooths the filter's states backward for offline runs;
:mod:`.status` names a part's status on a frame and its diagnostics.
"""

from surftrack.track.config import TrackConfig, TrackConfigError, load_track_config
from surftrack.track.inputs import InputError
from surftrack.track.kalman import CHI2_6DOF_999, KalmanConfig, PoseKalman
from surftrack.track.status import MEASURED, POSED, Diagnostics, Status
from surftrack.track.state import PartSpec, PartState, ended_revisions, filter_steps
from surftrack.track.tracker import Tracker

__all__ = [
    "CHI2_6DOF_999", "Diagnostics", "MEASURED", "POSED", "InputError", "KalmanConfig", "PartSpec",
    "PartState", "PoseKalman", "Status", "TrackConfig", "TrackConfigError", "Tracker", "ended_revisions",
    "filter_steps", "load_track_config",
]

"""Temporal tracking of per-part poses: :class:`PoseKalman`, a 12-state error-state constant-velocity
Kalman filter (right/body rotation error, nominal rotation outside the filter, pre-update chi2 gating)."""

from surftrack.track.kalman import CHI2_6DOF_999, KalmanConfig, PoseKalman

__all__ = ["CHI2_6DOF_999", "KalmanConfig", "PoseKalman"]

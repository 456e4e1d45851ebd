"""Monocular visual-inertial odometry: front-end, static initialisation, preintegration,
GTSAM fixed-lag back-end, IMU-rate propagation, sparse metric map and health."""

from autonomy.vins.estimator import FrameUpdate, Vins
from autonomy.vins.frontend import FeatureTracker, FrontendOptions, Tracks, fundamental_inliers
from autonomy.vins.health import Health, HealthState
from autonomy.vins.options import VinsOptions
from autonomy.vins.preintegration import ImuNoise
from autonomy.vins.static_init import StaticInitOptions

__all__ = ["FeatureTracker", "FrameUpdate", "FrontendOptions", "Health", "HealthState",
           "ImuNoise", "StaticInitOptions", "Tracks", "Vins", "VinsOptions",
           "fundamental_inliers"]

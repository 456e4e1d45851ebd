"""Monocular visual-inertial odometry: feature tracking front-end (back-end to follow)."""

from autonomy.vins.frontend import FeatureTracker, FrontendOptions, Tracks, fundamental_inliers

__all__ = ["FeatureTracker", "FrontendOptions", "Tracks", "fundamental_inliers"]

"""The route: waypoints in PX4's local frame ``L``, the last one the goal, followed in order.

Goals are given in ``L`` and planned in the VINS world ``W``; ``T_L_W`` ties the two
(:func:`autonomy.geometry.yaw_alignment`, fixed on the ground before take-off).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import invert_pose, yaw_of


def checked_waypoints(waypoints) -> np.ndarray:
    """``waypoints`` as an (N, 3) float array; ValueError unless N >= 1 finite points."""
    points = np.asarray(waypoints, dtype=float)
    if points.ndim == 1:
        points = points.reshape(1, -1)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"waypoints must be (N, 3) points, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("waypoints must be finite numbers")
    return points


def stop_waypoints(waypoints: np.ndarray, sharpest: float) -> list[bool]:
    """Per waypoint of ``waypoints`` (N, 3): does the vehicle stop there? The last (the goal)
    and every corner where the route turns by more than ``sharpest`` radians horizontally."""
    stops = [False] * len(waypoints)
    stops[-1] = True
    for k in range(1, len(waypoints) - 1):
        into, out = np.diff(waypoints[k - 1:k + 2, :2], axis=0)
        turn = math.atan2(into[0] * out[1] - into[1] * out[0], into @ out)
        stops[k] = abs(turn) > sharpest
    return stops


def to_world(T_L_W: np.ndarray, point_L) -> np.ndarray:
    """A point of PX4's local frame ``L`` in the VINS world ``W``."""
    T_W_L = invert_pose(T_L_W)
    return T_W_L[:3, :3] @ np.asarray(point_L, dtype=float) + T_W_L[:3, 3]


def heading_error(T_W_B: np.ndarray, target_W: np.ndarray, turned: float = 0.0) -> float:
    """Angle from the body's heading to the bearing of ``target_W`` turned by ``turned``
    (radians, counter-clockwise), radians in (-pi, pi]."""
    to_target = target_W - T_W_B[:3, 3]
    error = math.atan2(to_target[1], to_target[0]) + turned - yaw_of(T_W_B[:3, :3])
    return math.atan2(math.sin(error), math.cos(error))


@dataclass(frozen=True)
class Progress:
    """What one position did to the route: ``goal_reached``; ``passed`` waypoints passed;
    ``corner``: the last one passed was a stop waypoint (stop and turn before going on)."""

    goal_reached: bool = False
    passed: int = 0
    corner: bool = False


class Route:
    """The waypoints and which one is next (``index``).

    Stop waypoints (:func:`stop_waypoints` with ``corner_turn`` radians): the goal, and
    corners sharper than ``corner_turn``, approached slowly; at rest the vehicle faces the
    next leg.
    """

    def __init__(self, waypoints_L, corner_turn: float):
        self.waypoints_L = checked_waypoints(waypoints_L)
        self.stop_at = stop_waypoints(self.waypoints_L, corner_turn)
        self.index = 0

    @property
    def at_last(self) -> bool:
        """Is the next waypoint the goal?"""
        return self.index == len(self.waypoints_L) - 1

    @property
    def stops_next(self) -> bool:
        """Does the vehicle stop at the next waypoint (a corner, the goal)?"""
        return self.stop_at[self.index]

    def next_W(self, T_L_W: np.ndarray) -> np.ndarray:
        """The next waypoint in the VINS world."""
        return to_world(T_L_W, self.waypoints_L[self.index])

    def advance(self, position_W: np.ndarray, T_L_W: np.ndarray, options) -> Progress:
        """Pass every waypoint within ``waypoint_tolerance`` (a stop waypoint:
        ``corner_tolerance``), or reach the goal within ``goal_tolerance`` and
        ``height_tolerance`` (``options``: :class:`~autonomy.navigation.mission.FlightOptions`):
        horizontal distances and, for the goal, the height (as PX4's acceptance radius and
        altitude acceptance). A waypoint guides the route; the planner may pass it higher,
        over what lies below."""
        passed, corner = 0, False
        while True:
            offset = self.next_W(T_L_W) - position_W
            distance = float(np.hypot(offset[0], offset[1]))
            if self.at_last and distance <= options.goal_tolerance \
                    and abs(float(offset[2])) <= options.height_tolerance:
                return Progress(True, passed, corner)
            tolerance = options.corner_tolerance if self.stops_next else \
                options.waypoint_tolerance
            if self.at_last or distance > tolerance:
                return Progress(False, passed, corner)
            corner = self.stops_next
            passed += 1
            self.index += 1

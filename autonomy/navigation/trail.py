"""The flown trail: where the vehicle has just been, the ground it knows to be free.

Two behaviours fly back over it (docs/flight.md). The parallax glide after a turn in place
glides straight to the trail point :data:`GLIDE_STEP_M` behind and back. Backing off from a
dead end glides, every round, toward the trail point a quarter metre ahead of it on the way
back, and brakes once, over the way's last braking distance
(:class:`~autonomy.navigation.behaviours.Backoff`).
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: A position every TRAIL_SPACING_M of flight, TRAIL_LENGTH of them (6 m: more than
#: ``[flight] backoff_distance`` may be).
TRAIL_SPACING_M = 0.1
TRAIL_LENGTH = 60
#: How far back along the trail the parallax glide goes, and the shortest way a backing-off
#: flies, metres.
GLIDE_STEP_M = 0.5


class Trail:
    """The flown positions (frame W), newest last, with loops erased, each marked whether it
    was flown on the take-off climb."""

    def __init__(self):
        self.points: deque[np.ndarray] = deque(maxlen=TRAIL_LENGTH)
        self.climbing: deque[bool] = deque(maxlen=TRAIL_LENGTH)

    def __len__(self) -> int:
        return len(self.points)

    def record(self, position_W: np.ndarray, climbing: bool = False) -> None:
        """Add a flown position (``climbing``: on the take-off climb), loops erased: a
        position back within TRAIL_SPACING_M of an older one (a glide back and forth) cuts
        the trail there, so the trail is the way back without detours."""
        points = self.points
        for k in range(len(points) - 1, -1, -1):
            if np.linalg.norm(position_W - points[k]) < TRAIL_SPACING_M:
                while len(points) > k + 1:
                    points.pop()
                    self.climbing.pop()
                return
        points.append(position_W.copy())
        self.climbing.append(climbing)

    def point_behind(self, position_W: np.ndarray) -> np.ndarray | None:
        """The newest trail point at least GLIDE_STEP_M from ``position_W`` (None if none):
        where the parallax glide goes back to."""
        return next((p.copy() for p in reversed(self.points)
                     if np.linalg.norm(p - position_W) >= GLIDE_STEP_M), None)

    def way_back(self, position_W: np.ndarray, distance: float) -> np.ndarray | None:
        """The trail back from ``position_W``: the polyline from it through the trail's
        points, newest first, ending at the first one ``distance`` back along it, or at its
        oldest point above the take-off column (backing off never descends it). None when
        that is shorter than GLIDE_STEP_M, or than ``distance`` when that is shorter."""
        path, run = [position_W.copy()], 0.0
        for point, climbing in zip(reversed(self.points), reversed(self.climbing)):
            if climbing or run >= distance:
                break
            run += float(np.linalg.norm(point - path[-1]))
            path.append(point.copy())
        return np.array(path) if run >= min(distance, GLIDE_STEP_M) and run > 0.0 else None

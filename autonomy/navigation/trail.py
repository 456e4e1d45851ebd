"""The flown trail: where the vehicle has just been, the ground it knows to be free.

Two behaviours fly back over it (docs/flight.md): the parallax glide after a turn in place,
and backing off from a dead end. Both glide straight between trail points; with the points
:data:`GLIDE_STEP_M` apart, a glide stays within centimetres of the path flown.
"""

from __future__ import annotations

from collections import deque

import numpy as np

#: A position every TRAIL_SPACING_M of flight, TRAIL_LENGTH of them (6 m: more than
#: ``[flight] backoff_distance`` may be).
TRAIL_SPACING_M = 0.1
TRAIL_LENGTH = 60
#: Length of one straight glide back along the trail, metres (the parallax glide's too).
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

    def way_back(self, position_W: np.ndarray, distance: float) -> list[np.ndarray]:
        """Points of the trail back from ``position_W`` about every GLIDE_STEP_M of it,
        ending where it has run ``distance`` back, or at its oldest point above the take-off
        column (backing off never descends it): the straight glides between them stay within
        centimetres of the trail."""
        points, run, previous, since_point = [], 0.0, position_W, 0.0
        for point, climbing in zip(reversed(self.points), reversed(self.climbing)):
            if climbing:
                break
            step = float(np.linalg.norm(point - previous))
            run, since_point, previous = run + step, since_point + step, point
            if since_point >= GLIDE_STEP_M or run >= distance:
                points.append(point.copy())
                since_point = 0.0
            if run >= distance:
                break
        if points and run < distance and since_point > 0.0:
            points.append(previous.copy())  # the trail ran out: its oldest point
        return points

"""The speed wave: forward flight slowed and sped up again, slowly, so the VINS sees the scale.

A monocular VINS learns the scale of its map from the accelerometer: what the IMU says the
vehicle's speed changed by, against what the camera says it moved. At a constant speed the
accelerometer reads gravity and nothing else, and the scale is carried from landmark to
landmark with every track's error until the next acceleration (docs/vins.md, "The hallway's
drift is the cruise's": down the simulator's sewer pipe the map's scale walks by 3 % over a
minute of cruise, and swinging the speed by 0.3 m/s either way every 3.3 s holds it within
0.8 %).

The wave multiplies the speed along a flown path by

    m(t) = 1 - (swing / v) (1 - cos(2 pi t / period)) / 2,

between 1 and ``1 - swing / v``, so a vehicle flying a path checked at speed ``v`` never goes
faster than ``v`` and always along the same path: the check that cleared the path clears the
wave too. The phase runs on the clock ``t``, so consecutive plans join without a jump in
speed. The path's arc length after ``t0`` is ``v`` times

    W(t) - W(t0),  W(t) = (1 - s / 2) t + s period / (4 pi) sin(2 pi t / period),  s = swing / v,

the wave's progress, and the acceleration along it ``m' v``, with ``m'`` the wave's rate.
``swing / v`` is held to at most :data:`MAX_SHARE`, so a slow plan is not brought near rest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Largest share of a plan's speed the wave takes away at its trough.
MAX_SHARE = 0.5


@dataclass(frozen=True)
class SpeedWave:
    """The wave of the module docstring: ``swing`` m/s taken off at the trough, every
    ``period_s`` seconds."""

    swing: float
    period_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.swing) and self.swing > 0.0):
            raise ValueError(f"a speed wave's swing must be positive, got {self.swing!r}")
        if not (math.isfinite(self.period_s) and self.period_s > 0.0):
            raise ValueError(f"a speed wave's period must be positive, got {self.period_s!r}")

    @classmethod
    def of(cls, swing: float, period_s: float) -> "SpeedWave | None":
        """The wave of these settings, None for a ``swing`` of 0 (flown at speed)."""
        return cls(swing, period_s) if swing != 0.0 else None

    def share(self, speed: float) -> float:
        """The share of ``speed`` (m/s) taken off at the trough: ``swing / speed``, at most
        :data:`MAX_SHARE`; 0 for a plan at rest."""
        return min(self.swing / speed, MAX_SHARE) if speed > 0.0 else 0.0

    def factor(self, t: float, share: float) -> float:
        """``m(t)``: the speed's multiplier at clock time ``t`` for a plan of this ``share``."""
        return 1.0 - share * (1.0 - math.cos(self._omega * t)) / 2.0

    def rate(self, t: float, share: float) -> float:
        """``m'(t)``, per second."""
        return -share * self._omega * math.sin(self._omega * t) / 2.0

    def progress(self, t0: float, t: float, share: float) -> float:
        """``W(t) - W(t0)``: the seconds of the unslowed plan flown between ``t0`` and ``t``."""
        return ((1.0 - share / 2.0) * (t - t0)
                + share / (2.0 * self._omega) * (math.sin(self._omega * t)
                                                  - math.sin(self._omega * t0)))

    def time_at(self, t0: float, progress: float, share: float) -> float:
        """The clock time after ``t0`` at which the wave's :meth:`progress` reaches
        ``progress`` seconds (by bisection: the progress rises at ``1 - share`` to 1)."""
        low, high = t0 + progress, t0 + progress / (1.0 - share)
        for _ in range(60):
            middle = (low + high) / 2.0
            if self.progress(t0, middle, share) < progress:
                low = middle
            else:
                high = middle
        return high

    @property
    def _omega(self) -> float:
        return 2.0 * math.pi / self.period_s

"""The height wave: the flown path swung up and down a few centimetres, so the VINS sees the scale.

A monocular VINS learns the scale of its map from the accelerometer: what the IMU says the
vehicle's velocity changed by, against what the camera says it moved. At a constant velocity
the accelerometer reads gravity and nothing else, and the scale walks with the tracks' error
until the next acceleration (docs/vins.md, "The hallway's drift is the cruise's"). The speed
wave (speed_wave.py) gives the acceleration along the path, at a sixth of the speed; this wave
gives it across the path, vertically, without slowing the path down: any direction of
acceleration fixes the one scale of a monocular map. Checked with a sphere ``A`` larger it
cost 3 % of the speed on true depth and 9 % on estimated at 8 cm, most in narrow passages
(docs/vins.md, "The height wave"); the planner now checks its crest and trough instead
(below), and flies an arc level where only the level path is clear at its speed.

A plan's path is offset vertically by

    h(t) = A f(tau) sin(w t),   w = 2 pi / period,

with ``f`` the plan's motion share: 1 along its arc, falling linearly to 0 over its braking
(``f = 1 - s / T``, ``s`` the braking's elapsed time of ``T``), 0 at rest, so a vehicle at rest
holds its height. The phase runs on the clock, so consecutive arcs join without a jump. Its
velocity and acceleration are the derivatives,

    h' = A (f' sin + f w cos),   h'' = A (f'' sin + 2 f' w cos - f w² sin),

peaking at ``A w`` and ``A w²`` on the arc (0.25 m/s and 0.79 m/s² for 8 cm every 2 s, where
the speed wave's 0.6 m/s every 3.3 s peaks at 0.57 m/s²). The planner checks each arc about
the line the wave swings about at its crest and trough, with spheres of ``sqrt(r² + A²)``
(planner.py), so every sphere along the flown path lies inside one it checked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple


class Offset(NamedTuple):
    """The wave's vertical offset at one instant: ``height`` m, ``velocity`` m/s,
    ``acceleration`` m/s² (up)."""

    height: float
    velocity: float
    acceleration: float


@dataclass(frozen=True)
class HeightWave:
    """The wave of the module docstring: ``amplitude`` metres up and down, every ``period_s``
    seconds."""

    amplitude: float
    period_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amplitude) and self.amplitude > 0.0):
            raise ValueError(f"a height wave's amplitude must be positive, got "
                             f"{self.amplitude!r}")
        if not (math.isfinite(self.period_s) and self.period_s > 0.0):
            raise ValueError(f"a height wave's period must be positive, got {self.period_s!r}")

    @classmethod
    def of(cls, amplitude: float, period_s: float) -> "HeightWave | None":
        """The wave of these settings, None for an ``amplitude`` of 0 (flown level)."""
        return cls(amplitude, period_s) if amplitude != 0.0 else None

    def offset(self, t: float, share: float, share_rate: float = 0.0,
               share_curvature: float = 0.0) -> Offset:
        """``h``, ``h'``, ``h''`` at clock time ``t`` for the motion share ``f = share`` and
        its first and second time derivatives ``share_rate`` and ``share_curvature``."""
        w = 2.0 * math.pi / self.period_s
        sin, cos = math.sin(w * t), math.cos(w * t)
        a = self.amplitude
        return Offset(a * share * sin,
                      a * (share_rate * sin + share * w * cos),
                      a * (share_curvature * sin + 2.0 * share_rate * w * cos
                           - share * w * w * sin))

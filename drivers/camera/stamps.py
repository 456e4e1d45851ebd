"""Frame stamps read off the camera's frame grid, not off each frame's arrival.

A camera exposes its frames on a fixed grid, one every period of its own clock, and most
number them: a RealSense frame number, an OAK's sequence number
(:attr:`~autonomy.messages.Frame.counter`; the V4L2 driver, through OpenCV, reads none).
Where the stamp is taken on the host as the frame arrives (an unsynchronised USB camera's:
the realistic simulator's 1 ms of jitter, ``[sim_camera] timestamp_jitter_ms``), each frame's
stamp is off its exposure by its own draw
of the transfer's and the scheduler's delay. The VINS takes the stamp as the exposure's time:
at 2 m/s a 1 ms error puts the camera 2 mm off the pose the IMU reckons for it, and the IMU
preintegrated between two keyframes spans the wrong interval, differently each time.

**The grid.** With ``n`` the frame's counter, its stamp is ``t = a + p n + e``: ``p`` the
period on the host's clock (the camera's crystal drifts against the host's by some ppm, so
``p`` is fitted, not taken as ``1 / rate``), ``a`` where the grid sits, ``e`` the jitter.
:class:`GridStamps` fits the line by least squares to the last ``window`` frames and gives each
new frame the line's time at its counter. Causal (the frame itself is the newest point), and
with ``N`` frames in the fit the stamp's error at the newest point has a standard deviation
of about ``sigma_e sqrt(4 / N)`` (a line's fitted value at the end of ``N`` evenly spaced
points): 1 ms of jitter becomes 0.16 ms over 150 frames. A constant part of the delay stays in
``a``, as it stays in the raw stamps; the camera-IMU time offset takes it
(``[camera] time_offset_s``, ``[vins] estimate_time_offset``).

**What breaks the grid.** A frame held up far longer than the jitter (a host stall) is off the
line by more than ``max_residual_s``: it gets the line's stamp, which is when it was exposed,
and stays out of the fit. ``restart_after`` such frames in a row mean the line no longer holds
(the camera's clock stepped), and so does a counter that goes back (the driver restarted
its stream): the fit starts again from that frame. A frame with no counter, a repeated counter
(a frame delivered twice: the application refuses it as stale) or a stamp that is not a finite
number passes through unchanged and does not touch the fit; so does every frame until
``least_frames`` are in it.
"""

from __future__ import annotations

import collections
import logging
import math

import numpy as np

log = logging.getLogger(__name__)

#: Frames the line is fitted to before it stamps any: the first ones pass through as stamped.
LEAST_FRAMES = 10
#: Frames in the fit: 5 s at 30 Hz, 0.16 of the jitter left (module docstring); a crystal's
#: drift of even 100 ppm is a straight line over it.
WINDOW_FRAMES = 150
#: How far off the line, in frame periods, a stamp may be and still join the fit (the
#: simulator's jitter is clipped at a quarter period).
MAX_RESIDUAL_PERIODS = 0.25
#: Frames off the line in a row after which the line no longer holds.
RESTART_AFTER = 5


class GridStamps:
    """Stamps from the frame counter's grid (module docstring): ``stamp(t, counter)`` for each
    frame in the order delivered. ``window``: frames in the fit (at least
    :data:`LEAST_FRAMES`); ``max_residual_s``: how far off the line a stamp may be and still
    join the fit; ``restart_after``: frames off the line in a row after which the fit starts
    again."""

    @classmethod
    def for_rate(cls, rate_hz: float) -> "GridStamps":
        """The defaults for a camera of ``rate_hz`` frames a second."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"the frame rate must be a positive number of Hz, got {rate_hz}")
        return cls(WINDOW_FRAMES, MAX_RESIDUAL_PERIODS / rate_hz, RESTART_AFTER)

    def __init__(self, window: int, max_residual_s: float, restart_after: int):
        if window < LEAST_FRAMES:
            raise ValueError(f"the window must hold at least {LEAST_FRAMES} frames, got {window}")
        if not (math.isfinite(max_residual_s) and max_residual_s > 0):
            raise ValueError(f"max_residual_s must be a positive number, got {max_residual_s}")
        if restart_after < 1:
            raise ValueError(f"restart_after must be at least 1, got {restart_after}")
        self.max_residual_s, self.restart_after = max_residual_s, restart_after
        self._points: collections.deque[tuple[int, float]] = collections.deque(maxlen=window)
        self._off_line = 0  # frames off the line in a row
        self.restarts = 0  # times the fit started again (after its first start)

    def stamp(self, t: float, counter: int | None) -> float:
        """The stamp of the frame numbered ``counter`` and stamped ``t`` on arrival: the grid's
        time at ``counter`` once the fit holds, else ``t``."""
        if counter is None or not math.isfinite(t):
            return t
        last = self._points[-1][0] if self._points else None
        if last is not None and counter == last:
            return t
        if last is not None and counter < last:
            self._restart(f"frame {counter} numbered before frame {last} (stream restarted?)")
        if len(self._points) < LEAST_FRAMES:
            self._points.append((counter, t))
            return t
        on_grid = self._line_at(counter)
        if abs(t - on_grid) <= self.max_residual_s:
            self._off_line = 0
            self._points.append((counter, t))
            return self._line_at(counter)
        self._off_line += 1
        if self._off_line >= self.restart_after:
            self._restart(f"{self._off_line} frames in a row over {1e3 * self.max_residual_s:.1f} "
                          "ms off the grid (the camera's clock stepped?)")
            self._points.append((counter, t))
            return t
        return on_grid

    def _line_at(self, counter: int) -> float:
        """The least-squares line through the fit's points, at ``counter`` (centred sums: the
        counters and the host's seconds are large numbers whose differences matter)."""
        n = np.fromiter((p[0] for p in self._points), float, len(self._points))
        t = np.fromiter((p[1] for p in self._points), float, len(self._points))
        n_mean, t_mean = n.mean(), t.mean()
        dn = n - n_mean
        period = float(dn @ (t - t_mean)) / float(dn @ dn)
        return float(t_mean + period * (counter - n_mean))

    def _restart(self, reason: str) -> None:
        log.warning("frame stamps: %s; fitting the camera's frame grid again", reason)
        self._points.clear()
        self._off_line = 0
        self.restarts += 1

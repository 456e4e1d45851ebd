"""PX4 boot time onto the companion clock: the TIMESYNC offset estimate.

One TIMESYNC round trip: we send ``ts1 = t0`` (our clock) at ``t0``; PX4 answers with
``tc1 = τ``, its boot time when it answered; the answer reaches us at ``t2``. With the offset
``θ = t_companion - τ_px4`` and equal delays both ways, PX4 answered at our time
``(t0 + t2) / 2``, so one sample is

    θ_k = (t0 + t2) / 2 - τ,        |θ_k - θ| <= rtt / 2,   rtt = t2 - t0,

the NTP midpoint estimate; whatever the delays, the error is bounded by half the round trip.

The filter (after PX4's own ``Timesync.cpp``: low-RTT samples only, a reset after consecutive
far-off samples):

1. a sample whose round trip exceeds :data:`MAX_RTT_S` is discarded (its error bound is too
   loose);
2. the first accepted sample initialises ``θ``;
3. a sample more than :data:`OUTLIER_S` from ``θ`` is an outlier and discarded, so a one-off
   bad sample leaves the estimate unchanged; after :data:`RESET_AFTER_OUTLIERS` consecutive
   outliers the other side's clock has jumped (PX4 rebooted) and ``θ`` restarts from the
   latest sample;
4. otherwise ``θ += g (θ_k - θ)`` with gain ``g = max(1/n, MIN_GAIN)`` for the ``n``-th
   sample in a row: the plain mean of the first samples, then an exponential average with a
   time constant of ``1 / (MIN_GAIN * rate)`` (2 s at 10 Hz), which follows the slow drift
   between the two oscillators (tens of ppm, so well under a millisecond of lag).
"""

from __future__ import annotations

import math

#: Round trips longer than this give samples too loose to use (their error may be 10 ms).
MAX_RTT_S = 0.02
#: A sample this far from the estimate is an outlier (twice the worst accepted error bound).
OUTLIER_S = 0.01
#: This many outliers in a row mean the remote clock jumped: restart from the latest sample.
RESET_AFTER_OUTLIERS = 5
#: The gain the filter settles to (exponential average over about 20 samples).
MIN_GAIN = 0.05


class TimesyncFilter:
    """The offset ``θ = t_companion - t_px4`` (seconds) from TIMESYNC round trips."""

    def __init__(self) -> None:
        self.offset: float | None = None
        self.rtt: float | None = None
        self.accepted = 0
        self.rejected_rtt = 0
        self.outliers = 0
        self.resets = 0
        self._run = 0
        self._outliers_in_row = 0

    def reset(self) -> None:
        """Forget the estimate (the link was lost: PX4 may have rebooted)."""
        self.offset = None
        self._run = 0
        self._outliers_in_row = 0

    def add(self, t0: float, remote: float, t2: float) -> bool:
        """One round trip: sent at ``t0``, answered at ``remote`` (PX4 seconds since boot),
        received at ``t2``; whether the sample was used."""
        rtt = t2 - t0
        if not (math.isfinite(rtt) and math.isfinite(remote)) or not 0.0 <= rtt <= MAX_RTT_S:
            self.rejected_rtt += 1
            return False
        self.rtt = rtt
        sample = 0.5 * (t0 + t2) - remote
        if self.offset is not None and abs(sample - self.offset) > OUTLIER_S:
            return self._outlier(sample)
        self._outliers_in_row = 0
        self._run += 1
        if self.offset is None:
            self.offset = sample
        else:
            self.offset += max(1.0 / self._run, MIN_GAIN) * (sample - self.offset)
        self.accepted += 1
        return True

    def _outlier(self, sample: float) -> bool:
        self.outliers += 1
        self._outliers_in_row += 1
        if self._outliers_in_row < RESET_AFTER_OUTLIERS:
            return False
        self.resets += 1
        self.offset, self._run, self._outliers_in_row = sample, 1, 0
        self.accepted += 1
        return True

    def to_local(self, remote: float) -> float | None:
        """PX4 boot time (s) on the companion clock; None without an estimate."""
        return None if self.offset is None else remote + self.offset

    def to_remote(self, local: float) -> float | None:
        """Companion time as PX4 boot time (s); None without an estimate."""
        return None if self.offset is None else local - self.offset

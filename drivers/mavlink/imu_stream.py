"""HIGHRES_IMU messages as :class:`autonomy.messages.ImuSample` on the companion clock.

PX4 stamps a HIGHRES_IMU with the time its sample was taken, at the END of the interval the
sensor integrated; our samples hold over ``[t, t_next)`` from their stamp (zero-order hold, the
preintegration's convention). So message ``k`` (PX4 time ``τ_k``) becomes the sample

    ImuSample(t = τ_{k-1} + θ, gyro = frd_to_flu(gyro_k), accel = frd_to_flu(accel_k),
              pressure_pa = the barometer's pressure of message k, if new),

covering ``[τ_{k-1}, τ_k)`` mapped by the TIMESYNC offset ``θ``. PX4 puts the air data it
published since its last message into message ``k``, which closes the interval. The first
message of a chain only starts it. A chain restarts (its message starting the new chain, not
emitted) after

- a gap longer than :data:`GAP_PERIODS` typical periods (the median of recent intervals, and
  never less than that many periods of the requested rate): the previous sample does not
  cover the lost messages;
- PX4 time not increasing (a reordered or repeated datagram, or a PX4 reboot), or a mapped
  time not after the last one emitted (the offset estimate jumped): counted as ``backwards``;
- non-finite values (``invalid``), or no offset estimate yet (``no_time``).

``abs_pressure`` is in hPa, as MAVLink defines it and PX4 fills it since 2023
(``HIGHRES_IMU.hpp``: ``air_data.baro_pressure_pa * 0.01f``); earlier PX4 sent pascals
(``msg.abs_pressure = air_data.baro_pressure_pa``). A barometer's pressures in the two units
are a hundred times apart, so its size says which (:func:`pressure_pa`). A pressure no
barometer reads in either (a sensor fault) is left out of its sample, counted as
``bad_pressure``; the sample itself is kept.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from statistics import median

import numpy as np

from autonomy.messages import PRESSURE_RANGE_PA, ImuSample
from drivers.mavlink.frames import frd_to_flu

#: A gap longer than this many typical periods breaks the chain of samples.
GAP_PERIODS = 3.0
#: Recent intervals whose median is the typical period.
INTERVAL_HISTORY = 21
#: HIGHRES_IMU.fields_updated's abs_pressure bit: PX4 sets it in the first message after it
#: published air data (src/modules/mavlink/streams/HIGHRES_IMU.hpp).
ABS_PRESSURE_UPDATED = 1 << 9


def updated_pressure(fields_updated: int, abs_pressure: float) -> float | None:
    """A HIGHRES_IMU's ``abs_pressure`` when the message marks it new, else None."""
    return float(abs_pressure) if fields_updated & ABS_PRESSURE_UPDATED else None


def pressure_pa(abs_pressure: float) -> float | None:
    """HIGHRES_IMU's ``abs_pressure`` in pascals, read as hPa or as Pa by its size (module
    docstring); None for one no barometer reads in either."""
    low, high = PRESSURE_RANGE_PA
    for scale in (100.0, 1.0):
        if low <= abs_pressure * scale <= high:  # NaN fails both
            return abs_pressure * scale
    return None


class ImuStamper:
    """Turns PX4's HIGHRES_IMU stream into zero-order-hold samples; ``counts`` says what was
    dropped and why (``first``, ``gap``, ``backwards``, ``invalid``, ``no_time``,
    ``bad_pressure``: module docstring)."""

    def __init__(self, nominal_rate_hz: float):
        self.nominal_period = 1.0 / nominal_rate_hz
        self.counts: Counter = Counter()
        self._previous: float | None = None
        self._last_emitted = -math.inf
        self._intervals: deque[float] = deque(maxlen=INTERVAL_HISTORY)

    def restart(self) -> None:
        """Forget the chain (after a link loss); the next message starts a new one."""
        self._previous = None
        self._intervals.clear()

    @property
    def max_gap(self) -> float:
        """The longest interval held by one sample, seconds."""
        typical = median(self._intervals) if self._intervals else self.nominal_period
        return GAP_PERIODS * max(typical, self.nominal_period)

    def push(self, remote_t: float, gyro_FRD, accel_FRD, offset: float | None,
             abs_pressure: float | None = None) -> ImuSample | None:
        """One HIGHRES_IMU (PX4 time in seconds, FRD vectors, its new barometer pressure or
        None: :func:`updated_pressure`) with the offset estimate ``θ``; the sample it
        completes, or None."""
        gyro, accel = np.asarray(gyro_FRD, dtype=float), np.asarray(accel_FRD, dtype=float)
        pressure = self._pressure(abs_pressure)
        reason = self._drop_reason(remote_t, gyro, accel, offset)
        previous = self._previous
        self._previous = remote_t if math.isfinite(remote_t) else None
        if reason is not None:
            self.counts[reason] += 1
            return None
        self._intervals.append(remote_t - previous)
        self._last_emitted = previous + offset
        return ImuSample(self._last_emitted, frd_to_flu(gyro), frd_to_flu(accel), pressure)

    def _pressure(self, abs_pressure: float | None) -> float | None:
        if abs_pressure is None:
            return None
        pressure = pressure_pa(abs_pressure)
        if pressure is None:
            self.counts["bad_pressure"] += 1
        return pressure

    def _drop_reason(self, remote_t, gyro, accel, offset) -> str | None:
        if not (math.isfinite(remote_t) and np.isfinite(gyro).all()
                and np.isfinite(accel).all()):
            return "invalid"
        if offset is None:
            return "no_time"
        if self._previous is None:
            return "first"
        interval = remote_t - self._previous
        if interval <= 0.0 or self._previous + offset <= self._last_emitted:
            return "backwards"
        if interval > self.max_gap:
            self._intervals.append(interval)
            return "gap"
        return None

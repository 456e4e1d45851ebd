"""The barometer: a height the accelerometer cannot give, so the window stays level.

Flying straight, an accelerometer cannot tell a tilt from its bias: a VINS that holds its pitch
a degree off through a cruise reckons the camera's forward motion as a climb, 3 cm/s at 2 m/s,
that the vehicle does not make (docs/vins.md, "The height error is the tilt's"). Every PX4
flight controller has a barometer, and its pressure reaches the companion in HIGHRES_IMU
(:class:`autonomy.messages.ImuSample` ``pressure_pa``). Its height is relative (the weather,
the sensor's offset and the room's air move it), so the smoother reads it as a height with a
slowly moving offset, a variable of its own on every keyframe ``k``:

    z_k = h(p_k) - b_k + n,      n ~ N(0, sigma^2)      (GTSAM's ``BarometricFactor``)
    b_k - b_i ~ N(0, q^2 (t_k - t_i))                  (``BetweenFactorDouble``, i = k - 1)

with ``z_k`` the body's height in the VINS world (z up), ``h`` GTSAM's ISA height of a pressure
(``BarometricFactor::heightOut``; only its differences matter, a metre per 12 Pa near sea
level), ``sigma`` the option ``barometer_sigma_m`` and ``q`` ``barometer_drift_m_per_sqrt_s``.
The offset's chain starts, with a wide prior (:data:`OFFSET_PRIOR_SIGMA_M`) at the value the
first pressure gives, on the first keyframe of a smoother that has one (the estimator gives
none below ``barometer_min_height_m``, in the rotors' ground effect): the height stays the
VINS's own, the barometer holds only its changes. The gauge hold then leaves the height to
it (:mod:`autonomy.vins.backend`, ``HOLD_BAROMETER_HEIGHT_SIGMA``). A keyframe takes at most
one sample, the one nearest its time within :data:`MATCH_S`, and a sample serves one keyframe
(:class:`PressureHistory`): keyframes come every 45-100 ms, PX4's barometer every 50 ms, and a
sample read twice would count its noise twice. A retimed window (:mod:`autonomy.vins.estimator`)
keeps its pressures as matched: a few milliseconds move the height less than a millimetre.

A step of pressure that is not a climb (a door, a fan, a change of room: tens of pascals, metres
of ISA height, in a moment) would drag the height with it, the offset's walk allowing it
centimetres a keyframe. A sample whose height lies further than :data:`STEP_M` from the
keyframe's predicted height and the offset's estimate is taken as such a step: the offset's
link to the keyframe before is made as wide as its starting prior, so the offset takes the step
and the height keeps the IMU's (``steps`` counts them).
"""

from __future__ import annotations

import math
from collections import deque

import gtsam

from autonomy.messages import PRESSURE_RANGE_PA

#: The offset's prior where its chain starts, metres: wide, so that the height stays the
#: VINS's and the barometer holds only its changes.
OFFSET_PRIOR_SIGMA_M = 10.0
#: A sample further than this from a keyframe's time is not its height, seconds.
MATCH_S = 0.05
#: Samples kept waiting for a keyframe: 12 s of PX4's 20 Hz (on the ground before the
#: go, no keyframe takes them).
HISTORY_LENGTH = 240
#: A sample this far from the keyframe's predicted height and offset is a step of pressure,
#: not a climb, metres: five times the simulator's barometer noise (0.17 m) and more than a
#: keyframe's climb can be mispredicted by the IMU over 0.1 s.
STEP_M = 1.0


def usable_pressure(pressure_pa) -> float | None:
    """``pressure_pa`` as a float, or None where it is no pressure a barometer reads (not a
    number, or outside ``PRESSURE_RANGE_PA``: a recording's damaged record)."""
    try:
        pressure = float(pressure_pa)
    except (TypeError, ValueError):
        return None
    low, high = PRESSURE_RANGE_PA
    return pressure if low <= pressure <= high else None


class PressureHistory:
    """Barometer samples in time order, each given to at most one keyframe (module
    docstring)."""

    def __init__(self) -> None:
        self._samples: deque[tuple[float, float]] = deque(maxlen=HISTORY_LENGTH)

    def __len__(self) -> int:
        return len(self._samples)

    def add(self, t: float, pressure_pa: float) -> None:
        self._samples.append((float(t), float(pressure_pa)))

    def take(self, t: float) -> float | None:
        """The pressure of the unused sample nearest ``t`` within :data:`MATCH_S` (Pa), or
        None; that sample and every one before it are used up."""
        samples = self._samples
        while samples and samples[0][0] < t - MATCH_S:
            samples.popleft()
        if not samples or samples[0][0] > t + MATCH_S:
            return None
        # in time order, the distance to t falls to its least and rises again
        while len(samples) > 1 and abs(samples[1][0] - t) < abs(samples[0][0] - t):
            samples.popleft()
        return samples.popleft()[1]


def offset_key(k: int) -> int:
    """Keyframe ``k``'s barometer offset's key, ``P(k)``."""
    return gtsam.symbol("p", k)


class BarometerChain:
    """The offset variables and barometer factors of one smoother (module docstring)."""

    def __init__(self, sigma_m: float, drift_m_per_sqrt_s: float):
        self._height_noise = gtsam.noiseModel.Isotropic.Sigma(1, sigma_m)
        self._drift = drift_m_per_sqrt_s
        self._first: int | None = None
        self._last: tuple[int, float] | None = None
        self.offset: float | None = None  # the newest keyframe's offset's estimate, metres
        self.steps = 0  # samples taken as steps of pressure (module docstring)

    def restart(self) -> None:
        """A new smoother: the chain starts again at its first keyframe with a pressure."""
        self._first = self._last = None

    def keys(self, k: int) -> tuple[int, ...]:
        """Keyframe ``k``'s offset key, if it has one."""
        return () if self._first is None or k < self._first else (offset_key(k),)

    def add(self, k: int, t: float, height_m: float, pressure_pa: float | None,
            graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """Keyframe ``k`` at ``t``, its height predicted at ``height_m``: its offset and
        factors into ``graph`` and ``values`` (none before the chain's first pressure)."""
        if self._first is None:
            if pressure_pa is None:
                return
            self._first = k
            self.offset = barometric_height(pressure_pa) - height_m
            graph.add(gtsam.PriorFactorDouble(offset_key(k), self.offset,
                                              gtsam.noiseModel.Isotropic.Sigma(
                                                  1, OFFSET_PRIOR_SIGMA_M)))
            values.insert(offset_key(k), self.offset)
        else:
            i, t_i = self._last
            walk = self._drift * math.sqrt(max(t - t_i, 0.0))
            if pressure_pa is not None and abs(self._innovation(height_m, pressure_pa)) > STEP_M:
                self.steps += 1
                self.offset = barometric_height(pressure_pa) - height_m
                walk = OFFSET_PRIOR_SIGMA_M
            values.insert(offset_key(k), self.offset)
            graph.add(gtsam.BetweenFactorDouble(offset_key(i), offset_key(k), 0.0,
                                                gtsam.noiseModel.Isotropic.Sigma(
                                                    1, max(walk, 1e-6))))
        if pressure_pa is not None:
            graph.add(gtsam.BarometricFactor(gtsam.symbol("x", k), offset_key(k),
                                             pressure_pa * 1e-3, self._height_noise))
        self._last = (k, t)

    def _innovation(self, height_m: float, pressure_pa: float) -> float:
        """How far the pressure's height lies from the predicted height and offset, metres."""
        return barometric_height(pressure_pa) - height_m - self.offset

    def read(self, k: int, estimate: gtsam.Values) -> None:
        """The offset's estimate at the newest keyframe ``k``."""
        if self.keys(k):
            self.offset = float(estimate.atDouble(offset_key(k)))


def barometric_height(pressure_pa: float) -> float:
    """GTSAM's ISA height of ``pressure_pa`` (``BarometricFactor::heightOut``), metres."""
    return float(_HEIGHT_READER.heightOut(pressure_pa * 1e-3))


#: Any BarometricFactor: ``heightOut`` is a method, though it reads only its argument.
_HEIGHT_READER = gtsam.BarometricFactor(0, 1, 101.325, gtsam.noiseModel.Unit.Create(1))

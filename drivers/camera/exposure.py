"""Auto-exposure with a limit on the exposure time: one control law for the camera drivers that
run their own and for the simulated sensor that models them.

Why a limit. The feature tracker follows corners between frames; a pixel moving at ``u'``
px/s smears over ``u' E`` pixels in an exposure ``E``. A camera's own auto-exposure lengthens
``E`` up to a frame period (33 ms at 30 fps) before it raises gain, so in a dim tunnel a
1 rad/s turn smears corners over ten pixels and more. Above the limit the law raises gain
instead: a noisier image, but a sharp one. An OAK's firmware takes the limit itself
(depthai's ``CameraControl.setAutoExposureLimit``, depthai-core PR 926); a RealSense D4xx's
colour sensor has none (realsense-ros issue 2798: the limit exists for the stereo module
only), so its driver runs this law on the host, setting exposure and gain by hand
(librealsense issue 2104: "you can manually control exposure and gain in software").

The law is the one the msckf_vio authors describe (msckf_vio issue 41): after each frame the
product of exposure time and gain moves towards the target mean level,

    (E G)' = E G (target / mean)^rate,   0 < rate <= 1,

clipped to what the sensor can do, then split exposure first (up to the limit), gain for the
rest. ``rate < 1`` damps the step, since a camera applies a new setting some frames after the
one it was computed from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from autonomy.options import OptionError

#: Pixel stride of the brightness measurement (msckf_vio meters every 16th pixel; every 8th
#: keeps a thin bright structure from being missed at 640x480).
METERING_STRIDE = 8
#: The mean image level the law aims at, share of full scale, and its damping exponent: the
#: values the simulated camera models (``[sim_camera] exposure_target``, ``exposure_rate``),
#: assumptions (docs/simulator.md).
TARGET_LEVEL = 0.4
STEP_RATE = 0.5
#: The darkest mean level the law divides by: a black frame (lens cap, a dark tunnel with the
#: lights off) steps the exposure up by a bounded factor instead of to infinity.
DARKEST_MEAN = 1e-3


@dataclass(frozen=True)
class Exposure:
    """One frame's exposure time (s) and gain (a multiple of the lowest gain)."""

    time_s: float
    gain: float


@dataclass(frozen=True)
class ExposureLaw:
    """The control law (module docstring) within a sensor's limits: exposure time from
    ``min_s`` to ``max_s`` (the limit), gain from 1 to ``gain_max``."""

    target: float
    rate: float
    min_s: float
    max_s: float
    gain_max: float

    def __post_init__(self) -> None:
        if not 0.0 < self.target < 1.0:
            raise ValueError(f"target must be a share of full scale in (0, 1), got {self.target}")
        if not 0.0 < self.rate <= 1.0:
            raise ValueError(f"rate must be in (0, 1], got {self.rate}")
        if not 0.0 < self.min_s <= self.max_s:
            raise ValueError(f"exposure limits must satisfy 0 < min <= max, got {self.min_s} "
                             f"and {self.max_s} s")
        if not self.gain_max >= 1.0:
            raise ValueError(f"gain_max must be at least 1, got {self.gain_max}")

    def step(self, product: float, measured_mean: float) -> float:
        """The next exposure-gain product after a frame taken at ``product`` (seconds x gain)
        measured ``measured_mean`` (share of full scale)."""
        factor = (self.target / max(measured_mean, DARKEST_MEAN)) ** self.rate
        return self.clip(product * factor)

    def clip(self, product: float) -> float:
        """``product`` within what the sensor can do."""
        return float(np.clip(product, self.min_s, self.max_s * self.gain_max))

    def split(self, product: float) -> Exposure:
        """Exposure time first, up to the limit, then gain."""
        time_s = float(np.clip(product, self.min_s, self.max_s))
        return Exposure(time_s, float(np.clip(product / time_s, 1.0, self.gain_max)))


def mean_level(image: np.ndarray) -> float:
    """The metered brightness of a uint8 image: the mean of every :data:`METERING_STRIDE`-th
    pixel in each direction, as a share of full scale."""
    return float(image[::METERING_STRIDE, ::METERING_STRIDE].mean()) / 255.0


# A driver's exposure options (``[realsense]``, ``[oak]``) share three fields:
# ``auto_exposure``, ``auto_exposure_limit_us`` (0: none) and ``exposure_us`` (manual).

def check_limit(options) -> None:
    """OptionError for an auto-exposure limit set on a manual exposure."""
    if options.auto_exposure_limit_us and not options.auto_exposure:
        raise OptionError("auto_exposure_limit_us", "limits the auto-exposure: set "
                          "auto_exposure = true, or 0 for a manual exposure")


def longest_us(options) -> int | None:
    """The longest a driver's frame is exposed, us: the manual exposure, or the
    auto-exposure's limit; None when the camera's own auto-exposure may take a whole frame
    (no limit)."""
    if options.auto_exposure:
        return options.auto_exposure_limit_us or None
    return options.exposure_us

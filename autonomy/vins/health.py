"""The estimator's health: the numbers a pilot would watch, and one state the application acts on.

- ``INITIALISING``: no static initialisation yet (the vehicle must stand still on the ground).
- ``LOST``: no usable estimate: the IMU went silent, tracking starved (too few features) for
  longer than ``lost_after_s``, or the smoother refused a keyframe even after a rebuild. The
  estimator re-initialises in flight as soon as tracking returns; the application should stop.
- ``DEGRADED``: an estimate, but a weak one: few features or landmarks, a recent reset, or a
  slow update.
- ``OK``: everything in bounds.

``settling``: within ``degraded_after_reset_s`` of a reset, the new smoother's state is its
prior (an IMU propagation, in flight across whatever lost the old one) more than its
measurements: an estimate to navigate on carefully, but not one for PX4 to fuse.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from autonomy.vins.options import VinsOptions


class HealthState(enum.Enum):
    INITIALISING = "initialising"
    OK = "ok"
    DEGRADED = "degraded"
    LOST = "lost"


@dataclass(frozen=True)
class Health:
    """The state, why it is that state, and the figures it was judged on.

    ``parallax_px``: mean feature displacement since the last keyframe; ``speed`` m/s; biases
    as vector norms (rad/s, m/s^2); ``update_ms``: the last back-end update's duration as the
    caller measured it (None when not reported).
    """

    state: HealthState
    reason: str
    tracked: int = 0
    landmarks: int = 0
    parallax_px: float = 0.0
    speed: float = 0.0
    gyro_bias: float = 0.0
    accel_bias: float = 0.0
    resets: int = 0
    update_ms: float | None = None
    settling: bool = False


@dataclass(frozen=True)
class HealthInputs:
    """What :func:`assess` judges; ``starved_s`` is how long tracking has been below
    ``min_tracked_lost``, ``since_reset_s`` how long since the last reset."""

    tracked: int
    landmarks: int
    parallax_px: float
    speed: float
    gyro_bias: float
    accel_bias: float
    resets: int
    update_ms: float | None
    moved: bool
    starved_s: float
    since_reset_s: float


def assess(inputs: HealthInputs, options: VinsOptions) -> Health:
    """The health of an initialised estimator that has an estimate (module docstring)."""
    o = options
    settling = inputs.since_reset_s < o.degraded_after_reset_s
    if inputs.starved_s >= o.lost_after_s:
        return _health(HealthState.LOST, f"only {inputs.tracked} features tracked for "
                       f"{inputs.starved_s:.2f} s", inputs, settling)
    problems = []
    if inputs.tracked < o.min_tracked_ok:
        problems.append(f"{inputs.tracked} features tracked (< {o.min_tracked_ok})")
    if inputs.moved and inputs.landmarks < o.min_landmarks_ok:
        problems.append(f"{inputs.landmarks} landmarks (< {o.min_landmarks_ok})")
    if settling:
        problems.append(f"reset {inputs.since_reset_s:.2f} s ago")
    if inputs.update_ms is not None and inputs.update_ms > o.max_update_ms:
        problems.append(f"update took {inputs.update_ms:.0f} ms (> {o.max_update_ms:g})")
    if problems:
        return _health(HealthState.DEGRADED, "; ".join(problems), inputs, settling)
    return _health(HealthState.OK, "", inputs, settling)


def _health(state: HealthState, reason: str, i: HealthInputs, settling: bool) -> Health:
    return Health(state, reason, i.tracked, i.landmarks, i.parallax_px, i.speed, i.gyro_bias,
                  i.accel_bias, i.resets, i.update_ms, settling)

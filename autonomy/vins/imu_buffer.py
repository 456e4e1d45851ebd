"""IMU samples held for preintegration and forward propagation.

A sample at ``t_k`` holds over ``[t_k, t_{k+1})`` (zero-order hold); the newest holds until the
time asked for. :func:`propagate` integrates the navigation state through such pieces
(:class:`Propagator` incrementally) with the same model the preintegration uses (Forster et
al., TRO 2017, eq. 31 with constant measurements over each piece):

    R <- R Exp((w - b_g) dt)
    v <- v + (g + R (a - b_a)) dt
    p <- p + v dt + 1/2 (g + R (a - b_a)) dt^2

with ``g = (0, 0, -GRAVITY)`` in the gravity-aligned world (z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import GRAVITY, so3_exp
from autonomy.messages import ImuSample


@dataclass(frozen=True)
class NavState:
    """Body orientation ``R_W_B``, position and velocity in the world frame, at time ``t``."""

    t: float
    R_W_B: np.ndarray
    position: np.ndarray
    velocity: np.ndarray


@dataclass(frozen=True)
class ImuPieces:
    """Constant-measurement pieces covering an interval: ``gyro``/``accel`` (n, 3), ``dt`` (n,)."""

    gyro: np.ndarray
    accel: np.ndarray
    dt: np.ndarray


class ImuBuffer:
    """IMU samples in strictly increasing time order, trimmed from the front by the owner."""

    def __init__(self) -> None:
        self._t: list[float] = []
        self._gyro: list[np.ndarray] = []
        self._accel: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def first_time(self) -> float | None:
        return self._t[0] if self._t else None

    @property
    def last_time(self) -> float | None:
        return self._t[-1] if self._t else None

    def add(self, sample: ImuSample) -> None:
        """Append ``sample``; ValueError for a non-finite value or a time not after the last."""
        gyro = np.asarray(sample.gyro, dtype=float).reshape(-1)
        accel = np.asarray(sample.accel, dtype=float).reshape(-1)
        if gyro.shape != (3,) or accel.shape != (3,):
            raise ValueError(f"IMU sample at t={sample.t}: gyro and accel must have 3 values, "
                             f"got {gyro.shape[0]} and {accel.shape[0]}")
        if not (math.isfinite(sample.t) and np.isfinite(gyro).all() and np.isfinite(accel).all()):
            raise ValueError(f"IMU sample at t={sample.t}: contains NaN or infinite values")
        if self._t and sample.t <= self._t[-1]:
            raise ValueError(f"IMU sample at t={sample.t} is not after the previous one "
                             f"(t={self._t[-1]})")
        self._t.append(float(sample.t))
        self._gyro.append(gyro)
        self._accel.append(accel)

    def discard_before(self, t: float) -> None:
        """Drop samples no longer needed for times at or after ``t`` (the one holding at ``t``
        is kept)."""
        keep_from = max(0, int(np.searchsorted(self._t, t, side="right")) - 1)
        if keep_from:
            del self._t[:keep_from], self._gyro[:keep_from], self._accel[:keep_from]

    def correct_accel(self, correct) -> None:
        """Every buffered specific force replaced by ``correct(accel)``."""
        self._accel = [np.asarray(correct(accel), dtype=float) for accel in self._accel]

    @property
    def last_gyro(self) -> np.ndarray | None:
        return self._gyro[-1] if self._gyro else None

    def window(self, t_from: float, t_to: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times, gyro and accel of the samples from ``t_from`` to ``t_to``, both included."""
        start = int(np.searchsorted(self._t, t_from, side="left"))
        stop = int(np.searchsorted(self._t, t_to, side="right"))
        t = np.asarray(self._t[start:stop], dtype=float)
        if len(t) == 0:
            return t, np.zeros((0, 3)), np.zeros((0, 3))
        return t, np.stack(self._gyro[start:stop]), np.stack(self._accel[start:stop])

    def pieces(self, t0: float, t1: float) -> ImuPieces:
        """Zero-order-hold pieces covering ``[t0, t1]``; ValueError when no sample holds at
        ``t0`` (the buffer starts later, or is empty)."""
        if t1 < t0:
            raise ValueError(f"IMU interval ends before it starts ({t0} .. {t1})")
        if not self._t or self._t[0] > t0:
            raise ValueError(f"no IMU sample holds at t={t0} (buffer starts at "
                             f"{self.first_time})")
        times = np.asarray(self._t)
        first = int(np.searchsorted(times, t0, side="right")) - 1
        last = max(first, int(np.searchsorted(times, t1, side="left")) - 1)
        starts = times[first:last + 1].copy()
        starts[0] = t0
        ends = np.append(times[first + 1:last + 1], t1)
        keep = ends > starts
        return ImuPieces(np.stack(self._gyro[first:last + 1])[keep],
                         np.stack(self._accel[first:last + 1])[keep], (ends - starts)[keep])


def propagate(state: NavState, pieces: ImuPieces, bias_g: np.ndarray, bias_a: np.ndarray,
              gravity: float = GRAVITY) -> NavState:
    """``state`` carried through ``pieces`` (see the module docstring for the model)."""
    R, p, v = _integrate((state.R_W_B, state.position, state.velocity), pieces.gyro - bias_g,
                         pieces.accel - bias_a, pieces.dt, gravity)
    return NavState(state.t + float(pieces.dt.sum()), R, p, v)


def _integrate(Rpv: tuple, gyro: np.ndarray, accel: np.ndarray, dt: np.ndarray,
               gravity: float) -> tuple:
    """``(R, p, v)`` through bias-corrected pieces, one after the other."""
    R, p, v = Rpv
    g = np.array([0.0, 0.0, -gravity])
    for w, a, step in zip(gyro, accel, dt):
        acc = g + R @ a
        p = p + v * step + 0.5 * acc * step * step
        v = v + acc * step
        R = R @ so3_exp(w * step)
    return R, p, v


class Propagator:
    """:func:`propagate` from one start state again and again, to ever later times, without
    integrating the same samples twice.

    The odometry asks for the state at the newest IMU sample tens of times a second, each time
    from the same keyframe state through every sample since (hundreds, and growing until the
    next keyframe). The pieces up to the last are whole sample intervals that the next call
    shares, so their result is kept and the next call goes on from it. The arithmetic is the
    same, piece after piece, so the result is bit for bit :func:`propagate`'s.
    """

    def __init__(self, gravity: float = GRAVITY):
        self.gravity = gravity
        self._start: tuple | None = None  # (state, bias_g, bias_a) the kept prefix starts at
        self._prefix: ImuPieces | None = None  # whole pieces integrated
        self._Rpv: tuple | None = None  # the state after them

    def propagate(self, state: NavState, pieces: ImuPieces, bias_g: np.ndarray,
                  bias_a: np.ndarray) -> NavState:
        """Exactly ``propagate(state, pieces, bias_g, bias_a)``."""
        done = self._resumable(state, pieces, bias_g, bias_a)
        if done == 0:
            self._start, self._Rpv = (state, bias_g, bias_a), (state.R_W_B, state.position,
                                                               state.velocity)
        whole = len(pieces.dt) - 1  # the last piece may end inside a sample's interval
        if whole > done:
            self._Rpv = _integrate(self._Rpv, pieces.gyro[done:whole] - bias_g,
                                   pieces.accel[done:whole] - bias_a, pieces.dt[done:whole],
                                   self.gravity)
            done = whole
        self._prefix = ImuPieces(pieces.gyro[:done], pieces.accel[:done], pieces.dt[:done])
        R, p, v = _integrate(self._Rpv, pieces.gyro[done:] - bias_g,
                             pieces.accel[done:] - bias_a, pieces.dt[done:], self.gravity)
        return NavState(state.t + float(pieces.dt.sum()), R, p, v)

    def _resumable(self, state: NavState, pieces: ImuPieces, bias_g, bias_a) -> int:
        """How many leading pieces were integrated already from this very start (0: none)."""
        if self._start is None or self._prefix is None:
            return 0
        start, kept_g, kept_a = self._start
        k = len(self._prefix.dt)
        same_start = start is state and kept_g is bias_g and kept_a is bias_a
        if not same_start or len(pieces.dt) <= k:
            return 0
        prefix = self._prefix
        if not (np.array_equal(pieces.dt[:k], prefix.dt)
                and np.array_equal(pieces.gyro[:k], prefix.gyro)
                and np.array_equal(pieces.accel[:k], prefix.accel)):
            return 0
        return k

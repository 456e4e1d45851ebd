"""Recordings with a hidden camera-IMU time offset, and the VINS run over them (issue 23).

:func:`shift_recording` makes a copy of a EuRoC/ASL recording whose camera (and depth) stamps
are ``td`` seconds late, as an unsynchronised camera's are: the images and the IMU stay as they
were, only ``cam0/data.csv`` and ``depth0/data.csv`` change (the reader takes the file names from
them). :func:`run_vins_offset` feeds a recording to the VINS as the flight application does,
with the IMU fed up to the frame's exposure time when that lies after its stamp (a negative
offset), and scores each pose at the time the VINS says it holds for.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from autonomy.geometry import quat_to_rot, rot_z, yaw_of
from autonomy.trajectory import ate_rmse, interpolate_poses, path_length
from autonomy.vins import Vins, VinsOptions
from companion.tools.eval.vio import ImuFeed, read_vio_dataset, vio_frames


def shift_recording(source: Path, target: Path, td: float) -> Path:
    """``target``: ``source`` with every camera and depth stamp ``td`` seconds later (images,
    IMU and ground truth shared through symbolic links)."""
    source, target = Path(source), Path(target)
    shift_ns = int(round(td * 1e9))
    for name in ("imu0", "state_groundtruth_estimate0"):
        (target / "mav0").mkdir(parents=True, exist_ok=True)
        os.symlink((source / "mav0" / name).resolve(), target / "mav0" / name)
    for name in ("cam0", "depth0"):
        folder = source / "mav0" / name
        if not folder.is_dir():
            continue
        out = target / "mav0" / name
        out.mkdir(parents=True)
        os.symlink((folder / "data").resolve(), out / "data")
        shutil.copy(folder / "sensor.yaml", out / "sensor.yaml")
        lines = []
        for line in (folder / "data.csv").read_text(encoding="ascii").splitlines():
            if line and not line.startswith("#"):
                stamp, rest = line.split(",", 1)
                line = f"{int(stamp) + shift_ns},{rest}"
            lines.append(line)
        (out / "data.csv").write_text("\n".join(lines) + "\n", encoding="ascii")
    return target


@dataclass
class OffsetRun:
    """Per frame: ``stamps`` (as recorded), the ``exposures`` the VINS used, its offset
    ``offsets`` and their ``sigmas`` (NaN when none), ``positions`` and ``velocities`` (None
    without a pose);
    ``backend_ms``: the time :meth:`Vins.add_frame` took on each keyframe, ``other_ms`` on
    each other frame; ``offset_ms``: per frame, ``(keyframe, ms)`` spent in the time-offset
    estimator's frame work during it; ``offset_imu_s``: total time in its IMU work;
    ``windows``: every window's own solution, ``(stamp, offset, sigma)`` in seconds;
    ``window_s``: per frame, the time the smoother's window spans, oldest keyframe to newest."""

    stamps: list = field(default_factory=list)
    exposures: list = field(default_factory=list)
    offsets: list = field(default_factory=list)
    sigmas: list = field(default_factory=list)
    positions: list = field(default_factory=list)
    velocities: list = field(default_factory=list)
    health: list = field(default_factory=list)
    backend_ms: list = field(default_factory=list)
    other_ms: list = field(default_factory=list)
    offset_ms: list = field(default_factory=list)
    offset_imu_s: float = 0.0
    imu_samples: int = 0
    windows: list = field(default_factory=list)
    window_s: list = field(default_factory=list)
    resets: int = 0
    vins: Vins | None = None
    data: object = None

    def ate(self, *, at_stamps: bool = False) -> tuple[float, float]:
        """ATE (SE(3)-aligned RMSE, m) and distance of the posed frames, each pose compared
        with the truth at its exposure time (or, ``at_stamps``, at the frame's stamp)."""
        times = self.stamps if at_stamps else self.exposures
        chosen = [k for k, p in enumerate(self.positions) if p is not None]
        truth_t, truth = self.truth()
        chosen = [k for k in chosen if truth_t[0] <= times[k] <= truth_t[-1]]
        true_p, _ = interpolate_poses([times[k] for k in chosen], truth_t, truth.position,
                                      truth.q_W_B)
        estimated = np.array([self.positions[k] for k in chosen])
        return ate_rmse(estimated, true_p), path_length(true_p)

    def position_errors(self, until: float = np.inf) -> np.ndarray:
        """Each pose (up to ``until``) against the truth at its exposure time, in the VINS
        world (the start at the origin, zero initial yaw), metres."""
        truth_t, truth = self.truth()
        R_yaw = rot_z(-yaw_of(quat_to_rot(truth.q_W_B[0])))
        positions = (truth.position - truth.position[0]) @ R_yaw.T
        errors = [np.linalg.norm(p - [np.interp(t, truth_t, positions[:, i]) for i in range(3)])
                  for t, p in zip(self.exposures, self.positions) if p is not None and t <= until]
        return np.array(errors)

    def truth(self):
        data = self.data
        return (np.asarray(data.truth.t_ns, np.int64) - data.imu.t_ns[0]) * 1e-9, data.truth


def run_vins_offset(root: Path, options: VinsOptions, *,
                    max_frames: int | None = None) -> OffsetRun:
    """The VINS over the recording at ``root`` (module docstring)."""
    data = read_vio_dataset(root)
    stream = data.camera
    vins = Vins(stream.camera, stream.distortion, stream.T_B_C, data.noise, options)
    run = OffsetRun(vins=vins, data=data)
    spent = _time_the_offset_estimator(vins, run)
    feed = ImuFeed(data)
    for frame in vio_frames(data, max_frames):  # as eval vio reads them
        feed.before_frame(vins, frame.t)
        tracks = vins.track(frame.image)
        start = time.perf_counter()
        update = vins.add_frame(frame.t, tracks)
        (run.backend_ms if update.keyframe else run.other_ms).append(
            1e3 * (time.perf_counter() - start))
        run.offset_ms.append((update.keyframe, 1e3 * spent[0]))
        spent[0] = 0.0
        run.stamps.append(update.t)
        run.exposures.append(update.t_exposure)
        run.offsets.append(update.time_offset.seconds)
        sigma = update.time_offset.sigma
        run.sigmas.append(np.nan if sigma is None else sigma)
        run.positions.append(None if update.T_W_B is None else update.T_W_B[:3, 3].copy())
        run.velocities.append(None if update.velocity_W is None else update.velocity_W.copy())
        run.health.append(update.health.state.name)
        window = vins.backend.window_keyframes if vins.backend.started else []
        run.window_s.append(window[-1][1] - window[0][1] if window else 0.0)
    run.resets = vins.resets
    return run


def _time_the_offset_estimator(vins: Vins, run: OffsetRun) -> list:
    """Wraps the estimator's methods (if any) to time them: returns the per-frame accumulator
    of its frame work, seconds; its IMU work goes to ``run.offset_imu_s``, and each window it
    solves to ``run.windows``."""
    spent = [0.0]
    estimator = vins._offset_estimator
    if estimator is None:
        return spent
    add_frame, add_imu, refit = estimator.add_frame, estimator.add_imu, estimator._refit

    def timed_frame(*args):
        start = time.perf_counter()
        add_frame(*args)
        spent[0] += time.perf_counter() - start

    def timed_imu(*args):
        start = time.perf_counter()
        add_imu(*args)
        run.offset_imu_s += time.perf_counter() - start
        run.imu_samples += 1

    def traced_refit(stamp):
        refit(stamp)
        run.windows.append((stamp, estimator.window_offset, estimator.window_sigma))

    estimator.add_frame, estimator.add_imu = timed_frame, timed_imu
    estimator._refit = traced_refit
    return spent


def summarise(run: OffsetRun, true_offset: float, until: float = 5.5) -> dict:
    """ATE, position errors (the largest, up to ``until`` and at the last pose), the offset's
    convergence, the longest window and the update times of ``run``, for JSON."""
    ate, distance = run.ate()
    offsets, stamps = np.array(run.offsets), np.array(run.stamps)
    error = np.abs(offsets - true_offset)
    within = [k for k in range(len(error)) if np.all(error[k:] < 0.002)]
    return {
        "ate_rmse_m": ate, "distance_m": distance, "ate_over_distance": ate / distance,
        "time_offset_ms": 1e3 * offsets[-1], "time_offset_sigma_ms": 1e3 * run.sigmas[-1],
        "time_offset_error_ms": 1e3 * (offsets[-1] - true_offset),
        "within_2ms_from_s": float(stamps[within[0]]) if within else None,
        "position_error_max_m": float(run.position_errors().max()),
        "position_error_end_m": float(run.position_errors()[-1]),
        f"position_error_max_m_until_{until:g}s": float(run.position_errors(until).max()),
        "resets": run.resets, "keyframes": len(run.backend_ms),
        "window_s_max": max(run.window_s, default=0.0),
        "keyframe_ms_median": float(np.median(run.backend_ms)),
        "keyframe_ms_p95": float(np.percentile(run.backend_ms, 95)),
        "other_frame_ms_median": float(np.median(run.other_ms)),
        "other_frame_ms_p95": float(np.percentile(run.other_ms, 95)),
        **_offset_cost(run),
        **window_statistics(run, true_offset),
    }


def window_statistics(run: OffsetRun, true_offset: float) -> dict:
    """How well the time-offset estimator's windows know the offset: over the excited ones
    (``sigma`` within the estimator's ``time_offset_max_sigma_s``, those that may become its
    target), their count, the median error (signed, ms), and the median and 95th percentile of
    ``|z| = |offset - true| / sigma`` (about 0.67 and 1.96 when the sigmas are honest)."""
    if not run.windows:
        return {}
    limit = run.vins.options.time_offset_max_sigma_s
    excited = np.array([(td, sigma) for _, td, sigma in run.windows if sigma <= limit])
    if len(excited) == 0:
        return {"windows": len(run.windows), "windows_excited": 0}
    error = excited[:, 0] - true_offset
    z = np.abs(error) / excited[:, 1]
    return {"windows": len(run.windows), "windows_excited": len(excited),
            "window_error_ms_median": 1e3 * float(np.median(error)),
            "window_z_median": float(np.median(z)),
            "window_z_p95": float(np.percentile(z, 95))}


def _offset_cost(run: OffsetRun) -> dict:
    """The time-offset estimator's own cost: on average per frame; on the frames that did its
    work (each does up to three frames' worth); the most on any keyframe; per IMU sample."""
    if run.imu_samples == 0:
        return {}
    spent = np.array([ms for _, ms in run.offset_ms])
    worked = spent[spent > 0.0]
    on_keyframes = [ms for keyframe, ms in run.offset_ms if keyframe]
    return {"offset_ms_per_frame": float(spent.mean()),
            "offset_ms_working_frame_median": float(np.median(worked)),
            "offset_ms_working_frame_p95": float(np.percentile(worked, 95)),
            "offset_ms_on_a_keyframe_max": max(on_keyframes, default=0.0),
            "offset_us_per_imu_sample": 1e6 * run.offset_imu_s / run.imu_samples}


def main(argv=None) -> None:
    """``python -m tests.time_offset_runs DATASET --td-ms 15 [--estimate] [--set vins.KEY=V]``:
    the numbers of docs/vins.md ("The camera-IMU time offset", the windows' statistics of "The
    time offset's windows and the rotors' vibration", the end errors and window spans of "The
    take-off's window kept open") for one recording, as JSON; ``--windows FILE`` writes every
    window's solution there, one JSON line each."""
    import argparse
    import json
    import tempfile

    from companion.config import ConfigError, load_config

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--td-ms", type=float, default=0.0,
                        help="shift the camera stamps by this (the hidden offset), ms")
    parser.add_argument("--true-ms", type=float, default=None,
                        help="the offset the recording already has (a realistic one), ms")
    parser.add_argument("--estimate", action="store_true", help="estimate_time_offset = true")
    parser.add_argument("--offset-ms", type=float, default=0.0,
                        help="time_offset_s: the fixed or starting offset, ms")
    parser.add_argument("--windows", type=Path, default=None, metavar="FILE",
                        help="write each window's stamp, offset and sigma (s, ms, ms) here")
    parser.add_argument("--set", action="append", default=[], metavar="vins.KEY=VALUE",
                        help="a [vins] option over the flags above, e.g. "
                             "vins.retime_window=true; repeatable")
    args = parser.parse_args(argv)
    foreign = [text for text in args.set if not text.startswith("vins.")]
    if foreign:
        parser.error(f"--set takes [vins] options only, got {', '.join(foreign)}")
    try:
        options = load_config(None, [f"vins.estimate_time_offset={str(args.estimate).lower()}",
                                     f"vins.time_offset_s={args.offset_ms * 1e-3!r}",
                                     *args.set]).vins
    except ConfigError as error:
        parser.error(str(error))
    with tempfile.TemporaryDirectory() as folder:
        root = (shift_recording(args.dataset, Path(folder) / "shifted", args.td_ms * 1e-3)
                if args.td_ms else args.dataset)
        run = run_vins_offset(root, options)
    true = args.td_ms if args.true_ms is None else args.true_ms
    if args.windows is not None:
        args.windows.write_text("".join(
            json.dumps({"stamp_s": stamp, "offset_ms": 1e3 * td, "sigma_ms": 1e3 * sigma}) + "\n"
            for stamp, td, sigma in run.windows), encoding="ascii")
    print(json.dumps({"dataset": str(args.dataset), "td_ms": args.td_ms, "estimate": args.estimate,
                      "start_offset_ms": args.offset_ms, "set": args.set,
                      **summarise(run, true * 1e-3)}))


if __name__ == "__main__":
    main()

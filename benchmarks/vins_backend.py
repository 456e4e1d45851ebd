"""Speed of the VINS back-end on one core: milliseconds per keyframe on simulated flights.

    python benchmarks/vins_backend.py [--config FILE] [--duration 20] [--seed 0]
        [--worlds mine sewer dome] [--dataset DIR] [--cache DIR] [--base KEY=VALUE ...]
        [--set KEY=VALUE ...]

Records a simulated flight per world (or uses the recording or EuRoC/ASL dataset given), pins
the process to one CPU (and OpenCV to one thread), and runs the whole VINS over it exactly as
``companion eval vio`` does. Without ``--config`` the flights are the ideal profile's and the
VINS has every option at its default; with ``--config`` (``config/sim-realistic.toml``: what the
presets fly) the flights are recorded as ``companion eval vio-table`` records them in the
config's profile, the planner's waves included, and the VINS, its front-end and its start are
the config's. The back-end time is
``Vins.add_frame`` on keyframe frames (the smoother update, landmark gate, map); the front-end
time on the same frames is the baseline of the same run. Keyframes come at 10 Hz on these
flights (``keyframe_interval_s``), with 150 tracks. The covariance time is that of one
covariance the smoother computes, the newest keyframe's pose and velocity marginal, jointly
(``SlidingWindowSmoother._released_marginal``; a cached covariance is not timed), which the
evaluation asks for at every keyframe and the odometry every ``covariance_period_s``. Both
are on the VINS worker, one after the other: ``with_covariance_ms_p95`` is the p95 of a
keyframe's time with its covariance's (the odometry's at ``covariance_period_s = 0``), and
``as_flown_ms_p95`` the p95 of a keyframe's time with the covariance added where the config's
period refreshes it (at the first keyframe, then at the first keyframe at least that period
after the last refresh; a rebuild's refresh is not counted). With
``--set`` (``[vins]`` keys, TOML
values: ``--set drag_coefficient=0.3``) each flight is also run with those options, default and
variant twice in turn (A B A B) so that the host's load falls on both alike, and both are
reported; ``--base`` settings go into both (the default is then the defaults with them: an
option that needs another, timed against that other alone). Prints one JSON object.
"""

import argparse
import json
import os
import statistics
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

from autonomy.vins.backend import SlidingWindowSmoother, covariance_due
from companion.config import Config, ConfigError, load_config
from companion.tools.eval.rescale import cached_dataset
from companion.tools.eval.vio import EvaluationError, read_vio_dataset, run_vins, score_vio
from companion.tools.eval.vio_table import TableJob
from drivers.sim.options import WORLD_NAMES


TIMINGS = ("backend_ms_median", "backend_ms_p95", "frontend_ms_median", "covariance_ms_median",
           "with_covariance_ms_p95", "as_flown_ms_p95")


@contextmanager
def timed_covariances(milliseconds: dict[float, float]):
    """Put the time of each covariance the smoother computes in ``milliseconds``, under the
    time of the keyframe it is for (one per keyframe: the smoother keeps it for that
    keyframe)."""
    original = SlidingWindowSmoother._released_marginal

    def timed(smoother, *args, **kwargs):
        start = time.perf_counter()
        result = original(smoother, *args, **kwargs)
        milliseconds[smoother.latest.t] = (time.perf_counter() - start) * 1e3
        return result

    SlidingWindowSmoother._released_marginal = timed
    try:
        yield
    finally:
        SlidingWindowSmoother._released_marginal = original


def measure(root: Path, job: TableJob) -> dict:
    data = read_vio_dataset(root)
    covariance_ms: dict[float, float] = {}
    with timed_covariances(covariance_ms):
        trace = run_vins(data, job.vins, frontend=job.frontend, static=job.static)
    score = score_vio(trace, data)
    score["covariance_ms_median"] = statistics.median(covariance_ms.values())
    score.update(keyframes_with_covariances(trace, covariance_ms, job.vins.covariance_period_s))
    timing = {key: round(score[key], 2) for key in TIMINGS}
    return {"dataset": str(root), "keyframes": score["keyframes"],
            "keyframe_rate_hz": round(score["keyframes"] / (trace.t[-1] - trace.t[0]), 2),
            **timing, "resets": score["resets"]}


def keyframes_with_covariances(trace, covariance_ms: dict[float, float],
                                period_s: float) -> dict[str, float]:
    """``with_covariance_ms_p95`` and ``as_flown_ms_p95`` (module docstring) of a run whose
    every keyframe's covariance was timed."""
    keyframe_ms = [ms for ms, key in zip(trace.backend_ms, trace.keyframe) if key]
    times = [keyframe.t for keyframe in trace.keyframes]
    if set(times) != set(covariance_ms):
        raise SystemExit("vins_backend: the covariances timed are not one per keyframe")
    with_covariance, as_flown, refreshed_t = [], [], -np.inf
    for ms, t in zip(keyframe_ms, times, strict=True):
        with_covariance.append(ms + covariance_ms[t])
        refresh = covariance_due(t - refreshed_t, period_s)
        refreshed_t = t if refresh else refreshed_t
        as_flown.append(with_covariance[-1] if refresh else ms)
    return {"with_covariance_ms_p95": float(np.percentile(with_covariance, 95)),
            "as_flown_ms_p95": float(np.percentile(as_flown, 95))}


def measure_pair(root: Path, default: TableJob, variant: TableJob | None) -> dict:
    """The ``default`` job's run; with a ``variant``, both twice in turn (A B A B), each
    timing the mean of its two runs."""
    if variant is None:
        return measure(root, default)
    runs = {"default": [], "variant": []}
    for _ in range(2):
        runs["default"].append(measure(root, default))
        runs["variant"].append(measure(root, variant))
    result = {}
    for name, pair in runs.items():
        result[name] = {**pair[0], **{key: round(statistics.fmean(r[key] for r in pair), 2)
                                      for key in TIMINGS}}
    return result


def parse_config(path: Path | None, settings: list[str], flags: str) -> Config:
    """The config at ``path`` (None: every option at its default) with the ``KEY=VALUE``
    settings given by ``flags``, each read as the config's ``--set vins.KEY=VALUE``
    (:func:`companion.config.load_config`); ValueError naming what is wrong: the setting, or
    the config file."""
    try:
        return load_config(path, [f"vins.{setting}" for setting in settings])
    except ConfigError as error:
        if not error.source.startswith("--set vins."):
            raise ValueError(f"--config {error.source}: {error.message}") from None
        raise ValueError(f"{flags} {error.source.removeprefix('--set vins.')}: "
                         f"{error.message}") from None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, help="the config whose VINS is timed on "
                        "flights of its profile (default: every option at its default, the "
                        "ideal profile)")
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--seed", type=int, default=0, help="the flights' seed")
    parser.add_argument("--worlds", nargs="+", default=list(WORLD_NAMES), choices=WORLD_NAMES)
    parser.add_argument("--dataset", type=Path, help="a recorded dataset instead of new flights")
    parser.add_argument("--cache", type=Path, help="keep the flights in this folder and reuse "
                        "them from it, as companion eval's --cache (default: recorded afresh)")
    parser.add_argument("--base", action="append", default=[], metavar="KEY=VALUE",
                        help="a [vins] option of both the default and the variant")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a [vins] option of a variant timed beside the defaults")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        cache = args.cache or Path(scratch)
        try:
            default = TableJob.of(parse_config(args.config, args.base, "--base"), cache,
                                  args.duration)
            variant = TableJob.of(parse_config(args.config, args.base + args.set,
                                               "--base/--set"),
                                  cache, args.duration) if args.set else None
        except (ValueError, EvaluationError) as error:
            parser.error(str(error))
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        cv2.setNumThreads(1)
        heading = {"cpus": 1, "config": None if args.config is None else str(args.config),
                   "base": args.base, "variant": args.set}
        if args.dataset is not None:
            print(json.dumps({**heading, "runs": [measure_pair(args.dataset, default, variant)]}))
            return
        runs = []
        for world in args.worlds:
            try:
                root = cached_dataset(default.cache, world, args.seed, default.frames,
                                      default.recording)
            except EvaluationError as error:
                raise SystemExit(f"vins_backend: {error}") from None
            runs.append({"world": world, **measure_pair(root, default, variant)})
    print(json.dumps({**heading, "duration_s": args.duration, "seed": args.seed, "runs": runs}))


if __name__ == "__main__":
    main()

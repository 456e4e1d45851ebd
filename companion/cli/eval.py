"""``companion eval``: the accuracy of the algorithms against ground truth (``vio``,
``vio-table``, ``depth``, ``rescale``, ``nav``)."""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

from companion.cli import common
from companion.config import Config


def add_commands(commands: argparse._SubParsersAction) -> None:
    from drivers.sim.truth_tracks import TRACK_SOURCES

    configured = common.configured_parser()
    group = commands.add_parser("eval", help="measure the accuracy of the algorithms",
                                description="Measure the accuracy of the algorithms against "
                                            "a dataset's ground truth.")
    actions = common.add_command_group(group)
    dataset = argparse.ArgumentParser(add_help=False, parents=[configured])
    dataset.add_argument("dataset", type=Path, metavar="DATASET",
                         help="dataset folder, the one holding mav0/")
    common.add_json_flag(dataset, instead_of="a report")
    dataset.add_argument("--max-frames", type=common.positive_int, metavar="N",
                         help="stop after N camera frames (default: all)")
    vio = actions.add_parser(
        "vio", parents=[dataset], help="score the VINS on a EuRoC dataset",
        description="Run the VINS, with the [vins], [vins_frontend] and [vins_init] options of "
                    "the config, over a EuRoC/ASL dataset (real, or recorded by 'companion sim "
                    "record') and compare it with the ground truth: trajectory error after "
                    "SE(3) alignment, scale error, landmark depth error against depth0 when the "
                    "dataset has it, the static initialisation, and the time per stage.")
    vio.add_argument("--bound", action="store_true",
                     help="also solve the smoother's own factors as a batch, causally and over "
                          "the whole flight, and report each one's error beside the "
                          "smoother's: what its window loses and what the factors allow (a "
                          "minute or so more for 40 s)")
    vio.add_argument("--tracks", choices=TRACK_SOURCES, default="tracker",
                     help="the VINS's feature tracks: the tracker's; truth, the same tracks "
                          "with each pixel the true projection of the point it was born on, to "
                          "tell the tracker's error from the estimator's on the same images and "
                          "IMU; early-error / late-error, the truth's with the tracker's error "
                          "of each track's first six frames only / gathered after them only "
                          "(a recording of the ideal profile, with depth0; docs/vins.md) "
                          "(default: %(default)s)")
    vio.add_argument("--rectify", action="store_true",
                     help="rectify every frame (and depth image) onto the ideal pinhole before "
                          "the VINS sees it, as the flight application does; without it the "
                          "VINS tracks the raw frames and undistorts its points, as VINS-Mono "
                          "on EuRoC")
    vio.set_defaults(command=_eval_vio)

    depth = actions.add_parser(
        "depth", parents=[dataset], help="score the metric depth stage on a dataset",
        description="Run the depth path as in flight over a EuRoC/ASL dataset with depth0 "
                    "(recorded by 'companion sim record'): the VINS, the depth network "
                    "([depth_network] model, or without one the synthetic stand-in of "
                    "[synthetic_depth] on the ground-truth depth) and the metric depth stage "
                    "([depth], [rescale]); score every frame's metric depth against depth0 with "
                    "AbsRel, delta1, RMSE and the over-estimate rate, and time the stage.")
    depth.set_defaults(command=_eval_depth)
    simulated = common.configured_parser(simulator=True)
    _add_eval_vio_table(actions, simulated)
    _add_eval_rescale(actions, simulated)
    _add_eval_nav(actions, simulated)


def _add_eval_vio_table(actions: argparse._SubParsersAction,
                        configured: argparse.ArgumentParser) -> None:
    from drivers.sim.options import WORLD_NAMES

    # defaults are companion.tools.eval.vio_table's, resolved by _eval_vio_table: the parser
    # does not import the estimator
    command = actions.add_parser(
        "vio-table", parents=[configured],
        help="score the VINS on simulated flights of each world at several seeds (issue 24's "
             "table)",
        description="Record a flight of every world from every seed, as 'companion sim record "
                    "--world W --seed S --duration D' records it (or reuse it from the cache), "
                    "run the VINS over each as 'companion eval vio' does, the recordings side "
                    "by side, and tabulate issue 24's goals on every recording (ATE <= 0.5 % "
                    "of distance, map points' median depth error <= 2 %, no reset) with the "
                    "path's scale, the pose and velocity NEES and the bearing at the end: per "
                    "world, over all, and per recording. The result on stdout as Markdown, or "
                    'JSON {"recordings": [...], "summary": {WORLD|"all": {...}}, "goal_met"}. '
                    "The flights are each seed's own, with the planner's waves as sim record "
                    "flies them: for another vehicle or noise draw, record with sim record and "
                    "score with eval vio.")
    common.add_json_flag(command, instead_of="the Markdown report")
    command.add_argument("--worlds", nargs="+", choices=WORLD_NAMES, metavar="WORLD",
                         default=list(WORLD_NAMES),
                         help=f"worlds to fly, of {', '.join(WORLD_NAMES)} (default: all)")
    command.add_argument("--seeds", nargs="+", type=common.non_negative_int, metavar="S",
                         help="seeds to fly in every world: each its world, route and noise, "
                              "as sim record --seed (default: 0 to 9)")
    command.add_argument("--duration", type=common.positive_float, metavar="SECONDS",
                         help="simulated seconds of each flight (default: 40)")
    _add_recording_tasks(command, "recordings scored")
    command.add_argument("--markdown", type=Path, metavar="FILE",
                         help="also write the Markdown report to FILE")
    command.add_argument("--resume", type=Path, metavar="FILE",
                         help="add every recording's row to FILE (JSON lines) as it is scored; "
                              "a FILE from a run stopped part way is gone on with: only the "
                              "recordings it lacks are scored, with the options, code and "
                              "config it was started with, and the report has them all")
    command.set_defaults(command=_eval_vio_table)


def _add_eval_rescale(actions: argparse._SubParsersAction,
                      configured: argparse.ArgumentParser) -> None:
    from drivers.sim.options import WORLD_NAMES

    rescale = actions.add_parser(
        "rescale", parents=[configured], help="compare every rescaling method (paper Table I)",
        description="Record (or reuse from the cache) a simulated flight in each world, as "
                    "many frames as the paper (mine 850, sewer 700, dome 1000), run the VINS "
                    "and the depth network once over it, and fit every rescaling method with "
                    "sparse depth from the ground truth at the VINS feature pixels (GT) and "
                    "from the VINS map (VINS), with the config's [rescale] options whatever "
                    "rescale.method says; report AbsRel, delta1 and the over-estimate rate per "
                    "world and their frame-weighted average as a Markdown table shaped like "
                    "the paper's Table I.")
    common.add_json_flag(rescale, instead_of="the Markdown report")
    rescale.add_argument("--quick", action="store_true",
                         help="80 frames per world instead of the paper's counts (for CI)")
    rescale.add_argument("--seed", type=common.non_negative_int, metavar="N",
                         help="seed of the worlds, flights and the synthetic network "
                              "(default: [sim] seed)")
    rescale.add_argument("--worlds", nargs="+", choices=WORLD_NAMES, default=list(WORLD_NAMES),
                         metavar="WORLD", help="worlds to evaluate, of "
                                               f"{', '.join(WORLD_NAMES)} (default: all)")
    _add_recording_tasks(rescale, "worlds evaluated")
    rescale.add_argument("--plot", type=common.png_path, metavar="PNG",
                         help="draw the weighted AbsRel per method, GT against VINS, here")
    rescale.add_argument("--markdown", type=Path, metavar="FILE",
                         help="also write the Markdown report to FILE")
    rescale.set_defaults(command=_eval_rescale)


def _add_recording_tasks(command: argparse.ArgumentParser, tasks: str) -> None:
    """The options of an evaluation whose tasks record simulated datasets into a cache:
    ``--cache``, and where the ``tasks`` run (``--workers`` here, or ``--cluster``)."""
    command.add_argument("--cache", type=Path, metavar="DIR",
                         help="where recorded datasets are kept and reused (default: "
                              "$XDG_CACHE_HOME/companion/eval, else ~/.cache/companion/eval)")
    command.add_argument("--workers", type=common.positive_int, metavar="N",
                         help=f"{tasks} at once, each in its own process (default: the number "
                              f"of CPUs)")
    command.add_argument("--cluster", metavar="ADDRESS",
                         help=f"run the {tasks.split()[0]} as tasks on a running Ray cluster "
                              f"instead (as eval nav --cluster); each node records into its "
                              f"own cache")


def _add_eval_nav(actions: argparse._SubParsersAction,
                  configured: argparse.ArgumentParser) -> None:
    from drivers.sim.options import WORLD_NAMES
    from drivers.sim.truth_tracks import TRACK_SOURCES

    # defaults (None here) are companion.tools.eval.nav's, resolved by _eval_nav: the parser
    # does not import the simulator
    command = actions.add_parser(
        "nav", parents=[configured], help="count navigation successes (paper's navigation "
                                          "figure)",
        description="Fly every start/goal pair of each world, --trials times (trial k on seed "
                    "SEED+k), once planning on the renderer's true depth (gt) and once on the "
                    "estimate (estimated), each trial a lockstep 'companion sim fly' in a "
                    "worker process; count successes (goal reached, no collision), collisions "
                    "and timeouts (neither within --timeout seconds of navigation, or ended "
                    "early by a failsafe), with the successes' mean flight time and speed, "
                    "the least true clearance and the VINS error when navigation ended. "
                    "Progress on stderr; the result on stdout as a Markdown table, or JSON "
                    '{"gt"|"estimated": {WORLD: {"trials", "success", "collision", "timeout", '
                    '"error", "mean_time_s", "mean_speed_mps", "least_clearance_m", '
                    '"vins_error_median_m", "vins_error_worst_m"}}}.')
    common.add_json_flag(command, instead_of="the Markdown report")
    command.add_argument("--trials", type=common.positive_int, metavar="N",
                         help="trials per start/goal pair and depth source (default: 5)")
    command.add_argument("--seed", type=common.non_negative_int, metavar="N",
                         help="base seed: trial k flies seed N+k, its world, noise and network "
                              "errors (default: [sim] seed)")
    command.add_argument("--worlds", nargs="+", choices=WORLD_NAMES, metavar="WORLD",
                         help=f"worlds to fly, of {', '.join(WORLD_NAMES)} (default: all)")
    command.add_argument("--pairs", nargs="+", type=common.non_negative_int, metavar="P",
                         help="start/goal pairs to fly in every world (default: all)")
    command.add_argument("--timeout", type=common.positive_float, metavar="SECONDS",
                         help="simulated seconds of navigation to reach the goal, the "
                              "application's [flight] mission_timeout_s in the trials "
                              "(default: 120)")
    command.add_argument("--tracks", choices=TRACK_SOURCES, metavar="SOURCE",
                         help="the VINS's feature tracks, as sim fly --tracks: tracker (the "
                              "default), or truth, early-error, late-error (ideal profile "
                              "only: --config config/sim.toml) to bound what a better tracker "
                              "would give navigation")
    command.add_argument("--workers", type=common.positive_int, metavar="N",
                         help="trials flown at once, each in its own process (default: the "
                              "number of CPUs)")
    command.add_argument("--cluster", metavar="ADDRESS",
                         help="fly the trials as tasks on a running Ray cluster instead: auto "
                              "(the cluster this machine joined with `ray start`), the head's "
                              "HOST:PORT, or ray://HOST:PORT; needs companion[cluster] and the "
                              "same code on every node")
    command.add_argument("--quick", action="store_true",
                         help="one trial of pair 0 in one world (the first of --worlds, else "
                              "dome), for CI; overrides --trials and --pairs")
    command.add_argument("--plot", type=common.png_path, metavar="PNG",
                         help="draw the outcomes per world and depth source here")
    command.add_argument("--markdown", type=Path, metavar="FILE",
                         help="also write the Markdown report to FILE")
    command.add_argument("--runs", type=Path, metavar="FILE",
                         help="write every trial's record (seed, outcome, times, path length, "
                              "failsafes, code revision, config hash) to FILE as JSON lines, "
                              "each as its trial completes; FILE must be new")
    command.add_argument("--resume", type=Path, metavar="FILE",
                         help="go on with the interrupted run whose --runs file is FILE: fly "
                              "only the trials it lacks, add them to it, and report them all; "
                              "give the options the run was started with")
    command.add_argument("--merge", nargs="+", type=Path, metavar="RUNS",
                         help="fly nothing: report the records of these --runs files (an "
                              "evaluation flown in parts, e.g. one --seed each) as one run; "
                              "takes none of the flight options")
    command.add_argument("--compare", nargs="+", type=Path, metavar="BEFORE AFTER",
                         help="fly nothing: compare two --runs files (one may be interrupted) "
                              "on the trials both flew (several pairs BEFORE AFTER ...: each "
                              "matched on its own trials, all pooled): each run's successes, "
                              "collisions, speed, least clearance and VINS error, the changed "
                              "outcomes, the identical flights, the after/before ratio of the "
                              "times to the goal, and the VINS at the end as issue 24 judges it "
                              "(worst, over 1 m, nearer and farther with the sign test's p and "
                              "the median change, seeds nearer and farther, paths made long, "
                              "|scale - 1|)")
    command.add_argument("--calibration", nargs="+", type=Path, metavar="RUNS",
                         help="fly nothing: fit the bearing and the scale of the VINS's error "
                              "at the end of navigation in these --runs files to each "
                              "vehicle's camera yaw on the body and accelerometer z scale "
                              "error, as the simulator drew them from the record's seed under "
                              "this command's --config and --set (give the runs' own): how "
                              "much of the error the calibration explains")
    command.set_defaults(command=_eval_nav)


def _eval_vio(args: argparse.Namespace, config: Config) -> int:
    # Imported here: the evaluation pulls in the dataset readers and the estimator.
    from companion.tools.eval import vio as evaluation

    try:
        result = evaluation.evaluate_vio(args.dataset, config.vins, frontend=config.vins_frontend,
                                         static=config.vins_init, max_frames=args.max_frames,
                                         bound=args.bound, track_source=args.tracks,
                                         rectify=args.rectify)
    except evaluation.EvaluationError as error:
        print(f"eval vio: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(result) if args.json else evaluation.format_vio_report(result))
    return common.EXIT_OK


def _eval_vio_table(args: argparse.Namespace, config: Config) -> int:
    from companion.tools.eval import provenance, records as eval_records, rescale, vio_table
    from companion.tools.eval.vio import EvaluationError

    unfollowed = vio_table.settings_not_flown(config)
    if unfollowed:
        print(f"eval vio-table: the table's flights are each seed's own vehicle and noise; "
              f"drop {', '.join(unfollowed)}, or record with 'companion sim record' and score "
              f"with 'companion eval vio'", file=sys.stderr)
        return common.EXIT_USAGE
    duration = vio_table.DEFAULT_DURATION_S if args.duration is None else args.duration
    try:
        job = vio_table.TableJob.of(config, args.cache or rescale.default_cache_dir(),
                                    duration)
        done, on_row = [], None
        if args.resume:
            done, note = eval_records.reopen(args.resume, vio_table.parse_row)
            if note:
                print(f"eval vio-table: {note}", file=sys.stderr)
            on_row = functools.partial(eval_records.append_record, out=args.resume)
        result = vio_table.evaluate_table(
            args.worlds, vio_table.DEFAULT_SEEDS if args.seeds is None else args.seeds,
            job=job, stamp=provenance.stamp(config), workers=args.workers,
            cluster=args.cluster, done=done, on_row=on_row)
    except (EvaluationError, OSError) as error:
        print(f"eval vio-table: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    return common.report("eval vio-table", args, result,
                         vio_table.format_markdown(result, duration_s=duration))


def _eval_depth(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.tools.eval import depth
    from companion.tools.eval.vio import EvaluationError

    try:
        network = depth.open_relative_depth_source(
            config.depth_network, config.synthetic_depth.for_profile(config.sim.profile),
            seed=config.sim.seed)
        options = depth.DepthEvalOptions(config.vins, config.rescale, config.depth,
                                         config.vins_frontend, config.vins_init,
                                         min_confidence=config.planner.min_confidence,
                                         max_range=config.planner.max_range)
        result = depth.evaluate_depth(args.dataset, options, network,
                                      max_frames=args.max_frames)
    except (NetworkError, EvaluationError) as error:
        print(f"eval depth: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(result) if args.json else depth.format_depth_report(result))
    return common.EXIT_OK


def _eval_rescale(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.tools.eval import depth, provenance, rescale
    from companion.tools.eval.vio import EvaluationError

    _warn_of_unestimated_errors("eval rescale", config)
    seed = config.sim.seed if args.seed is None else args.seed
    try:
        result = rescale.evaluate_rescaling(
            rescale.frames_per_world(args.worlds, quick=args.quick), seed=seed,
            cache=args.cache or rescale.default_cache_dir(),
            recording=rescale.Recording(
                config.camera, config.vehicle, config.imu,
                config.sim_camera.for_profile(config.sim.profile)),
            options=depth.DepthEvalOptions(config.vins, config.rescale, config.depth,
                                           config.vins_frontend, config.vins_init),
            open_network=functools.partial(
                depth.open_relative_depth_source, config.depth_network,
                config.synthetic_depth.for_profile(config.sim.profile), seed=seed),
            workers=args.workers, cluster=args.cluster)
    except (NetworkError, EvaluationError) as error:
        print(f"eval rescale: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    return common.report("eval rescale", args, result,
                         rescale.format_markdown(result, seed=seed),
                         (args.plot, lambda path: rescale.plot_absrel(
                             result, path, seed=seed, revision=provenance.code_revision())))


def _warn_of_unestimated_errors(command: str, config: Config) -> None:
    """Once, before the trials: their workers log errors only."""
    from companion.launch.simulated import realistic_errors_not_estimated

    unestimated = realistic_errors_not_estimated(config)
    if unestimated:
        print(f"{command}: warning: {unestimated}", file=sys.stderr)


def _eval_nav(args: argparse.Namespace, config: Config) -> int:
    from companion.tools.eval import nav, records as eval_records
    from companion.tools.eval.vio import EvaluationError

    for mode, refused in (("--calibration", _NAV_FLIGHT_OPTIONS + ("resume", "runs", "merge",
                                                                   "compare", "plot")),
                          ("--compare", _NAV_FLIGHT_OPTIONS + ("resume", "runs", "merge",
                                                               "plot")),
                          ("--merge", _NAV_FLIGHT_OPTIONS + ("resume",))):
        if getattr(args, mode[2:]):
            given = [f"--{name}" for name in refused if getattr(args, name) not in (None, False)]
            if given:
                print(f"eval nav: {mode} flies nothing; drop {', '.join(given)}",
                      file=sys.stderr)
                return common.EXIT_USAGE
    if args.calibration:
        return _calibration_nav(args, config)
    if args.compare:
        return _compare_nav(args)
    runs = args.resume or args.runs
    if args.resume and args.runs:
        print("eval nav: --resume adds to its own file; drop --runs", file=sys.stderr)
        return common.EXIT_USAGE
    if args.runs and args.runs.exists() and args.runs.stat().st_size:
        print(f"eval nav: {args.runs} exists; --resume it, or choose a new --runs file",
              file=sys.stderr)
        return common.EXIT_USAGE
    try:
        records = nav.read_runs(args.merge) if args.merge else _fly_nav(args, config, runs)
    except (EvaluationError, OSError) as error:
        print(f"eval nav: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    result = nav.summarise(records)
    return common.report("eval nav", args, result, nav.format_markdown(result, records),
                         (runs, lambda path: eval_records.write_records(records, path)),
                         (args.plot, lambda path: nav.plot_navigation(result, records, path)))


def _compare_nav(args: argparse.Namespace) -> int:
    from companion.tools.eval import nav_compare
    from companion.tools.eval.vio import EvaluationError

    if len(args.compare) % 2:
        print(f"eval nav: --compare takes runs in pairs, BEFORE AFTER [BEFORE AFTER ...]; "
              f"got {len(args.compare)}", file=sys.stderr)
        return common.EXIT_USAGE
    names = list(zip(args.compare[::2], args.compare[1::2]))
    try:
        (before, after), *also = [(nav_compare.read_run(b), nav_compare.read_run(a))
                                  for b, a in names]
        comparison = nav_compare.compare_runs(before, after, also)
    except EvaluationError as error:
        print(f"eval nav: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    return common.report("eval nav", args, comparison, nav_compare.format_markdown(
        comparison, [(str(b), str(a)) for b, a in names]))


def _calibration_nav(args: argparse.Namespace, config: Config) -> int:
    from companion.tools.eval import nav, nav_calibration, nav_compare
    from companion.tools.eval.vio import EvaluationError
    from drivers.sim.host import vehicle_errors

    try:
        records = [record for path in args.calibration for record in nav_compare.read_run(path)]
        nav.refuse_repeated_trials(records)
        configs = sorted({str(r.get("config_hash")) for r in records})
        if len(configs) > 1:
            raise EvaluationError(f"the runs were flown with different configs "
                                  f"({', '.join(configs)}): their vehicles may differ; fit "
                                  "each config's runs on their own")
        fit = nav_calibration.calibration_fit(records,
                                              functools.partial(vehicle_errors, config))
    except EvaluationError as error:
        print(f"eval nav: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    return common.report("eval nav", args, fit, nav_calibration.format_markdown(
        fit, [str(path) for path in args.calibration]))


#: The options of ``eval nav`` that choose what to fly, which ``--merge`` and ``--compare``
#: do not take.
_NAV_FLIGHT_OPTIONS = ("trials", "seed", "worlds", "pairs", "timeout", "tracks", "workers",
                       "cluster", "quick")


def _fly_nav(args: argparse.Namespace, config: Config, runs: Path | None) -> list[dict]:
    """Fly the trials ``args`` plan, those of the ``--resume`` file excepted, adding each
    record to ``runs`` (if given) as it completes."""
    from companion.tools.eval import nav, records as eval_records
    from drivers.sim.options import WORLD_NAMES

    done = []
    if args.resume:
        done, note = eval_records.reopen(args.resume, nav.parse_record)
        if note:
            print(f"eval nav: {note}", file=sys.stderr)

    _warn_of_unestimated_errors("eval nav", config)
    seed = config.sim.seed if args.seed is None else args.seed
    timeout = nav.TIMEOUT_S if args.timeout is None else args.timeout
    worlds, pairs, trials = args.worlds or list(WORLD_NAMES), args.pairs, args.trials or nav.TRIALS
    if args.quick:
        worlds, pairs, trials = (args.worlds or [nav.QUICK_WORLD])[:1], [0], 1
    _, records = nav.evaluate_navigation(
        config, worlds=worlds, pairs=pairs, trials=trials, seed=seed, timeout_s=timeout,
        tracks=args.tracks or "tracker", workers=args.workers, cluster=args.cluster,
        progress=sys.stderr, done=done,
        on_record=None if runs is None else functools.partial(eval_records.append_record,
                                                                out=runs))
    return records

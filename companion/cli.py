"""The ``companion`` command line: a thin shell over library calls.

Every command works on the effective configuration, which :func:`main` loads once (the file,
then ``--set`` overrides) before dispatching, so a bad config is reported the same way by
every command: one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
from pathlib import Path
from typing import Callable, Sequence

from autonomy.options import OptionError
from companion import __version__
from companion.config import LOG_LEVELS, Config, ConfigError, dump_toml, load_config
from autonomy.navigation.mission import parse_point

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

EXIT_OK = 0
EXIT_FAILED = 1  # the command ran and could not do its job
EXIT_USAGE = 2  # argparse's status for bad arguments; a bad config is a bad argument too


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``); return the exit status."""
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help, --version, or a usage error argparse has printed
        return done.code
    if args.command is None:
        args.help_of.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        config = load_config(args.config_path, args.overrides)
    except ConfigError as error:
        print(error, file=sys.stderr)
        return EXIT_USAGE
    logging.basicConfig(level=args.log_level or config.log.level, stream=sys.stderr,
                        format=LOG_FORMAT)
    return args.command(args, config)


def _config_check(args: argparse.Namespace, config: Config) -> int:
    print(f"{args.config_path}: ok")
    return EXIT_OK


def _config_show(args: argparse.Namespace, config: Config) -> int:
    print(dump_toml(config), end="")
    return EXIT_OK


def _bench_rescale(args: argparse.Namespace, config: Config) -> int:
    # Imported here: the benchmark pulls in the whole rescaler, which no other command needs.
    from companion.tools import bench

    try:
        result = bench.run_rescale_benchmark(config.rescale, anchors=args.anchors,
                                             shape=args.size, repeats=args.repeats)
    except bench.BenchmarkError as error:
        print(f"bench rescale: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(json.dumps(result) if args.json else bench.format_rescale_table(result))
    return EXIT_OK


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion",
        description="Flight application for a PX4 drone's companion computer.")
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    parser.add_argument("--log-level", choices=LOG_LEVELS,
                        help="lowest severity logged to stderr (default: [log] level of the "
                             "config, INFO unless set)")
    commands = _add_command_group(parser)
    overrides = argparse.ArgumentParser(add_help=False)
    overrides.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override one config value, e.g. --set rescale.kappa=1e5 or "
             "--set rescale.method=poly1 (a TOML value; a bare word is a string); repeatable, "
             "the last one wins")
    configured = argparse.ArgumentParser(add_help=False, parents=[overrides])
    configured.add_argument("--config", dest="config_path", metavar="FILE",
                            help="TOML config file (default: none, all defaults)")
    _add_config_commands(commands, overrides)
    _add_bench_commands(commands, configured)
    _add_sim_commands(commands, configured)
    _add_eval_commands(commands, configured)
    _add_depth_commands(commands, configured)
    _add_fly_command(commands, configured)
    return parser


def _add_fly_command(commands: argparse._SubParsersAction,
                     configured: argparse.ArgumentParser) -> None:
    fly = commands.add_parser(
        "fly", parents=[configured], help="fly the real vehicle (the systemd service's command)",
        description="Connect to the flight controller ([mavlink] url), the camera ([v4l2]) and "
                    "the depth network ([depth_network] model), then fly the mission: "
                    "[flight] waypoints, or --goal. Stops, holds and lands on any failure and "
                    "on SIGTERM. See docs/operations.md.")
    fly.add_argument("--goal", dest="goals", type=_point, action="append", default=[],
                     metavar="X,Y,Z",
                     help="waypoint in metres in PX4's local frame (x east, y north, z up); "
                          "repeatable, the last is the goal; replaces [flight] waypoints")
    _add_json_flag(fly, instead_of="the summary table")
    fly.set_defaults(command=_fly)


def _fly(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.launch import real
    from companion.flight.app import format_flight
    from drivers.camera.v4l2 import CameraError

    waypoints = args.goals or config.flight.waypoint_points()
    try:
        summary = real.run(config, waypoints)
    except (real.FlyError, NetworkError, CameraError, ValueError, OSError) as error:
        print(f"fly: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(json.dumps(summary) if args.json else format_flight(summary))
    return EXIT_OK if summary["final_state"] == "landed" and summary["reached_goal"] \
        else EXIT_FAILED


def _add_command_group(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """Subcommands of ``parser``; given none, the command prints ``parser``'s help."""
    parser.set_defaults(command=None, help_of=parser)
    return parser.add_subparsers(title="commands", metavar="COMMAND")


def _add_config_commands(commands: argparse._SubParsersAction,
                         overrides: argparse.ArgumentParser) -> None:
    group = commands.add_parser("config", help="validate or print a configuration",
                                description="Validate or print a TOML configuration.")
    actions = _add_command_group(group)
    check = actions.add_parser(
        "check", parents=[overrides], help="validate a config file",
        description="Validate a config file and its overrides: print 'FILE: ok' and exit 0, "
                    "or print what is wrong and where, and exit 2.")
    check.add_argument("config_path", metavar="FILE", help="TOML config file")
    check.set_defaults(command=_config_check)
    show = actions.add_parser(
        "show", parents=[overrides], help="print the effective config as TOML",
        description="Print the effective configuration as TOML, every key with its value: "
                    "the defaults, then FILE, then the overrides.")
    show.add_argument("config_path", metavar="FILE", nargs="?",
                      help="TOML config file (default: none, all defaults)")
    show.set_defaults(command=_config_show)


def _add_bench_commands(commands: argparse._SubParsersAction,
                        configured: argparse.ArgumentParser) -> None:
    group = commands.add_parser("bench", help="measure the speed of the algorithms",
                                description="Measure the speed of the algorithms on "
                                            "synthetic input.")
    actions = _add_command_group(group)
    rescale = actions.add_parser(
        "rescale", parents=[configured], help="time the depth rescaler",
        description="Time fitting the rescaling curve to sparse anchors and applying it to a "
                    "relative-disparity image, with the [rescale] options of the config. "
                    "Every method is timed, whatever rescale.method says; the result is "
                    "medians in milliseconds, with the direct per-pixel evaluation of the same "
                    "curve as the baseline.")
    _add_json_flag(rescale, instead_of="a table")
    rescale.add_argument("--repeats", type=_positive_int, default=30,
                         help="timed runs per measurement (default: %(default)s)")
    rescale.add_argument("--anchors", type=_positive_int, default=150,
                         help="sparse metric anchors per frame (default: %(default)s)")
    rescale.add_argument("--size", type=_image_size, default=(480, 640), metavar="HxW",
                         help="image height x width in pixels (default: 480x640)")
    rescale.set_defaults(command=_bench_rescale)


def _add_sim_commands(commands: argparse._SubParsersAction,
                       configured: argparse.ArgumentParser) -> None:
    from drivers.sim.options import CLOCK_MODES, WORLD_NAMES

    group = commands.add_parser("sim", help="run the simulated vehicle",
                                description="The simulated vehicle: a mock PX4 over real "
                                            "MAVLink, a rendered camera and a synthetic IMU.")
    actions = _add_command_group(group)
    world = argparse.ArgumentParser(add_help=False)
    world.add_argument("--world", choices=WORLD_NAMES,
                       help="the world (default: [sim] world of the config)")
    world.add_argument("--seed", type=_non_negative_int,
                       help="seed of the world, the noise and the path (default: [sim] seed)")

    serve = actions.add_parser(
        "serve", parents=[configured, world], help="serve the vehicle to any MAVLink client",
        description="Run the simulated PX4 quadrotor alone for any MAVLink client (MAVSDK, "
                    "QGroundControl, mavproxy) until interrupted. With --mavlink pty the "
                    "pseudo-terminal's path is printed; open it like a serial port.")
    serve.add_argument("--mavlink", default="udpin://127.0.0.1:14540", metavar="URL",
                       help="udpin://HOST:PORT, udpout://HOST:PORT, tcp://HOST:PORT or pty "
                            "(default: %(default)s)")
    serve.add_argument("--clock", choices=CLOCK_MODES,
                       help="realtime for outside clients, lockstep for as fast as the CPU "
                            "allows (default: [sim] clock)")
    serve.add_argument("--duration", type=_positive_float, metavar="SECONDS",
                       help="stop after this much simulated time (default: run until "
                            "interrupted)")
    serve.set_defaults(command=_sim_serve)

    record = actions.add_parser(
        "record", parents=[configured, world], help="record a flight as a EuRoC dataset",
        description="Fly a smooth collision-free path through the world and write camera "
                    "images, ground-truth depth, IMU and ground truth in the EuRoC/ASL "
                    "layout (mav0/cam0, depth0, imu0, state_groundtruth_estimate0).")
    record.add_argument("--duration", type=_positive_float, default=40.0, metavar="SECONDS",
                        help="simulated seconds to record (default: %(default)s)")
    record.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="dataset folder to create (must be new or empty)")
    record.set_defaults(command=_sim_record)

    fly = actions.add_parser(
        "fly", parents=[configured, world], help="fly the whole stack in the simulator",
        description="Start the simulator (mock PX4 over loopback UDP MAVLink, rendered camera, "
                    "synthetic IMU) and fly the whole application against it: VINS, depth "
                    "network (the synthetic stand-in unless [depth_network] model is set), "
                    "rescaler and planner, from a start/goal pair of the world. Prints progress "
                    "and a summary, and draws the flown path over the world map.")
    fly.add_argument("--pair", type=_non_negative_int, default=0,
                     help="start/goal pair of the world (default: %(default)s)")
    fly.add_argument("--goal", type=_point, metavar="X,Y,Z",
                     help="fly to this point (metres, world frame, z up) instead of the pair's "
                          "goal, from the pair's start")
    fly.add_argument("--start-yaw", type=float, metavar="DEG",
                     help="heading the vehicle stands at before take-off, degrees "
                          "counter-clockwise from east (default: facing the first leg)")
    fly.add_argument("--clock", choices=CLOCK_MODES, default="lockstep",
                     help="lockstep: deterministic, as fast as the CPU allows; realtime: the "
                          "simulator in its own thread on the wall clock (default: %(default)s)")
    fly.add_argument("--depth", choices=("estimated", "truth"), default="estimated",
                     help="the planner's depth: estimated (network and rescaler on the VINS "
                          "map) or the renderer's truth (default: %(default)s)")
    fly.add_argument("--fault", dest="faults", action="append", default=[],
                     metavar="KIND[@AFTER[+DURATION]]",
                     help="inject a fault AFTER seconds into cruise for DURATION seconds "
                          "(default: 1 s, for good): camera_freeze, camera_blackout, imu_gap, "
                          "link_cut, network_nan, loop_stall; repeatable")
    fly.add_argument("--plot", type=Path, default=Path("sim-fly.png"), metavar="PNG",
                     help="where to draw the top view of the flight (default: %(default)s)")
    fly.add_argument("--no-plot", action="store_true", help="draw no plot")
    _add_json_flag(fly, instead_of="the summary table")
    fly.set_defaults(command=_sim_fly)


def _add_eval_commands(commands: argparse._SubParsersAction,
                       configured: argparse.ArgumentParser) -> None:
    group = commands.add_parser("eval", help="measure the accuracy of the algorithms",
                                description="Measure the accuracy of the algorithms against "
                                            "a dataset's ground truth.")
    actions = _add_command_group(group)
    dataset = argparse.ArgumentParser(add_help=False, parents=[configured])
    dataset.add_argument("dataset", type=Path, metavar="DATASET",
                         help="dataset folder, the one holding mav0/")
    _add_json_flag(dataset, instead_of="a report")
    dataset.add_argument("--max-frames", type=_positive_int, metavar="N",
                         help="stop after N camera frames (default: all)")
    vio = actions.add_parser(
        "vio", parents=[dataset], help="score the VINS on a EuRoC dataset",
        description="Run the VINS, with the [vins], [vins_frontend] and [vins_init] options of "
                    "the config, over a EuRoC/ASL dataset (real, or recorded by 'companion sim "
                    "record') and compare it with the ground truth: trajectory error after "
                    "SE(3) alignment, scale error, landmark depth error against depth0 when the "
                    "dataset has it, the static initialisation, and the time per stage.")
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
    _add_eval_rescale(actions, configured)
    _add_eval_nav(actions, configured)


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
    _add_json_flag(rescale, instead_of="the Markdown report")
    rescale.add_argument("--quick", action="store_true",
                         help="80 frames per world instead of the paper's counts (for CI)")
    rescale.add_argument("--seed", type=_non_negative_int, metavar="N",
                         help="seed of the worlds, flights and the synthetic network "
                              "(default: [sim] seed)")
    rescale.add_argument("--worlds", nargs="+", choices=WORLD_NAMES, default=list(WORLD_NAMES),
                         metavar="WORLD", help="worlds to evaluate, of "
                                               f"{', '.join(WORLD_NAMES)} (default: all)")
    rescale.add_argument("--cache", type=Path, metavar="DIR",
                         help="where recorded datasets are kept and reused (default: "
                              "$XDG_CACHE_HOME/companion/eval, else ~/.cache/companion/eval)")
    rescale.add_argument("--plot", type=_png_path, metavar="PNG",
                         help="draw the weighted AbsRel per method, GT against VINS, here")
    rescale.add_argument("--markdown", type=Path, metavar="FILE",
                         help="also write the Markdown report to FILE")
    rescale.set_defaults(command=_eval_rescale)


def _add_eval_nav(actions: argparse._SubParsersAction,
                  configured: argparse.ArgumentParser) -> None:
    from drivers.sim.options import WORLD_NAMES

    # defaults (None here) are companion.tools.eval.nav's, resolved by _eval_nav: the parser does not
    # import the simulator
    command = actions.add_parser(
        "nav", parents=[configured], help="count navigation successes (paper's navigation "
                                          "figure)",
        description="Fly every start/goal pair of each world, --trials times (trial k on seed "
                    "SEED+k), once planning on the renderer's true depth (gt) and once on the "
                    "estimate (estimated), each trial a lockstep 'companion sim fly' in a "
                    "worker process; count successes (goal reached, no collision), collisions "
                    "and timeouts (neither within --timeout seconds of navigation, or ended "
                    "early by a failsafe), with the successes' mean flight time. Progress on "
                    "stderr; the result on stdout as a Markdown table, or JSON "
                    '{"gt"|"estimated": {WORLD: {"trials", "success", "collision", "timeout", '
                    '"mean_time_s"}}}.')
    _add_json_flag(command, instead_of="the Markdown report")
    command.add_argument("--trials", type=_positive_int, metavar="N",
                         help="trials per start/goal pair and depth source (default: 5)")
    command.add_argument("--seed", type=_non_negative_int, metavar="N",
                         help="base seed: trial k flies seed N+k, its world, noise and network "
                              "errors (default: [sim] seed)")
    command.add_argument("--worlds", nargs="+", choices=WORLD_NAMES, metavar="WORLD",
                         help=f"worlds to fly, of {', '.join(WORLD_NAMES)} (default: all)")
    command.add_argument("--pairs", nargs="+", type=_non_negative_int, metavar="P",
                         help="start/goal pairs to fly in every world (default: all)")
    command.add_argument("--timeout", type=_positive_float, metavar="SECONDS",
                         help="simulated seconds of navigation to reach the goal, the "
                              "application's [flight] mission_timeout_s in the trials "
                              "(default: 120)")
    command.add_argument("--workers", type=_positive_int, metavar="N",
                         help="trials flown at once, each in its own process (default: the "
                              "number of CPUs)")
    command.add_argument("--quick", action="store_true",
                         help="one trial of pair 0 in one world (the first of --worlds, else "
                              "dome), for CI; overrides --trials and --pairs")
    command.add_argument("--plot", type=_png_path, metavar="PNG",
                         help="draw the outcomes per world and depth source here")
    command.add_argument("--markdown", type=Path, metavar="FILE",
                         help="also write the Markdown report to FILE")
    command.add_argument("--runs", type=Path, metavar="FILE",
                         help="write every trial's record (seed, outcome, times, path length, "
                              "failsafes) to FILE as JSON lines")
    command.add_argument("--merge", nargs="+", type=Path, metavar="RUNS",
                         help="fly nothing: report the records of these --runs files (an "
                              "evaluation flown in parts, e.g. one --seed each) as one run; "
                              "takes none of the flight options")
    command.set_defaults(command=_eval_nav)


def _eval_nav(args: argparse.Namespace, config: Config) -> int:
    from companion.tools.eval import nav
    from companion.tools.eval.vio import EvaluationError

    if args.merge:
        flight_options = [f"--{name}" for name in _NAV_FLIGHT_OPTIONS
                          if getattr(args, name) not in (None, False)]
        if flight_options:
            print(f"eval nav: --merge flies nothing; drop {', '.join(flight_options)}",
                  file=sys.stderr)
            return EXIT_USAGE
    try:
        records = nav.read_runs(args.merge) if args.merge else _fly_nav(args, config)
    except EvaluationError as error:
        print(f"eval nav: {error}", file=sys.stderr)
        return EXIT_FAILED
    result = nav.summarise(records)
    return _report("eval nav", args, result, nav.format_markdown(result, records),
                   (args.runs, lambda path: nav.write_runs(records, path)),
                   (args.plot, lambda path: nav.plot_navigation(result, path)))


#: The options of ``eval nav`` that choose what to fly, which ``--merge`` does not take.
_NAV_FLIGHT_OPTIONS = ("trials", "seed", "worlds", "pairs", "timeout", "workers", "quick")


def _fly_nav(args: argparse.Namespace, config: Config) -> list[dict]:
    from companion.tools.eval import nav
    from drivers.sim.options import WORLD_NAMES

    seed = config.sim.seed if args.seed is None else args.seed
    timeout = nav.TIMEOUT_S if args.timeout is None else args.timeout
    worlds, pairs, trials = args.worlds or list(WORLD_NAMES), args.pairs, args.trials or nav.TRIALS
    if args.quick:
        worlds, pairs, trials = (args.worlds or [nav.QUICK_WORLD])[:1], [0], 1
    _, records = nav.evaluate_navigation(
        config, worlds=worlds, pairs=pairs, trials=trials, seed=seed, timeout_s=timeout,
        workers=args.workers, progress=sys.stderr)
    return records


def _add_depth_commands(commands: argparse._SubParsersAction,
                        configured: argparse.ArgumentParser) -> None:
    group = commands.add_parser("depth", help="the depth network and the metric depth stage",
                                description="The depth network runtime and the metric depth "
                                            "stage.")
    actions = _add_command_group(group)
    bench = actions.add_parser(
        "bench", parents=[configured], help="time the depth network and the stage",
        description="Time the depth network runtime (pre-processing, inference, "
                    "post-processing) per preset and input size on every execution provider "
                    "of [depth_network] providers that onnxruntime offers here, with a small "
                    "generated test model and, with --model or [depth_network] model, the "
                    "user's model; and the metric depth stage without the network. Medians "
                    "in milliseconds.")
    bench.add_argument("--model", metavar="FILE",
                       help="the user's ONNX depth model (default: [depth_network] model)")
    _add_json_flag(bench, instead_of="a table")
    bench.add_argument("--repeats", type=_positive_int, default=20,
                       help="timed runs per measurement (default: %(default)s)")
    bench.add_argument("--size", type=_image_size, default=(480, 640), metavar="HxW",
                       help="camera image height x width in pixels (default: 480x640)")
    bench.set_defaults(command=_depth_bench)


def _depth_bench(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.tools import bench, depth_bench

    network = config.depth_network
    if args.model is not None:
        network = dataclasses.replace(network, model=args.model, sha256="")
    try:
        result = depth_bench.run_depth_benchmark(network, config.rescale, config.depth,
                                                 shape=args.size, repeats=args.repeats)
    except (NetworkError, bench.BenchmarkError) as error:
        print(f"depth bench: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(json.dumps(result) if args.json else depth_bench.format_depth_table(result))
    return EXIT_OK


def _eval_depth(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.tools.eval import depth
    from companion.tools.eval.vio import EvaluationError

    try:
        network = depth.open_relative_depth_source(config.depth_network,
                                                   config.synthetic_depth, seed=config.sim.seed)
        options = depth.DepthEvalOptions(config.vins, config.rescale, config.depth,
                                         config.vins_frontend, config.vins_init)
        result = depth.evaluate_depth(args.dataset, options, network,
                                      max_frames=args.max_frames)
    except (NetworkError, EvaluationError) as error:
        print(f"eval depth: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(json.dumps(result) if args.json else depth.format_depth_report(result))
    return EXIT_OK


def _eval_rescale(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.tools.eval import depth, rescale
    from companion.tools.eval.vio import EvaluationError

    seed = config.sim.seed if args.seed is None else args.seed
    try:
        result = rescale.evaluate_rescaling(
            rescale.frames_per_world(args.worlds, quick=args.quick), seed=seed,
            cache=args.cache or rescale.default_cache_dir(),
            recording=rescale.Recording(config.camera, config.vehicle, config.imu),
            options=depth.DepthEvalOptions(config.vins, config.rescale, config.depth,
                                           config.vins_frontend, config.vins_init),
            open_network=lambda: depth.open_relative_depth_source(
                config.depth_network, config.synthetic_depth, seed=seed))
    except (NetworkError, EvaluationError) as error:
        print(f"eval rescale: {error}", file=sys.stderr)
        return EXIT_FAILED
    return _report("eval rescale", args, result, rescale.format_markdown(result, seed=seed),
                   (args.plot, lambda path: rescale.plot_absrel(result, path)))


def _report(command: str, args: argparse.Namespace, result: dict, report: str,
            *files: tuple[Path | None, Callable[[Path], object]]) -> int:
    """Print an evaluation's ``result`` (``--json``) or Markdown ``report``, then write
    ``--markdown`` and each of ``files`` (path or None, writer): exit 1 with one line when
    one cannot be written (the result is printed already)."""
    print(json.dumps(result) if args.json else report)
    try:
        if args.markdown is not None:
            args.markdown.parent.mkdir(parents=True, exist_ok=True)
            args.markdown.write_text(report + "\n")
        for path, write in files:
            if path is not None:
                write(path)
    except OSError as error:
        print(f"{command}: {error}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def _eval_vio(args: argparse.Namespace, config: Config) -> int:
    # Imported here: the evaluation pulls in the dataset readers and the estimator.
    from companion.tools.eval import vio as evaluation

    try:
        result = evaluation.evaluate_vio(args.dataset, config.vins, frontend=config.vins_frontend,
                                         static=config.vins_init, max_frames=args.max_frames)
    except evaluation.EvaluationError as error:
        print(f"eval vio: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(json.dumps(result) if args.json else evaluation.format_vio_report(result))
    return EXIT_OK


def _sim_options(args: argparse.Namespace, config: Config):
    """The [sim] section with the command line's --world, --seed and --clock on top."""
    changes = {key: getattr(args, key) for key in ("world", "seed", "clock")
               if getattr(args, key, None) is not None}
    return dataclasses.replace(config.sim, **changes)


def _sim_serve(args: argparse.Namespace, config: Config) -> int:
    import asyncio

    from drivers.sim import serve as sim_serve
    from drivers.sim.world import build_world

    sim = _sim_options(args, config)
    world = build_world(sim.world, sim.seed)

    def ready(vehicle) -> None:
        where = vehicle.px4.link.pty_path or args.mavlink
        print(f"serving a simulated PX4 quadrotor in {sim.world} (seed {sim.seed}, "
              f"{sim.clock} clock) on {where}", flush=True)

    try:
        summary = asyncio.run(sim_serve.serve(
            args.mavlink, world, seed=sim.seed, clock_mode=sim.clock,
            vehicle_options=config.vehicle, imu_options=config.imu, px4_options=config.px4,
            duration=args.duration, on_ready=ready))
    except KeyboardInterrupt:
        return EXIT_OK
    except (ValueError, OSError) as error:
        print(f"sim serve: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(f"served {summary.sim_time:.1f} s of simulated flight"
          + (f"; collision at t={summary.collision.time:.2f} s" if summary.collision else ""))
    return EXIT_OK


def _sim_record(args: argparse.Namespace, config: Config) -> int:
    from drivers.sim import record
    from drivers.sim.render import RenderError

    sim = _sim_options(args, config)
    try:
        summary = record.record_dataset(args.out, sim, config.camera, config.vehicle,
                                        config.imu, duration=args.duration)
    except (record.RecordError, RenderError, OSError) as error:
        print(f"sim record: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(f"recorded {summary.duration:g} s of {summary.world} route {summary.route} "
          f"({summary.frames} frames, {summary.imu_samples} IMU samples, path "
          f"{summary.path_length:.1f} m) into {args.out}")
    return EXIT_OK


def _sim_fly(args: argparse.Namespace, config: Config) -> int:
    from companion.launch import simulated
    from drivers.sim.faults import Fault
    from drivers.sim.render import RenderError

    sim = _sim_options(args, config)
    try:
        mission = simulated.SimMission(world=sim.world, seed=sim.seed, pair=args.pair,
                                    goal=args.goal, start_yaw_deg=args.start_yaw,
                                    clock=args.clock, depth=args.depth,
                                    faults=tuple(Fault.parse(f) for f in args.faults))
        summary = simulated.run(config, mission, plot=None if args.no_plot else args.plot,
                             progress=None if args.json else _print_progress)
    except (simulated.SimError, RenderError, ValueError, OSError) as error:
        print(f"sim fly: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(json.dumps(summary) if args.json else simulated.format_summary(summary))
    # a fault-free flight must reach its goal; any flight must end without a collision
    safe = summary["collisions"] == 0 and summary["final_state"] == "landed"
    return EXIT_OK if safe and (summary["reached_goal"] or mission.faults) else EXIT_FAILED


def _print_progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _point(text: str) -> tuple[float, float, float]:
    """``x,y,z`` metres -> a finite 3-tuple (:func:`autonomy.navigation.mission.parse_point`)."""
    try:
        return parse_point(text)
    except OptionError:
        raise argparse.ArgumentTypeError(
            f"expected X,Y,Z in metres, e.g. 10,-4,1.5; got {text!r}") from None


def _add_json_flag(parser: argparse.ArgumentParser, instead_of: str) -> None:
    parser.add_argument("--json", action="store_true",
                        help=f"print the result as one JSON object instead of {instead_of}")


def _png_path(text: str) -> Path:
    """A path ending in .png (checked before a long run, not after it)."""
    if not text.lower().endswith(".png"):
        raise argparse.ArgumentTypeError(f"expected a .png file name, got {text!r}")
    return Path(text)


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _integer_at_least(minimum: int, wording: str):
    """An argparse type: an integer >= ``minimum``, else a usage error in ``wording``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected a {wording} integer, got {text!r}")
        return value
    return parse


_positive_int = _integer_at_least(1, "positive")
_non_negative_int = _integer_at_least(0, "non-negative")


def _image_size(text: str) -> tuple[int, int]:
    """``480x640`` -> ``(480, 640)``: height first, as in a numpy shape."""
    parts = text.lower().split("x")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH, e.g. 480x640; got {text!r}")
    height, width = (_positive_int(part) for part in parts)
    return height, width

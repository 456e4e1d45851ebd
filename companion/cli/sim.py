"""``companion sim``: the simulated vehicle (``serve`` it, ``record`` a dataset, ``fly`` the
whole stack in it)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from companion.cli import common
from companion.config import Config


#: Where ``sim fly`` draws the top view of its flight when not told.
DEFAULT_PLOT = Path("sim-fly.png")


def add_commands(commands: argparse._SubParsersAction) -> None:
    from companion.tools.fault_matrix import MATRIX_FAULTS
    from drivers.sim.faults import FAULT_KINDS, MOMENTS
    from drivers.sim.options import CLOCK_MODES, WORLD_NAMES
    from drivers.sim.serve import LINKS
    from drivers.sim.truth_tracks import TRACK_SOURCES

    configured = common.configured_parser()
    simulated = common.configured_parser(simulator=True)
    group = commands.add_parser("sim", help="run the simulated vehicle",
                                description="The simulated vehicle: a mock PX4 over real "
                                            "MAVLink, a rendered camera and a synthetic IMU.")
    actions = common.add_command_group(group)
    world = argparse.ArgumentParser(add_help=False)
    world.add_argument("--world", choices=WORLD_NAMES,
                       help="the world (default: [sim] world of the config)")
    world.add_argument("--seed", type=common.non_negative_int,
                       help="seed of the world, the noise and the path (default: [sim] seed)")
    mission = argparse.ArgumentParser(add_help=False)
    mission.add_argument("--pair", type=common.non_negative_int, default=0,
                         help="start/goal pair of the world (default: %(default)s)")
    mission.add_argument("--goal", type=common.point, metavar="X,Y,Z",
                         help="fly to this point (metres, world frame, z up) instead of the "
                              "pair's goal, from the pair's start")
    mission.add_argument("--via", type=common.point, metavar="X,Y,Z", action="append",
                         default=[], help="with --goal: fly through this waypoint first "
                                          "(repeat for several, flown in order)")
    mission.add_argument("--depth", choices=("estimated", "truth"), default="estimated",
                         help="the planner's depth: estimated (network and rescaler on the VINS "
                              "map) or the renderer's truth (default: %(default)s)")

    serve = actions.add_parser(
        "serve", parents=[configured, world], help="serve the vehicle to any MAVLink client",
        description="Run the simulated PX4 quadrotor alone for any MAVLink client (MAVSDK, "
                    "QGroundControl, mavproxy) until interrupted. With --mavlink pty the "
                    "pseudo-terminal's path is printed; open it like a serial port.")
    serve.add_argument("--mavlink", default="udpin://127.0.0.1:14540", metavar="URL",
                       help="MAVSDK's connection strings: udpin://HOST:PORT (listen; a client "
                            "sends first), udpout://HOST:PORT (send to a listening client), "
                            "tcpin://HOST:PORT (listen for a TCP client), tcpout://HOST:PORT "
                            "(connect to a TCP server), serial:///dev/ttyX:BAUD (a serial "
                            "port), pty (a new pseudo-terminal); tcp:// is deprecated, as in "
                            "MAVSDK (default: %(default)s)")
    serve.add_argument("--clock", choices=CLOCK_MODES,
                       help="realtime for outside clients, lockstep for as fast as the CPU "
                            "allows (default: [sim] clock)")
    serve.add_argument("--duration", type=common.positive_float, metavar="SECONDS",
                       help="stop after this much simulated time (default: run until "
                            "interrupted)")
    serve.set_defaults(command=_sim_serve)

    record = actions.add_parser(
        "record", parents=[simulated, world], help="record a flight as a EuRoC dataset",
        description="Fly a smooth collision-free path through the world and write camera "
                    "images, ground-truth depth, IMU and ground truth in the EuRoC/ASL "
                    "layout (mav0/cam0, depth0, imu0, state_groundtruth_estimate0).")
    record.add_argument("--duration", type=common.positive_float, metavar="SECONDS",
                        help="simulated seconds to record (default: 40; with --timed, the "
                             "whole flight)")
    record.add_argument("--speed", type=common.positive_float, metavar="M/S",
                        help="cruise speed along the route, at most the vehicle's [vehicle] "
                             "xy_vel_max; the planner's flights cruise at up to [planner] "
                             "speed (default: 1 m/s, drivers/sim/record.py's SPEED)")
    record.add_argument("--along", type=Path, metavar="FLIGHT.mcap",
                        help="follow the true path of a recorded simulated flight, in its world "
                             "and seed (so not with --world or --seed; [sim] vehicle_seed flies "
                             "another vehicle), instead of the seed's route: the estimator "
                             "scored open loop on the places and at the speed a navigation "
                             "flight met (docs/vins.md)")
    record.add_argument("--timed", action="store_true",
                        help="with --along: fly the flight's own motion again in time (its "
                             "take-off, changes of speed, stops and turns, from its lift-off), "
                             "not a steady cruise along its path; not with --speed")
    record.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="dataset folder to create (must be new or empty)")
    record.set_defaults(command=_sim_record)

    fly = actions.add_parser(
        "fly", parents=[simulated, world, mission],
        help="fly the whole stack in the simulator",
        description="Start the simulator (mock PX4 over real MAVLink, rendered camera, "
                    "synthetic IMU) and fly the whole application against it: VINS, depth "
                    "network (the synthetic stand-in unless [depth_network] model is set), "
                    "rescaler and planner, from a start/goal pair of the world. Prints progress "
                    "and a summary, and draws the flown path over the world map.")
    fly.add_argument("--tracks", choices=TRACK_SOURCES, default="tracker",
                     help="the VINS's feature tracks: the tracker's; truth, the same tracks "
                          "with each pixel the true projection of the point it was born on, to "
                          "tell the tracker's error from the estimator's; early-error / "
                          "late-error, the truth's with the tracker's error of each track's "
                          "first six frames only / gathered after them only (ideal profile "
                          "only; docs/vins.md) (default: %(default)s)")
    fly.add_argument("--start-yaw", type=float, metavar="DEG",
                     help="heading the vehicle stands at before take-off, degrees "
                          "counter-clockwise from east (default: facing the first leg)")
    fly.add_argument("--go-after", type=common.non_negative_float, metavar="SECONDS",
                     help="the operator's go that many simulated seconds after the vehicle "
                          "is ready and waits for it, standing on the ground (default: the "
                          "command line is the go)")
    fly.add_argument("--clock", choices=CLOCK_MODES, default="lockstep",
                     help="lockstep: deterministic, as fast as the CPU allows; realtime: the "
                          "simulator in its own thread on the wall clock (default: %(default)s)")
    fly.add_argument("--link", choices=LINKS, default="udp",
                     help="how the application reaches the mock PX4: udp (loopback) or serial "
                          "(the mock on a pseudo-terminal, opened by the application as "
                          "serial:///dev/pts/N:921600, the code a flight controller on a UART "
                          "goes through) (default: %(default)s)")
    fly.add_argument("--fault", dest="faults", action="append", default=[],
                     metavar="KIND[@[MOMENT:]AFTER[+DURATION]]",
                     help="inject a fault AFTER seconds after MOMENT (one of "
                          f"{', '.join(MOMENTS)}; default cruise) for DURATION seconds "
                          f"(default: 1 s, for good): {', '.join(FAULT_KINDS)}; repeatable")
    fly.add_argument("--plot", type=common.png_path, metavar="PNG",
                     help=f"where to draw the top view of the flight (default: {DEFAULT_PLOT}, "
                          "where matplotlib, the [plots] extra, is installed)")
    fly.add_argument("--no-plot", action="store_true", help="draw no plot")
    common.add_record_flags(fly)
    common.add_json_flag(fly, instead_of="the summary table")
    fly.set_defaults(command=_sim_fly)

    soak = actions.add_parser(
        "soak", parents=[configured, world, mission],
        help="fly missions again and again, watching the process for leaks",
        description="Fly the simulated mission again and again in one process until MINUTES "
                    "of wall time have passed, sampling the process's memory, threads and "
                    "open files, and judge the soak: no growth past the bounds, no setpoint "
                    "deadline missed, every mission landed without a collision "
                    "(docs/reliability.md). Exit status 1 when it fails.")
    soak.add_argument("--minutes", type=common.positive_float, default=30.0,
                      help="wall time to soak for, and at least one mission after the "
                           "warm-up (default: %(default)s)")
    soak.add_argument("--warm-up", type=common.positive_int, default=3, metavar="MISSIONS",
                      help="missions flown before the baseline the rest are judged against "
                           "(default: %(default)s)")
    soak.add_argument("--clock", choices=CLOCK_MODES, default="realtime",
                      help="realtime, as on the vehicle, or lockstep (default: %(default)s)")
    common.add_json_flag(soak, instead_of="the verdict's lines")
    soak.set_defaults(command=_sim_soak)

    faults = actions.add_parser(
        "faults", parents=[configured],
        help="fly the fault matrix: every fault at each moment of a flight",
        description="Fly a short lockstep mission in the dome once per fault and moment "
                    "(take-off, cruise, near an obstacle, landing) and judge each outcome "
                    "against the behaviour docs/reliability.md documents for the fault. "
                    "Prints the matrix as a markdown table; exits 1 if any row failed.")
    faults.add_argument("--fault", dest="kinds", action="append", choices=MATRIX_FAULTS,
                        metavar="KIND", help="only this fault (repeatable; default: all of "
                                             f"{', '.join(MATRIX_FAULTS)})")
    faults.add_argument("--moment", dest="moments", action="append", choices=MOMENTS,
                        help="only this moment (repeatable; default: all)")
    faults.add_argument("--quick", action="store_true",
                        help="each fault once, the moments taken in turn (CI's reduced form)")
    faults.add_argument("--seed", type=common.non_negative_int, default=0,
                        help="seed of the world and the noise (default: %(default)s)")
    faults.add_argument("--workers", type=common.positive_int,
                        help="worker processes (default: the CPU count)")
    common.add_json_flag(faults, instead_of="the table")
    faults.set_defaults(command=_sim_faults)


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
    world = build_world(sim.world, sim.seed, sim.profile)

    def ready(vehicle) -> None:
        where = vehicle.px4.link.pty_path or args.mavlink
        print(f"serving a simulated PX4 quadrotor in {sim.world} (seed {sim.seed}, "
              f"{sim.clock} clock) on {where}", flush=True)

    try:
        summary = asyncio.run(sim_serve.serve(
            args.mavlink, world, seed=sim.seed, clock_mode=sim.clock,
            vehicle_options=config.vehicle, imu_options=config.imu.for_profile(sim.profile),
            px4_options=config.px4, baro_options=config.baro.for_profile(sim.profile),
            duration=args.duration, on_ready=ready))
    except KeyboardInterrupt:
        return common.EXIT_OK
    except (ValueError, OSError) as error:
        print(f"sim serve: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(f"served {summary.sim_time:.1f} s of simulated flight"
          + (f"; collision at t={summary.collision.time:.2f} s" if summary.collision else ""))
    return common.EXIT_OK


def _sim_record(args: argparse.Namespace, config: Config) -> int:
    from companion.recording.replay import ReplayError
    from drivers.sim import record
    from drivers.sim.render import RenderError

    try:
        sim, along = _recorded_along(args, config)
        # the flight's speed and height swing as the application's flights do; a timed one
        # flies its own
        wave, height_wave = (None, None) if args.timed else config.planner.waves
        duration = 40.0 if args.duration is None and not args.timed else args.duration
        summary = record.record_dataset(args.out, sim, config.camera, config.vehicle,
                                        config.imu, duration=duration,
                                        sim_camera=config.sim_camera, wave=wave,
                                        height_wave=height_wave,
                                        speed=record.SPEED if args.speed is None
                                        else args.speed, along=along, timed=args.timed)
    except (record.RecordError, RenderError, OSError, ReplayError) as error:
        print(f"sim record: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(f"recorded {summary.duration:g} s of {summary.world} route {summary.route} "
          f"({summary.frames} frames, {summary.imu_samples} IMU samples, path "
          f"{summary.path_length:.1f} m) into {args.out}")
    return common.EXIT_OK


def _recorded_along(args: argparse.Namespace, config: Config):
    """The [sim] options to record with and, with ``--along``, the flight, recorded in its
    world and seed (the world is built from the seed, so another would not hold the path:
    RecordError)."""
    from drivers.sim.record import RecordError

    if args.along is None:
        if args.timed:
            raise RecordError("--timed flies a recorded flight's motion again: give it --along")
        return _sim_options(args, config), None
    from companion.recording.replay import flown_path

    if args.world is not None or args.seed is not None:
        raise RecordError("--along flies the flight's own world and seed: drop --world and "
                          "--seed")
    if args.timed and args.speed is not None:
        raise RecordError("--timed flies the flight's own speeds: drop --speed")
    return config.sim, flown_path(args.along)


def _sim_fly(args: argparse.Namespace, config: Config) -> int:
    from companion.launch import simulated
    from companion.recording.live import LiveViewError
    from companion.recording.storage import RecordingError
    from drivers.sim.faults import Fault
    from drivers.sim.render import RenderError

    sim = _sim_options(args, config)
    plot = plot_destination(args)
    try:
        mission = simulated.SimMission(world=sim.world, seed=sim.seed, pair=args.pair,
                                       goal=args.goal, via=tuple(args.via),
                                       start_yaw_deg=args.start_yaw,
                                       clock=args.clock, depth=args.depth, link=args.link,
                                       tracks=args.tracks,
                                       faults=tuple(Fault.parse(f) for f in args.faults),
                                       go_after_s=args.go_after)
        summary = simulated.run(config, mission, plot=plot,
                                progress=None if args.json else common.print_progress,
                                record=common.recording_wanted(args, config), live=args.live)
    except (simulated.SimError, RenderError, RecordingError, LiveViewError, ValueError,
            OSError) as error:
        print(f"sim fly: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(summary) if args.json else simulated.format_summary(summary))
    # a fault-free flight must reach its goal; any flight must end without a collision
    safe = summary["collisions"] == 0 and summary["final_state"] == "landed"
    return common.EXIT_OK if safe and (summary["reached_goal"] or mission.faults) \
        else common.EXIT_FAILED


def plot_destination(args: argparse.Namespace) -> Path | None:
    """Where ``sim fly`` draws its top view: ``--plot``, else :data:`DEFAULT_PLOT`; nowhere with
    ``--no-plot``, nor by default where matplotlib (the ``plots`` extra) is missing, which the
    flight does not need: one line on stderr says so. (An explicit ``--plot`` without it is
    refused with the arguments, :func:`common.png_path`.)"""
    from companion.tools.plot import missing_extra

    if args.no_plot:
        return None
    if args.plot is not None:
        return args.plot
    missing = missing_extra()
    if missing is not None:
        print(f"sim fly: no top view drawn ({DEFAULT_PLOT}): {missing}", file=sys.stderr)
        return None
    return DEFAULT_PLOT


def _sim_soak(args: argparse.Namespace, config: Config) -> int:
    from companion.launch import simulated
    from companion.tools.soak import SoakOptions, soak
    from drivers.sim.render import RenderError

    sim = _sim_options(args, config)
    mission = simulated.SimMission(world=sim.world, seed=sim.seed, pair=args.pair,
                                   goal=args.goal, via=tuple(args.via), clock=args.clock,
                                   depth=args.depth)

    def report(record: dict) -> None:
        print(f"mission {record['mission']}: {record['final_state']}, "
              f"{'goal reached' if record['reached_goal'] else 'goal not reached'}, "
              f"{record['rss_mb']:.0f} MB ({record['python_blocks']} Python blocks), "
              f"{record['threads']} threads, "
              f"{record['open_files']} files, loop lag p99 {record['loop_lag_ms_p99']:.1f} ms",
              file=sys.stderr, flush=True)

    options = SoakOptions(minutes=args.minutes, warm_up_missions=args.warm_up)
    try:
        result = soak(lambda: simulated.run(config, mission), options, report)
    except (simulated.SimError, RenderError, ValueError, OSError) as error:
        print(f"sim soak: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{len(result['missions'])} missions in {result['minutes']:.1f} min: "
              + ("passed" if result["passed"] else "FAILED"))
        for problem in result["problems"]:
            print(f"  {problem}")
    return common.EXIT_OK if result["passed"] else common.EXIT_FAILED


def _sim_faults(args: argparse.Namespace, config: Config) -> int:
    from companion.tools import fault_matrix
    from companion.tools.eval.executor import ExecutorError, open_executor

    faults = fault_matrix.matrix_faults(args.kinds or fault_matrix.MATRIX_FAULTS,
                                        args.moments or fault_matrix.MOMENTS, quick=args.quick)

    def report(row: dict) -> None:
        print(f"{row['injected']}: {row['outcome']}"
              + ("" if row["passed"] else f" FAILED (allowed: {', '.join(row['allowed'])})"),
              file=sys.stderr, flush=True)

    try:
        executor = open_executor(None, args.workers, len(faults))
        result = fault_matrix.run_matrix(config, faults, seed=args.seed, executor=executor,
                                         progress=report)
    except ExecutorError as error:
        print(f"sim faults: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    if args.json:
        print(json.dumps(result))
    else:
        print(fault_matrix.markdown_table(result))
        for row in result["rows"]:
            if not row["passed"]:
                again = fault_matrix.rerun_command(row, args.seed, args.config_path,
                                                   args.overrides)
                print(f"failed: {again}")
    return common.EXIT_OK if result["passed"] else common.EXIT_FAILED

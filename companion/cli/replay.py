"""``companion replay``: a recorded flight through the stages again, under any config."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from companion.cli import common
from companion.config import Config, ConfigError


def add_commands(commands: argparse._SubParsersAction) -> None:
    replay = commands.add_parser(
        "replay", parents=[common.configured_parser()],
        help="replay a flight recording's camera and IMU through the VINS, depth and planner",
        description="Feed a recording's camera frames and IMU samples through the VINS, the "
                    "depth stage and the planner, as fast as the CPU allows, and report what "
                    "changed against the recording: depth accuracy where it has true depth "
                    "(simulated flights), planner decisions, stage timings. The config is the "
                    "recording's own, or --config FILE, with --set on top. See "
                    "docs/recording.md.")
    replay.add_argument("recording", type=Path, metavar="FILE", help="the .mcap recording")
    replay.add_argument("--plot", type=common.png_path, metavar="PNG",
                        help="also draw the recorded flight's estimated path over its world, "
                             "as sim fly does (simulated flights)")
    replay.add_argument("--until", type=common.positive_float, metavar="SECONDS", dest="until_s",
                        help="replay only the recording's first SECONDS (from its first "
                             "message), the recorded side compared over the same span")
    replay.add_argument("--vins-only", action="store_true",
                        help="replay the VINS alone, not the depth stage or the planner: its "
                             "error where navigation ended, for a VINS option, in about half "
                             "the time")
    common.add_json_flag(replay, instead_of="the table")
    replay.set_defaults(command=_replay)


def _replay(args: argparse.Namespace, config: Config) -> int:
    from companion.recording.replay import (ALL_STAGES, VINS_ONLY, ReplayError, plot,
                                            recorded_config, replay)

    try:
        chosen, mission = recorded_config(args.recording, args.overrides,
                                          Path(args.config_path) if args.config_path else None)
        if args.plot is not None:
            plot(args.recording, mission, chosen, args.plot)
        report = replay(args.recording, chosen, mission, args.until_s,
                        VINS_ONLY if args.vins_only else ALL_STAGES).as_dict()
    except ConfigError as error:
        print(f"replay: {error}", file=sys.stderr)
        return common.EXIT_USAGE
    except (ReplayError, OSError, ValueError) as error:
        print(f"replay: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    if args.plot is not None:
        report["plot"] = str(args.plot)
    print(json.dumps(report) if args.json else format_report(report))
    return common.EXIT_OK


def format_report(report: dict) -> str:
    lines = [f"  frames              {report['frames']} ({report['vins_same_frames']} with the "
             "flight's own VINS state)",
             *_lossy(report),
             f"  VINS lost frames    {report['vins_lost_frames']}",
             f"  VINS error          {_vins_error(report['vins_error'])}"]
    if "depth" in report["stages"]:
        lines += _depth_and_planner(report)
    else:
        lines.append("  (the VINS alone: no depth, planner or failsafes)")
    lines.append(f"  stage medians (ms)  {report['timings_ms']}")
    return "\n".join(lines)


def _lossy(report: dict) -> list[str]:
    """A line saying that JPEG images keep a replay from being the flight, when they did."""
    if not report["lossy_frames"]:
        return []
    return [f"  lossy images        {report['lossy_frames']} stored as JPEG, not the frames the "
            "flight tracked: the replay drifts from the flight, so read a config against the "
            "replay of the recording's own, or record with [recorder] camera_format = \"png\""]


def _depth_and_planner(report: dict) -> list[str]:
    agreement, failsafes = report["planner_agreement"], report["failsafes"]
    return [
        f"  depth AbsRel        recorded {report['abs_rel']['recorded']}, "
        f"replayed {report['abs_rel']['replayed']} (frames with truth: "
        f"{report['frames_with_depth']['recorded']}, {report['frames_with_depth']['replayed']})",
        f"  planner agreement   {'-' if agreement is None else f'{agreement:.1%}'} of "
        f"{report['planner_rounds']} rounds",
        f"  failsafes           recorded {_failsafes(failsafes['recorded'])}; replayed, first "
        f"{_failsafes([failsafes['replayed_first']] if failsafes['replayed_first'] else [])}",
        f"  frames without fit  {report['depth_failures'] or 'none'}",
    ]


def _vins_error(scored: dict | None) -> str:
    """The VINS's error where navigation ended, recorded and replayed (the path's scale in
    brackets), or why there is none."""
    if scored is None:
        return "- (no truth, or the VINS never tied to PX4's local frame)"

    def one(name: str) -> str:
        split = scored[name]["split"]
        scale = "" if split is None else f" (path scale {split['scale']:.4f})"
        return f"{name} {scored[name]['error_m']:.2f} m{scale}"
    return f"at {scored['at']} ({scored['t']:.1f} s): {one('recorded')}, {one('replayed')}"


def _failsafes(failsafes: list[dict]) -> str:
    return ", ".join(f"{f['reason']} at {f['t']:.1f} s" for f in failsafes) or "none"

"""``companion log``: what a flight recording holds (``info``), a simulated flight's VINS
against its truth (``vins``), where the navigation time went (``time``), and a recording cut
short by a crash or a power cut made a complete file again (``recover``); docs/recording.md."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from companion.cli import common
from companion.config import Config


def add_commands(commands: argparse._SubParsersAction) -> None:
    group = commands.add_parser("log", help="summarise or recover a flight recording",
                                description="Read the MCAP recordings the flight recorder "
                                            "writes (docs/recording.md).")
    actions = common.add_command_group(group)
    _action(actions, "info", _info, "the summary", help="summarise a recording",
            description="Summarise a recording: complete or truncated, its duration, each "
                        "channel's topic, schema and message count, the metadata, the "
                        "messages the recorder dropped and why, and the flight events and "
                        "failsafes. A truncated recording is summarised as far as it is "
                        "readable. Exits 1 with one line when FILE is missing or not MCAP.")
    vins = _action(
        actions, "vins", _vins, "the table (every frame)",
        help="the VINS's error against the truth over a simulated flight",
        description="Over a simulated flight's recording, the VINS's position error (metres) "
                    "and heading and tilt errors (degrees: pitch, positive nose low, and "
                    "roll, positive right side low) against where the simulator truly had the "
                    "vehicle, in PX4's local frame, at every --every seconds and wherever the "
                    "VINS's state changed (a reset, lost, degraded), with its landmarks: where "
                    "a drift began and what the VINS said of itself then; with --map, the "
                    "map's scale too. Exits 1 with one line when FILE cannot be read or holds "
                    "no truth (a real flight).")
    vins.add_argument("--every", type=float, default=2.0, metavar="SECONDS",
                      help="seconds between the table's rows (default: 2)")
    vins.add_argument("--map", action="store_true",
                      help="also each frame's map scale: the median of its tracked landmarks' "
                           "depth over the true depth there (reads the true depth images)")
    _action(actions, "time", _time, "the table", help="where a flight's navigation time went",
            description="Over a recording, the navigation phase (from the switch to Offboard "
                        "until the flight comes down) split by what the vehicle was doing: the "
                        "planner's arcs by speed tier, each glide and stop by its reason (no "
                        "safe primitive, gliding for parallax, backing off, the approach to a "
                        "waypoint, stopping to turn), turning in place, and the stops after "
                        "the goal or a failsafe; with the plans published and the median time "
                        "between arc rounds. Exits 1 with one line when FILE cannot be read or "
                        "never navigated.")
    recover = _action(
        actions, "recover", _recover, "one line",
        help="rewrite a truncated recording as a complete one",
        description="Write every readable message of FILE (a recording cut short by a crash, "
                    "a power cut or a full disk: everything up to its last complete chunk) "
                    "into OUT, a new, complete MCAP file that Foxglove and replay open. Exits "
                    "1 with one line when FILE cannot be read or OUT exists or cannot be "
                    "written.")
    recover.add_argument("out", type=Path, metavar="OUT", help="new file to write (.mcap)")


def _action(actions, name: str, command, json_instead_of: str,
            **texts) -> argparse.ArgumentParser:
    """A ``log`` action on a recording FILE, with ``--json`` printing instead of
    ``json_instead_of``; ``texts``: the parser's help and description."""
    action = actions.add_parser(name, **texts)
    action.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    common.add_json_flag(action, instead_of=json_instead_of)
    action.set_defaults(command=command, config_path=None, overrides=[])
    return action


def _info(args: argparse.Namespace, config: Config) -> int:
    from companion.recording import inspect

    try:
        summary = inspect.summarise(args.file)
    except inspect.InspectError as error:
        print(f"log info: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(summary) if args.json else inspect.format_summary(summary))
    return common.EXIT_OK


def _recover(args: argparse.Namespace, config: Config) -> int:
    from companion.recording import inspect

    try:
        result = inspect.recover(args.file, args.out)
    except inspect.InspectError as error:
        print(f"log recover: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    source = "complete" if result["complete"] else "truncated"
    print(json.dumps(result) if args.json else
          f"{args.out}: {result['messages']} messages from {args.file} ({source})")
    return common.EXIT_OK


def _vins(args: argparse.Namespace, config: Config) -> int:
    from dataclasses import asdict

    from companion.recording.replay import ReplayError, vins_error

    if not args.every > 0:
        print(f"log vins: --every must be above 0 seconds, got {args.every}", file=sys.stderr)
        return common.EXIT_FAILED
    try:
        samples = vins_error(args.file, with_map=args.map)
    except ReplayError as error:
        print(f"log vins: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    if args.json:
        print(json.dumps([asdict(sample) for sample in samples]))
    else:
        print(_vins_table(args.file, samples, args.every, args.map))
    return common.EXIT_OK


def _time(args: argparse.Namespace, config: Config) -> int:
    from dataclasses import asdict

    from companion.recording.replay import ReplayError, navigation_time

    try:
        spent = navigation_time(args.file)
    except ReplayError as error:
        print(f"log time: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(asdict(spent)) if args.json else _time_table(args.file, spent))
    return common.EXIT_OK


def _time_table(path: Path, spent) -> str:
    """The activities, longest first, with their share of the navigation phase."""
    gap = spent.arc_round_gap_s
    rate = f"every {gap:.3f} s ({1.0 / gap:.1f} Hz)" if gap else "-"
    lines = [f"{path}: {spent.seconds:.1f} s of navigation; {spent.plans} plans, "
             f"{spent.arc_rounds} of them arc rounds, median {rate}",
             "  seconds  share  activity"]
    for label, seconds in sorted(spent.activities.items(), key=lambda item: -item[1]):
        share = seconds / spent.seconds if spent.seconds > 0 else 0.0
        lines.append(f"  {seconds:7.1f}  {share:5.0%}  {label}")
    if spent.faster_tiers:
        lines += ["why not faster: the rounds that found nothing safe in a tier, and the "
                  "median share of its arcs blocked by an observed surface (the rest met "
                  "only unseen space)", "   rounds  blocked  tier"]
        lines += [f"  {tier['rounds']:7d}  {tier['blocked_share']:7.0%}  {speed}"
                  for speed, tier in spent.faster_tiers.items()]
    return "\n".join(lines)


def _displacement_line(split, least_m: float) -> str:
    """The error at the end taken apart: the path's scale and bearing, and the metres each
    and the height and start add."""
    if split is None:
        return f"error at the end not split: under {least_m:g} m flown from the first frame"
    return (f"error at the end over the {split.distance_m:.1f} m flown: scale "
            f"{split.scale:.4f} ({split.along_m:+.2f} m along), bearing "
            f"{split.bearing_deg:+.2f}° ({split.across_m:+.2f} m across), height "
            f"{split.height_m:+.2f} m, first frame {split.start_m:.2f} m off")


def _length_line(accrued: dict) -> str:
    """The path's length error by true speed: each band's seconds, metres and scale error."""
    bands = [f"{label} {band.seconds:.0f} s, {band.flown_m:.0f} m, "
             f"{100.0 * band.along_m / band.flown_m:+.2f} %" if band.flown_m > 0.0
             else f"{label} none" for label, band in accrued.items()]
    return "path length by speed: " + "; ".join(bands)


def _degrees(angle: float | None) -> str:
    """A table cell of ``angle`` degrees, signed; ``-`` where there is none."""
    return "      -" if angle is None else f"{angle:+6.2f}°"


def _vins_table(path: Path, samples: list, every: float, with_map: bool) -> str:
    """The rows every ``every`` seconds and at each change of the VINS's state, under lines
    with the error at the end, the largest and the median, the heading error's accrual, the
    error at the end split (:func:`_displacement_line`) and the path's length error by speed
    (:func:`_length_line`); ``with_map``, the map scale too."""
    if not samples:
        return f"{path}: no frame with both a VINS pose and the truth"
    from autonomy.trajectory import DISPLACEMENT_MIN_M
    from companion.recording.replay import (TURNING_RATE_DEG_S, displacement_split,
                                            heading_accrual, length_accrual)

    errors = [sample.error_m for sample in samples]
    largest = max(samples, key=lambda sample: sample.error_m)
    accrued = heading_accrual(samples)
    turning, straight = accrued["turning"], accrued["straight"]
    lines = [f"{path}: {len(samples)} frames, {samples[0].t:.1f}-{samples[-1].t:.1f} s; "
             f"VINS error at the end {samples[-1].error_m:.2f} m, largest {largest.error_m:.2f}"
             f" m (t {largest.t:.1f} s), median {sorted(errors)[len(errors) // 2]:.2f} m",
             f"heading error accrued turning (over {TURNING_RATE_DEG_S:g}°/s: "
             f"{turning.seconds:.1f} s, {turning.turned_deg:.0f}° turned) "
             f"{turning.error_change_deg:+.2f}°, flying straight ({straight.seconds:.1f} s) "
             f"{straight.error_change_deg:+.2f}°",
             _displacement_line(displacement_split(samples), DISPLACEMENT_MIN_M),
             _length_line(length_accrual(samples)),
             "      t     error   heading    pitch     roll  state        landmarks"
             + ("  map scale" if with_map else "")]
    next_row, state = samples[0].t, None
    for sample in samples:
        due = sample.t >= next_row
        if due or sample.state != state or sample is samples[-1]:
            scale = ("" if not with_map else "          -" if sample.map_scale is None
                     else f"      {sample.map_scale:.3f}")
            lines.append(f"{sample.t:7.2f}  {sample.error_m:6.2f} m  {sample.heading_deg:+6.2f}°  "
                         f"{_degrees(sample.pitch_deg)}  {_degrees(sample.roll_deg)}  "
                         f"{sample.state:<12} {sample.landmarks:4d}{scale}")
        if due:
            next_row = sample.t + every
        state = sample.state
    return "\n".join(lines)

"""The fault matrix: every fault the simulator injects, at each moment of one flight, each
flight judged against what docs/reliability.md promises for that fault (issue 27).

The flight (:data:`MATRIX_GOAL`): from the dome's first start to a goal 12 m east, past an
obstacle the fault-free flight comes within about 1.2 m of; 20 simulated seconds, lockstep, so
it has a take-off, a cruise, a close pass and a landing and the whole matrix stays affordable.
Each fault starts :data:`FAULT_DELAY_S` after its moment (:data:`drivers.sim.faults.MOMENTS`)
and lasts for good, or as :data:`FAULT_DURATION_S` says for the faults the stack must see
recover (a link back, an IMU back).

A flight's outcome (:func:`outcome`):

===============  ==========================================================================
``reached``      landed at the goal with no failsafe (the fault was absorbed)
``failsafe``     a failsafe stopped the flight: it held, then landed where it was
``aborted``      PX4 stopped the motors in the air; the companion commanded nothing more
``short``        landed away from the goal with no failsafe named
``collision``    hit an obstacle
``not injected`` the fault's moment never came: the row proves nothing
``error``        the application raised
===============  ==========================================================================

A row passes when its outcome is one the fault allows at that moment (:func:`allowed`); a
``collision``, an ``error`` or ``not injected`` never passes.
"""

from __future__ import annotations

import dataclasses
import math
import shlex
import tempfile
import traceback
from typing import Callable, Iterable, Sequence

from drivers.sim.faults import FAULT_KINDS, MOMENTS, Fault

#: The matrix's flight: from the dome's pair 0 start (-23, -15) to 12 m east, at 1.5 m.
MATRIX_WORLD = "dome"
MATRIX_GOAL = (-11.0, -15.0, 1.5)
#: Seconds after its moment that a fault starts.
FAULT_DELAY_S = 0.5
#: Faults that end, and how long they last, seconds; the others last for good.
FAULT_DURATION_S = {"imu_gap": 2.0, "link_cut": 3.0, "camera_blackout": 1.5,
                    "packet_loss": 3.0}
#: ``loop_stall`` is left out: it needs the real-time clock (in lockstep the simulator shares
#: the stalled loop), and tests/test_flight_realtime.py flies it.
MATRIX_FAULTS = tuple(kind for kind in FAULT_KINDS if kind != "loop_stall")

#: The faults the stack absorbs (duplicates and reordering dropped and counted; the TIMESYNC
#: estimate held; the recording stopped, the flight not): the flight goes on to the goal.
ABSORBED = {"imu_repeat", "imu_reorder", "frame_repeat", "frame_reorder", "timesync_stop",
            "disk_full"}
#: The faults where PX4 stops the motors: the companion must not command a falling vehicle.
MOTORS_STOPPED = {"disarm", "px4_reboot"}


def allowed(kind: str, moment: str) -> frozenset[str]:
    """The outcomes that are the documented safe behaviour for ``kind`` at ``moment``.

    - Absorbed faults: ``reached``.
    - The motors stopped: ``aborted``. At ``landing`` the landing's own end is a disarm, so
      the companion counts the vehicle landed (``reached`` or ``short``); nothing more is
      commanded either way.
    - Every other fault is a failsafe (stop, hold, land) while the flight is guarded; at
      ``landing`` the landing goes on (it is the failsafe's own end): ``reached`` or
      ``short``. At ``takeoff`` the vehicle climbing under PX4's own control is not yet
      guarded, so the fault may be seen only once it is (``failsafe``) or, if it ended by
      then, not at all (``reached``).
    """
    if kind in ABSORBED:
        return frozenset({"reached"})
    if kind in MOTORS_STOPPED:
        return frozenset({"aborted", "reached", "short"} if moment == "landing" else {"aborted"})
    if moment == "landing":
        return frozenset({"reached", "short"})
    if moment == "takeoff" and kind in FAULT_DURATION_S:
        return frozenset({"failsafe", "reached"})
    return frozenset({"failsafe"})


def matrix_faults(kinds: Iterable[str] = MATRIX_FAULTS, moments: Iterable[str] = MOMENTS,
                  quick: bool = False) -> list[Fault]:
    """The rows: every kind at every moment, or (``quick``, CI's reduced form) each kind once,
    the moments taken in turn so that every moment is flown."""
    kinds, moments = list(kinds), list(moments)
    for kind in kinds:
        if kind not in MATRIX_FAULTS:
            raise ValueError(f"{kind!r} is not in the matrix; choose from "
                             f"{', '.join(MATRIX_FAULTS)}")
    for moment in moments:
        if moment not in MOMENTS:
            raise ValueError(f"unknown moment {moment!r}; choose from {', '.join(MOMENTS)}")
    pairs = ([(kind, moments[k % len(moments)]) for k, kind in enumerate(kinds)] if quick
             else [(kind, moment) for kind in kinds for moment in moments])
    return [Fault(kind, FAULT_DELAY_S, FAULT_DURATION_S.get(kind, math.inf), moment)
            for kind, moment in pairs]


def outcome(summary: dict, fault: Fault) -> str:
    """The flight's outcome (module docstring) from its summary."""
    if summary["collisions"]:
        return "collision"
    if fault.moment not in summary["fault_moments"]:
        return "not injected"
    if summary["final_state"] == "aborted":
        return "aborted"
    if summary["failsafes"]:
        return "failsafe"
    return "reached" if summary["reached_goal"] else "short"


def fly_row(shared: tuple, fault: Fault) -> dict:
    """One row: the matrix's flight with ``fault`` (``shared``: the config and the world's
    seed); an exception is the ``error`` outcome with its traceback, never the run's end."""
    from companion.launch import simulated

    config, seed = shared
    mission = simulated.SimMission(world=MATRIX_WORLD, seed=seed, goal=MATRIX_GOAL,
                                   faults=(fault,))
    row = {"fault": fault.kind, "moment": fault.moment, "injected": str(fault),
           "allowed": sorted(allowed(fault.kind, fault.moment))}
    recorded = fault.kind == "disk_full"
    try:
        with tempfile.TemporaryDirectory(prefix="companion-faults-") as scratch:
            summary = simulated.run(_recording_into(config, scratch) if recorded else config,
                                    mission, record=recorded)
    except Exception:  # noqa: BLE001 - the row records it: the matrix is there to find these
        return {**row, "outcome": "error", "passed": False, "error": traceback.format_exc()}
    result = outcome(summary, fault)
    counters = summary["autopilot_counters"]
    return {**row, "outcome": result, "passed": result in row["allowed"],
            "final_state": summary["final_state"], "failsafes": summary["failsafes"],
            "moment_t": summary["fault_moments"].get(fault.moment),
            "min_clearance_m": summary["min_clearance_m"],
            "vins_resets": summary["vins_resets"],
            "frames_out_of_order": summary["frames_out_of_order"],
            "frames_stale": summary["frames_stale"],
            "imu_dropped": {key[4:]: n for key, n in counters.items()
                            if key.startswith("imu_") and key != "imu_interval_requests" and n},
            "watchdog_setpoints": summary["watchdog_setpoints"],
            "recording_error": (summary.get("recording") or {}).get("error")}


def _recording_into(config, directory: str):
    """``config`` recording into ``directory``: for the one fault that needs a recorded flight
    (``disk_full``); the other rows fly unrecorded, as the recorder costs CPU."""
    return dataclasses.replace(config, recorder=dataclasses.replace(config.recorder,
                                                                    directory=directory))


def run_matrix(config, faults: list[Fault], *, seed: int = 0, executor,
               progress: Callable[[dict], None] | None = None) -> dict:
    """Fly every row on ``executor`` (:mod:`companion.tools.eval.executor`); the rows in the
    order given, and whether all passed."""
    rows: list[dict | None] = [None] * len(faults)
    for index, row in executor.run(fly_row, (config, seed), faults):
        rows[index] = row
        if progress is not None:
            progress(row)
    return {"goal": list(MATRIX_GOAL), "world": MATRIX_WORLD, "seed": seed, "rows": rows,
            "passed": all(row["passed"] for row in rows)}


def markdown_table(result: dict) -> str:
    """The matrix as docs/reliability.md shows it: a row per fault, a column per moment, each
    cell the outcome (and the first failsafe, without its figures), failed cells marked."""
    moments = [m for m in MOMENTS if any(r["moment"] == m for r in result["rows"])]
    cells: dict[tuple[str, str], str] = {}
    for row in result["rows"]:
        text = row["outcome"]
        if row.get("failsafes"):
            text += f": {row['failsafes'][0].split(' (')[0]}"
        cells[row["fault"], row["moment"]] = text if row["passed"] else f"**FAIL** {text}"
    kinds = list(dict.fromkeys(row["fault"] for row in result["rows"]))
    lines = ["| fault | " + " | ".join(moments) + " |",
             "|---|" + "---|" * len(moments)]
    for kind in kinds:
        lines.append(f"| `{kind}` | " + " | ".join(cells.get((kind, m), "") for m in moments)
                     + " |")
    return "\n".join(lines)


def rerun_command(row: dict, seed: int, config_path: str | None = None,
                  overrides: Sequence[str] = ()) -> str:
    """The ``sim fly`` command that flies ``row`` again, to look at it, with the matrix's
    config file (``config_path``; None: all defaults, which ``sim fly`` reads from
    config/sim.toml, its own defaults being the realistic vehicle) and ``overrides``."""
    goal = ",".join(f"{v:g}" for v in MATRIX_GOAL)
    settings = "".join(f" --set {shlex.quote(text)}" for text in overrides)
    return (f"companion sim fly --config {shlex.quote(config_path or 'config/sim.toml')}"
            f"{settings} --world {MATRIX_WORLD} --seed {seed} --goal={goal} "
            f"--fault {row['injected']}")

"""The fault matrix (companion/tools/fault_matrix.py, issue 27): which outcomes each fault
allows, how a flight's summary is judged, and the command's reduced form as CI runs it: every
fault once, the moments taken in turn, each flight over real MAVLink in lockstep.

The full matrix (every fault at every moment) is a documented run, docs/reliability.md."""

from __future__ import annotations

import json

import pytest

from companion.cli import main
from companion.tools import fault_matrix
from companion.tools.fault_matrix import (MATRIX_FAULTS, allowed, markdown_table, matrix_faults,
                                          outcome)
from drivers.sim.faults import MOMENTS, Fault

#: What the first failsafe may name, for the faults that stop the flight: the fault itself, or
#: what it did first (the IMU silent behind a cut link; during the climb, where the failsafes
#: wait for the flight to be guarded, a VINS reset, or after an IMU gap the VINS lost until it
#: can restart; a stale camera's frames refused, numbered as the last one taken).
FAILSAFE_NAMES = {"camera_freeze": ("camera silent",), "camera_blackout": ("VINS",),
                  "camera_stale": ("camera silent",),
                  "imu_gap": ("IMU silent", "VINS lost (IMU back after a gap"),
                  "link_cut": ("MAVLink link lost", "IMU silent", "VINS reset in flight"),
                  "network_nan": ("no metric depth",), "network_const": ("no metric depth",),
                  "packet_loss": ("MAVLink link lost", "IMU silent", "VINS")}


def summary(**changes) -> dict:
    """A flight's summary as simulated.run gives it, reaching its goal unless changed."""
    return {"collisions": 0, "fault_moments": {"takeoff": 2.0, "cruise": 4.5},
            "final_state": "landed", "failsafes": [], "reached_goal": True, **changes}


def test_the_quick_form_flies_every_fault_once_and_every_moment():
    rows = matrix_faults(quick=True)
    assert [f.kind for f in rows] == list(MATRIX_FAULTS)
    assert {f.moment for f in rows} == set(MOMENTS)
    assert len(matrix_faults()) == len(MATRIX_FAULTS) * len(MOMENTS)
    assert "loop_stall" not in MATRIX_FAULTS  # real time only: its own test


@pytest.mark.parametrize("kinds, moments, words", [
    (["gremlins"], MOMENTS, "'gremlins' is not in the matrix"),
    (["loop_stall"], MOMENTS, "'loop_stall' is not in the matrix"),
    (["imu_gap"], ["later"], "unknown moment 'later'"),
])
def test_a_row_outside_the_matrix_is_refused_by_name(kinds, moments, words):
    with pytest.raises(ValueError, match=words):
        matrix_faults(kinds, moments)


def test_what_each_kind_of_fault_may_end_in():
    assert allowed("frame_repeat", "cruise") == {"reached"}
    assert allowed("px4_reboot", "obstacle") == {"aborted"}
    assert allowed("camera_freeze", "cruise") == {"failsafe"}
    assert allowed("camera_freeze", "landing") == {"reached", "short"}
    assert allowed("link_cut", "takeoff") == {"failsafe", "reached"}  # it may end unseen
    assert allowed("camera_freeze", "takeoff") == {"failsafe"}  # for good: it must be seen
    for kind in MATRIX_FAULTS:
        for moment in MOMENTS:
            assert not {"collision", "error", "not injected"} & allowed(kind, moment)


def test_a_flights_outcome_comes_from_its_summary():
    at_cruise = Fault("imu_gap", moment="cruise")
    assert outcome(summary(), at_cruise) == "reached"
    assert outcome(summary(reached_goal=False), at_cruise) == "short"
    assert outcome(summary(failsafes=["IMU silent"], reached_goal=False), at_cruise) == \
        "failsafe"
    assert outcome(summary(final_state="aborted", failsafes=["x"]), at_cruise) == "aborted"
    assert outcome(summary(collisions=1, final_state="aborted"), at_cruise) == "collision"
    # the obstacle moment never came: whatever happened, the fault did not
    assert outcome(summary(), Fault("imu_gap", moment="obstacle")) == "not injected"


def test_an_application_that_raises_is_an_error_row_and_the_matrix_goes_on(monkeypatch):
    from companion.launch import simulated

    def broken(config, mission, **options):
        raise RuntimeError("perception failed")
    monkeypatch.setattr(simulated, "run", broken)
    row = fault_matrix.fly_row((None, 0), Fault("imu_gap", 0.5, 2.0, "cruise"))
    assert row["outcome"] == "error" and not row["passed"]
    assert "RuntimeError: perception failed" in row["error"]


def test_the_table_marks_a_failed_cell_and_names_the_failsafe():
    rows = [{"fault": "imu_gap", "moment": "cruise", "outcome": "failsafe",
             "failsafes": ["IMU silent"], "passed": True},
            {"fault": "imu_gap", "moment": "landing", "outcome": "collision", "failsafes": [],
             "passed": False}]
    table = markdown_table({"rows": rows}).splitlines()
    assert table[0] == "| fault | cruise | landing |"
    assert table[2] == "| `imu_gap` | failsafe: IMU silent | **FAIL** collision |"


def test_the_quick_matrix_ends_every_fault_in_its_documented_safe_behaviour(capsys):
    """CI's reduced form of `companion sim faults`: each fault once, at take-off, in cruise,
    near an obstacle or while landing, on real MAVLink; every row in the outcome its fault
    allows, and the detail behind it: the failsafe named, duplicates and reordering dropped
    and counted, no missed setpoint deadline, no collision."""
    code = main(["sim", "faults", "--quick", "--workers", "1", "--json"])
    result = json.loads(capsys.readouterr().out)
    rows = {row["fault"]: row for row in result["rows"]}
    failed = [(r["injected"], r["outcome"], r.get("failsafes"), r.get("error"))
              for r in result["rows"] if not r["passed"]]
    assert code == 0 and result["passed"] and not failed, failed
    assert set(rows) == set(MATRIX_FAULTS)
    for kind, row in rows.items():
        assert row["moment_t"] is not None and row["min_clearance_m"] > 0.0, row
        assert row["watchdog_setpoints"] == 0, row
        if row["outcome"] == "failsafe":
            assert row["failsafes"][0].startswith(FAILSAFE_NAMES[kind]), row
    assert rows["frame_repeat"]["frames_out_of_order"] > 0
    assert rows["frame_reorder"]["frames_out_of_order"] > 0
    assert rows["camera_stale"]["frames_stale"] > 0
    for kind in ("imu_repeat", "imu_reorder"):  # a repeated stamp does not go forward either
        assert rows[kind]["imu_dropped"].get("backwards", 0) > 0, rows[kind]
    assert rows["px4_reboot"]["failsafes"][-1] == "PX4 disarmed the vehicle in the air"
    # the full disk stopped the recording, not the flight
    assert rows["disk_full"]["recording_error"].startswith("File too large")


def test_a_failed_rows_command_flies_that_row_again():
    fault = Fault("imu_gap", 0.5, 2.0, "obstacle")
    command = fault_matrix.rerun_command({"injected": str(fault)}, seed=3).split()
    assert command[:3] == ["companion", "sim", "fly"]
    # the matrix on all defaults: sim fly's own defaults are the realistic vehicle
    assert command[command.index("--config") + 1] == "config/sim.toml"
    assert command[command.index("--world") + 1] == fault_matrix.MATRIX_WORLD
    assert command[command.index("--seed") + 1] == "3"
    assert Fault.parse(command[command.index("--fault") + 1]) == fault
    mine = fault_matrix.rerun_command({"injected": str(fault)}, 3, "my vehicle.toml",
                                      ["vins.window=8"])
    assert " --config 'my vehicle.toml' --set vins.window=8 " in mine

"""The one failsafe lockstep cannot show: the application's event loop stalled, in real time.

In lockstep the simulator shares the application's loop and clock, so a stalled loop stalls
simulated time with it. Here the simulator runs in its own thread on the wall clock, the
application's stages in worker threads, as on the vehicle; the watchdog thread must send the
stop while the loop is blocked. Its own module: a real-time flight wants the machine to itself,
not beside the minutes-long lockstep flights of ``test_flight_sim``.
"""

from __future__ import annotations

import pytest

from companion import simfly
from companion.config import Config
from drivers.sim.faults import Fault

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def test_an_event_loop_stall_is_caught_by_the_watchdog_in_real_time():
    mission = simfly.SimMission(world="dome", faults=(Fault.parse("loop_stall@1+1.5"),),
                                clock="realtime")
    summary = simfly.run(Config(), mission)
    assert summary["collisions"] == 0, summary["collision"]
    assert summary["final_state"] == "landed", summary["transitions"]
    assert summary["watchdog_setpoints"] > 0
    assert any(r.startswith(("event loop stalled", "setpoint deadline missed"))
               for r in summary["failsafes"]), summary["failsafes"]

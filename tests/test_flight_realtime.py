"""The one failsafe lockstep cannot show: the application's event loop stalled, in real time.

In lockstep the simulator shares the application's loop and clock, so a stalled loop stalls
simulated time with it. Here the simulator runs in its own thread on the wall clock, the
application's stages in worker threads, as on the vehicle; the watchdog thread must send the
stop while the loop is blocked. Its own module: a real-time flight wants the machine to itself,
not beside the minutes-long lockstep flights of ``test_flight_sim``: it is marked ``realtime``,
which the README's test command runs after the rest, alone.

On a shared two-core host the real-time pipeline can fall behind for seconds, and the
camera, IMU and depth monitors would rightly stop the flight before the stall comes (what
they catch is tested in lockstep). So this flight flies on true depth (no network to run)
with those three timeouts widened (0.5, 0.25 and 1 s to 2, 1 and 3 s), and the stall is what
it must catch: after it the loop's lag is checked before the sensors' ages.
"""

from __future__ import annotations

from dataclasses import replace

import pytest

from companion.launch import simulated
from companion.config import Config
from drivers.sim.faults import Fault

pytestmark = [pytest.mark.filterwarnings("ignore::DeprecationWarning"), pytest.mark.realtime]


def test_an_event_loop_stall_is_caught_by_the_watchdog_in_real_time():
    mission = simulated.SimMission(world="dome", faults=(Fault.parse("loop_stall@1+1.5"),),
                                clock="realtime", depth="truth")
    flight = replace(Config().flight, camera_timeout_s=2.0, imu_timeout_s=1.0,
                     depth_timeout_s=3.0)
    summary = simulated.run(replace(Config(), flight=flight), mission)
    assert summary["collisions"] == 0, summary["collision"]
    assert summary["final_state"] == "landed", summary["transitions"]
    assert summary["watchdog_setpoints"] > 0
    assert any(r.startswith(("event loop stalled", "setpoint deadline missed"))
               for r in summary["failsafes"]), summary["failsafes"]

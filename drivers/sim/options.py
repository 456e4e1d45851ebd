"""What the simulator runs: which world, from which seed, on which clock; and the config
tables the simulator reads (:data:`CONFIG_SECTIONS`)."""

from __future__ import annotations

from dataclasses import dataclass

from autonomy.options import option, validate
from drivers.sim.baro import BaroOptions
from drivers.sim.imu import ImuOptions
from drivers.sim.mock_px4 import Px4Options
from drivers.sim.quadrotor import VehicleOptions
from drivers.sim.sensor import SensorOptions

WORLD_NAMES = ("mine", "sewer", "dome")
CLOCK_MODES = ("lockstep", "realtime")
#: How faithful the simulated sensors are: ``ideal`` (exact images, timestamps and mounting,
#: an IMU with white noise and bias walk only: for debugging the stack) or ``realistic`` (every
#: error source of docs/simulator.md at its cited value).
PROFILES = ("ideal", "realistic")


@dataclass(frozen=True)
class SimOptions:
    """The simulated run. The same seed gives the same world, sensor noise and path; the
    vehicle seed, the same vehicle."""

    world: str = option("dome", choices=WORLD_NAMES, doc="the world flown in")
    seed: int = option(0, ge=0, doc="seed of the world, the sensor noise and the recorded path")
    vehicle_seed: int = option(
        -1, ge=-1,
        doc="seed of the errors a vehicle keeps from flight to flight (the IMU's scale and "
        "misalignment, the camera's mounting error), so that two seeds can fly one vehicle; "
        "-1: the run's seed",
    )
    noise_seed: int = option(
        -1, ge=-1,
        doc="seed of the sensors' noise on one flight (white noise, bias walk and turn-on "
        "bias, the camera's noise, stamps and lost frames, the link's losses), so that one "
        "world, route and vehicle can be flown again with a fresh draw of noise alone; -1: "
        "the run's seed",
    )
    clock: str = option(
        "realtime",
        choices=CLOCK_MODES,
        doc="lockstep: simulated time as fast as the CPU allows, deterministic; "
        "realtime: paced by the wall clock, for outside MAVLink clients",
    )

    camera_counter: bool = option(
        True,
        doc="the simulated camera numbers its frames, as a RealSense or an OAK does, so that a "
        "stale buffer (the camera_stale fault) repeats its number and the application refuses "
        "it; false: a camera without numbers (a V4L2 webcam through OpenCV), whose stale "
        "buffer only the VINS's blind failsafe catches",
    )
    profile: str = option(
        "ideal",
        choices=PROFILES,
        doc="ideal: exact sensors, for debugging; realistic: the camera, IMU and calibration "
        "errors of a real vehicle at their cited values (docs/simulator.md)",
    )

    def __post_init__(self) -> None:
        validate(self)

    def vehicle_for(self, seed: int) -> int:
        """The seed of the vehicle's own errors on a flight of ``seed``: ``vehicle_seed``, or
        ``seed`` when that is -1."""
        return seed if self.vehicle_seed < 0 else self.vehicle_seed

    def noise_for(self, seed: int) -> int:
        """The seed of the sensors' noise on a flight of ``seed``: ``noise_seed``, or ``seed``
        when that is -1."""
        return seed if self.noise_seed < 0 else self.noise_seed


@dataclass(frozen=True)
class LatencyOptions:
    """How long the target computer takes for each stage's main computation, charged to
    simulated time in lockstep by the realistic profile (companion.flight.workers). Defaults:
    the paper's vehicle (a Jetson Orin; Yang et al.: depth at 15 Hz with the network under
    TensorRT, planning at 12 Hz) and, for the VINS, which the paper does not time, this
    project's own front-end and back-end medians (docs/benchmarks.md)."""

    network_s: float = option(1.0 / 15.0, ge=0.0, le=1.0,
                              doc="one depth inference, seconds (the paper: 15 Hz)")
    planner_s: float = option(1.0 / 12.0, ge=0.0, le=1.0,
                              doc="one planning round, seconds (the paper: 12 Hz)")
    vins_s: float = option(0.017, ge=0.0, le=1.0,
                           doc="one VINS frame, front-end and keyframe back-end, seconds "
                               "(docs/benchmarks.md: 8 + 9 ms medians on the 2-core host)")

    def __post_init__(self) -> None:
        validate(self)

    def per_stage(self) -> dict[str, float]:
        """Seconds by worker name (companion.flight.app.WORKERS)."""
        return {"vins": self.vins_s, "network": self.network_s, "planner": self.planner_s}


#: The simulator's own tables of the application's config, by name: ``companion.config`` adds
#: them after the flight's. The flight process reads none of them (the estimator's IMU noise
#: model is ``[vins_imu]``, not the simulated IMU's ``[imu]``).
CONFIG_SECTIONS = {"sim": SimOptions, "vehicle": VehicleOptions, "imu": ImuOptions,
                   "baro": BaroOptions, "sim_camera": SensorOptions,
                   "sim_latency": LatencyOptions, "px4": Px4Options}

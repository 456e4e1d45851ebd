"""What the simulator runs: which world, from which seed, on which clock."""

from __future__ import annotations

from dataclasses import dataclass

from autonomy.options import option, validate

WORLD_NAMES = ("mine", "sewer", "dome")
CLOCK_MODES = ("lockstep", "realtime")


@dataclass(frozen=True)
class SimOptions:
    """The simulated run. The same seed gives the same world, sensor noise and path."""

    world: str = option("dome", choices=WORLD_NAMES, doc="the world flown in")
    seed: int = option(0, ge=0, doc="seed of the world, the sensor noise and the recorded path")
    clock: str = option(
        "realtime",
        choices=CLOCK_MODES,
        doc="lockstep: simulated time as fast as the CPU allows, deterministic; "
        "realtime: paced by the wall clock, for outside MAVLink clients",
    )

    def __post_init__(self) -> None:
        validate(self)

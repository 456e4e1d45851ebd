"""Test-wide settings.

The application's single OpenBLAS thread (companion/__init__.py) holds for every test.

Under CI (the environment variable CI is set, as `.ci/run` runs) hypothesis draws the same
examples every run, so a submission's result does not depend on the draw; a developer's runs
keep exploring new examples and its database replays any failure found.
"""

import os

# Before anything imports numpy: one OpenBLAS thread, as the application runs
# (companion/__init__.py says why); the simulated flights' subprocesses inherit it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture(scope="session")
def opengl():
    """Skips the test where the simulator's renderer has no OpenGL (EGL) here."""
    from drivers.camera.options import CameraOptions
    from drivers.sim.render import Renderer, RenderError
    from drivers.sim.world import build_world

    try:
        Renderer(build_world("dome", 0), CameraOptions(width=16, height=16).pinhole()).close()
    except RenderError as error:
        pytest.skip(f"EGL/OpenGL unavailable here: {error}")


@pytest.fixture(scope="session")
def record_flight(tmp_path_factory):
    """``record_flight(world, seconds)``: the folder of a simulated flight (seed 0) recorded
    once per test session; skips the test when OpenGL is unavailable here."""
    from drivers.camera.options import CameraOptions
    from drivers.sim.imu import ImuOptions
    from drivers.sim.options import SimOptions
    from drivers.sim.record import record_dataset
    from drivers.sim.render import RenderError
    from drivers.sim.quadrotor import VehicleOptions

    recorded = {}

    def record(world: str, seconds: float):
        key = (world, seconds)
        if key not in recorded:
            root = tmp_path_factory.mktemp(f"flight_{world}_{seconds:g}s")
            try:
                record_dataset(root, SimOptions(world=world, seed=0), CameraOptions(),
                               VehicleOptions(), ImuOptions(), duration=seconds)
            except RenderError as error:
                pytest.skip(f"EGL/OpenGL unavailable here: {error}")
            recorded[key] = root
        return recorded[key]

    return record

"""Test-wide settings.

The application's single OpenBLAS thread and pinned kernels (companion/__init__.py) hold for
every test.

Under CI (the environment variable CI is set, as `.ci/run` runs) hypothesis draws the same
examples every run, so a submission's result does not depend on the draw; a developer's runs
keep exploring new examples and its database replays any failure found.
"""

import os
from pathlib import Path

# Before anything imports numpy: OpenBLAS's threads and kernels as the application runs them
# (companion/__init__.py says why); the simulated flights' subprocesses inherit them.
import companion  # noqa: F401

import asyncio  # noqa: E402
import threading  # noqa: E402

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

#: The test files that fly the most simulated seconds, costliest first (CPU seconds measured
#: 2026-12-01, README "Tests"). The workers take whole files in collection order (pyproject's
#: ``--dist loadfile --no-loadscope-reorder``), so these go first: a run that ends on one of
#: them keeps one worker flying for minutes while the other has nothing left to do. The
#: other files follow in pytest's order.
COSTLIEST_FILES = (
    "test_flight_sim.py", "test_fault_matrix.py", "test_flight_failsafes.py",
    "test_vins_depth_acceptance.py", "test_replay.py", "test_eval_nav.py", "test_flight_go.py",
    "test_vins_gyro_alignment.py", "test_vins_time_offset.py", "test_flight_serial.py",
    "test_vins_estimator.py", "test_eval_rescale.py", "test_recording_live.py",
    "test_sim_world.py", "test_soak.py",
)
_renamed = [name for name in COSTLIEST_FILES if not (Path(__file__).parent / name).is_file()]
if _renamed:  # a renamed file would silently go last again
    raise ImportError(f"tests/conftest.py: COSTLIEST_FILES names no such file: {_renamed}")


def pytest_collection_modifyitems(items):
    """The costliest files first (:data:`COSTLIEST_FILES`); the sort is stable, so each
    file's tests keep their order."""
    rank = {name: k for k, name in enumerate(COSTLIEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


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


@pytest.fixture
def served_vehicle():
    """The simulator serving udpin://127.0.0.1:PORT in real time, as `companion sim serve`
    would, in a background thread; yields ``(port, outcome)``, where ``outcome["sim"]`` is the
    running simulation once it is ready. Fails the test if serving raised or did not stop."""
    from drivers.sim.host import free_udp_port
    from drivers.sim.serve import serve

    port = free_udp_port()
    stop = threading.Event()
    outcome = {}

    def run():
        try:
            outcome["summary"] = asyncio.run(serve(
                f"udpin://127.0.0.1:{port}", None, clock_mode="realtime", stop=stop,
                duration=120.0, on_ready=lambda sim: outcome.setdefault("sim", sim)))
        except BaseException as error:  # reported by the test, not lost in the thread
            outcome["error"] = error

    thread = threading.Thread(target=run, name="sim-serve", daemon=True)
    thread.start()
    yield port, outcome
    stop.set()
    thread.join(timeout=10)
    assert not thread.is_alive(), "the served simulator did not stop"
    assert "error" not in outcome, outcome.get("error")

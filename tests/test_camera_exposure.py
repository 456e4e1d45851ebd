"""The auto-exposure law the host-run auto-exposure and the simulated camera share
(drivers/camera/exposure.py), and the vehicle presets' limit against the simulator's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from drivers.camera.exposure import ExposureLaw, mean_level

LAW = ExposureLaw(target=0.4, rate=0.5, min_s=1e-4, max_s=8e-3, gain_max=16.0)
PRESETS = sorted((Path(__file__).parent.parent / "config").glob("orin-*.toml"))


def test_a_frame_at_the_target_level_keeps_its_exposure():
    assert LAW.step(4e-3, 0.4) == pytest.approx(4e-3)


def test_the_step_is_the_damped_ratio_of_target_to_measured_level():
    assert LAW.step(2e-3, 0.1) == pytest.approx(2e-3 * (0.4 / 0.1) ** 0.5)
    assert LAW.step(2e-3, 0.8) == pytest.approx(2e-3 * (0.4 / 0.8) ** 0.5)


def test_repeated_steps_on_a_linear_sensor_converge_to_the_target():
    """A scene whose level is proportional to exposure x gain: the loop settles on the
    product that gives the target."""
    radiance, product = 30.0, 1e-3  # level = radiance x product
    for _ in range(40):
        product = LAW.step(product, min(1.0, radiance * product))
    assert radiance * product == pytest.approx(0.4, rel=1e-3)


def test_exposure_rises_to_its_limit_before_gain():
    split = LAW.split(5e-3)
    assert (split.time_s, split.gain) == (pytest.approx(5e-3), pytest.approx(1.0))
    split = LAW.split(0.032)
    assert (split.time_s, split.gain) == (pytest.approx(8e-3), pytest.approx(4.0))


def test_the_product_stays_within_what_the_sensor_can_do():
    assert LAW.step(0.1, 0.0) == pytest.approx(8e-3 * 16.0)  # black frame: up, bounded
    assert LAW.step(1e-4, 1.0) == pytest.approx(1e-4)  # saturated at the shortest exposure
    assert np.isfinite(LAW.step(1e-3, 0.0))


@pytest.mark.parametrize("changes, message", [
    ({"target": 1.0}, "target"), ({"rate": 0.0}, "rate"), ({"min_s": 0.0}, "exposure limits"),
    ({"max_s": 1e-5}, "exposure limits"), ({"gain_max": 0.5}, "gain_max")])
def test_impossible_limits_are_refused(changes, message):
    fields = dict(target=0.4, rate=0.5, min_s=1e-4, max_s=8e-3, gain_max=16.0) | changes
    with pytest.raises(ValueError, match=message):
        ExposureLaw(**fields)


def test_the_metered_level_is_the_mean_of_a_sparse_grid_as_a_share_of_full_scale():
    image = np.zeros((480, 640, 3), np.uint8)
    image[::8, ::8] = 255  # every metered pixel lit, the rest dark
    assert mean_level(image) == pytest.approx(1.0)


@pytest.mark.parametrize("preset", PRESETS, ids=lambda p: p.stem)
def test_the_simulated_camera_exposes_as_each_vehicle_preset_does(preset):
    """The realistic profile predicts a flight of the presets only if its camera is limited as
    theirs: auto-exposure, no longer than the presets' limit."""
    vehicle = load_config(preset, [])
    driver = getattr(vehicle, vehicle.camera.driver)
    simulated = load_config(None, []).sim_camera
    assert driver.auto_exposure
    assert driver.auto_exposure_limit_us * 1e-3 == pytest.approx(simulated.exposure_max_ms)

"""The camera-IMU time offset a flight learned, kept for the next flight: written only when the
estimate moved, read back for the same camera and mode only, and a bad file is named and
ignored (the flight starts as configured)."""

import json
from datetime import datetime, timezone

import pytest

from autonomy.vins.time_offset import TimeOffset
from companion.config import load_config
from companion.flight.app import time_offset_summary
from companion.launch.learned_offset import (
    camera_identity, keep_learned, learned_offset_path, start_from_learned,
)

NOW = datetime(2026, 11, 26, 12, 0, tzinfo=timezone.utc)


def _config(tmp_path, *overrides):
    return load_config("config/orin-d455.toml", [
        f"camera.learned_time_offset_file={tmp_path / 'offset.json'}", *overrides])


def _summary(seconds=0.0123, sigma=0.0004, estimating=True) -> dict:
    return {"vins_time_offset": time_offset_summary(TimeOffset(seconds, sigma, estimating))}


def test_an_offset_kept_after_a_flight_is_where_the_next_flight_starts(tmp_path):
    config = _config(tmp_path)
    assert config.vins.time_offset_s == 0.0
    path = keep_learned(config, _summary(), NOW)
    assert json.loads(path.read_text()) == {
        "format": 1, "camera": "realsense '' 640x480 at 30 Hz", "offset_s": 0.0123,
        "sigma_s": 0.0004, "saved": "2026-11-26T12:00:00+00:00"}
    assert not list(tmp_path.glob("*.partial"))
    assert start_from_learned(config).vins.time_offset_s == 0.0123


@pytest.mark.parametrize("summary", [
    _summary(sigma=None),  # the estimate never moved: nothing learned
    _summary(estimating=False),  # a fixed offset is the configuration's, not learned
    {},  # a flight that never got a VINS
])
def test_nothing_is_kept_unless_the_estimate_moved(tmp_path, summary):
    assert keep_learned(_config(tmp_path), summary, NOW) is None
    assert not (tmp_path / "offset.json").exists()


def test_offsets_are_not_kept_when_the_file_is_unset_or_the_offset_not_estimated(tmp_path):
    assert learned_offset_path(load_config("config/orin-d455.toml", [
        "camera.learned_time_offset_file="])) is None
    config = _config(tmp_path, "vins.estimate_time_offset=false")
    assert learned_offset_path(config) is None
    assert keep_learned(config, _summary(), NOW) is None


def test_another_camera_or_mode_starts_from_the_configuration(tmp_path, caplog):
    keep_learned(_config(tmp_path), _summary(), NOW)
    for other in ('realsense.serial="123456789"', "camera.rate_hz=15"):
        assert start_from_learned(_config(tmp_path, other)).vins.time_offset_s == 0.0
    assert "learned with another camera, realsense '' 640x480 at 30 Hz; this one is " \
           "realsense '123456789' 640x480 at 30 Hz" in caplog.text
    assert "this one is realsense '' 640x480 at 15 Hz" in caplog.text


def test_the_camera_is_named_by_its_driver_device_and_mode():
    oak = load_config("config/orin-oak.toml", [])
    assert camera_identity(oak) == f"oak '' CAM_B {oak.camera.width}x{oak.camera.height} at " \
                                   f"{oak.camera.rate_hz:g} Hz"
    assert camera_identity(load_config(None, ["camera.driver=v4l2"])).startswith(
        "v4l2 '/dev/video0' 640x480")


@pytest.mark.parametrize("content, complaint", [
    ("{not json", "not JSON"),
    ('[1, 2]', "not a format-1 offset file"),
    ('{"format": 2}', "not a format-1 offset file"),
    ('{"format": 1, "camera": "realsense \'\' 640x480 at 30 Hz", "offset_s": "12 ms"}',
     "offset_s is '12 ms', not a finite number"),
    ('{"format": 1, "camera": "realsense \'\' 640x480 at 30 Hz", "offset_s": NaN}',
     "offset_s is nan, not a finite number"),
    ('{"format": 1, "camera": "realsense \'\' 640x480 at 30 Hz", "offset_s": 0.2}',
     "time_offset_s"),  # beyond [vins] max_time_offset_s: the options refuse it
])
def test_a_bad_file_is_named_and_ignored(tmp_path, caplog, content, complaint):
    (tmp_path / "offset.json").write_text(content)
    config = _config(tmp_path)
    assert start_from_learned(config) is config
    assert f"ignoring the learned camera-IMU time offset in {tmp_path / 'offset.json'}" \
           in caplog.text and complaint in caplog.text

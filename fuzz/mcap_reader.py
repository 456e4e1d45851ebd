#!/usr/bin/env python3
"""Fuzz every reader of flight recordings (MCAP) with hostile files.

    python fuzz/mcap_reader.py [libFuzzer options] [CORPUS_DIR ...]

Each input is a recording's bytes. Every reader of ``companion/recording/`` reads it:
``inspect.summarise`` and ``format_summary`` (``companion log info``), ``inspect.recover``
(``companion log recover``), ``replay.recorded_config`` and ``replay.replay`` (``companion
replay``, under the recording's own config where it has a good one, else the defaults with a
simulated mission), ``replay.vins_error`` with the map scale (``companion log vins --map``).

The invariant: ``summarise`` and ``recover`` either raise
:class:`~companion.recording.inspect.InspectError` or return their documented dicts, and the
file ``recover`` wrote is a complete recording with as many messages as it says;
``recorded_config`` raises :class:`~companion.recording.replay.ReplayError` or a
:class:`~companion.config.ConfigError`, or returns a config and a mission that is None or a
dict; ``replay`` raises ``ReplayError`` or returns a report; ``vins_error`` raises
``ReplayError`` or returns samples with finite errors in time order. Anything else escaping (a
KeyError, a protobuf DecodeError, a JSON error...) is a finding.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from fuzz import harness  # noqa: E402

if __name__ == "__main__":
    harness.require_atheris()

with harness.instrumented(__name__ == "__main__"):
    from companion.config import Config, ConfigError
    from companion.recording import inspect
    from companion.recording.replay import ReplayError, recorded_config, replay, vins_error

TARGET = "mcap_reader"
#: The mission replay is given when the recording's own config or mission is unusable.
DEFAULT_MISSION = {"seed": 0}
#: Where each input is written, and what recover writes (one folder per process, reused).
_FOLDER = harness.scratch(TARGET)
_FILE, _RECOVERED = _FOLDER / "flight.mcap", _FOLDER / "recovered.mcap"


def run(data: bytes) -> list[str]:
    """Read one input with every reader, checking the invariant (module docstring); what
    they said: their errors' messages."""
    _FILE.write_bytes(data)
    said: list[str] = []
    _summarise(_FILE, said)
    _recover(said)
    _replay(said)
    _vins_error(said)
    return said


def test_one_input(data: bytes) -> None:
    """libFuzzer's entry point: :func:`run`."""
    run(data)


def _summarise(path: Path, said: list[str]) -> dict | None:
    try:
        summary = inspect.summarise(path)
    except inspect.InspectError as error:
        said.append(str(error))
        return None
    assert isinstance(inspect.format_summary(summary), str)
    return summary


def _recover(said: list[str]) -> None:
    _RECOVERED.unlink(missing_ok=True)
    try:
        result = inspect.recover(_FILE, _RECOVERED)
    except inspect.InspectError as error:
        said.append(str(error))
        return
    summary = _summarise(_RECOVERED, said)
    assert summary is not None and summary["complete"], f"recovered into {summary}"
    assert summary["messages"] == result["messages"], (summary["messages"], result)


def _replay(said: list[str]) -> None:
    try:
        config, mission = recorded_config(_FILE)
    except (ReplayError, ConfigError) as error:
        said.append(str(error))
        config, mission = Config(), None
    assert mission is None or isinstance(mission, dict), mission
    try:
        replay(_FILE, config, mission or DEFAULT_MISSION)
    except ReplayError as error:
        said.append(str(error))


def _vins_error(said: list[str]) -> None:
    try:
        samples = vins_error(_FILE, with_map=True)
    except ReplayError as error:
        said.append(str(error))
        return
    times = [sample.t for sample in samples]
    assert times == sorted(times), times
    assert all(math.isfinite(sample.error_m) and math.isfinite(sample.heading_deg)
               and math.isfinite(sample.pitch_deg) and math.isfinite(sample.roll_deg)
               and (sample.map_scale is None or not math.isnan(sample.map_scale))
               for sample in samples), samples


if __name__ == "__main__":
    harness.fuzz(test_one_input)

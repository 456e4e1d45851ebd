#!/usr/bin/env python3
"""Fuzz the config loader: a TOML file and ``--set`` overrides, as an operator types them.

    python fuzz/config_set.py [libFuzzer options] [CORPUS_DIR ...]

Each input is a config file with its command line: its lines that begin ``--set `` are the
overrides (the rest after the prefix, decoded as Python decodes a command line argument,
undecodable bytes kept as surrogates), the other lines are the file, written as they are
(UTF-8 or not). ``load_config(file, overrides)`` reads them.

The invariant: ``load_config`` either raises :class:`~companion.config.ConfigError`, whose
message starts with the file or the ``--set`` that is to blame, or returns a ``Config`` that
``dump_toml`` writes as UTF-8 TOML (what ``config show`` prints and a recording keeps) and that
reads back to an equal ``Config``. Anything else escaping (a TypeError, a RecursionError...)
is a finding.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from fuzz import harness  # noqa: E402

if __name__ == "__main__":
    harness.require_atheris()

with harness.instrumented(__name__ == "__main__"):
    from companion.config import ConfigError, config_from_toml, dump_toml, load_config

TARGET = "config_set"
OVERRIDE = b"--set "
#: Where each input's file is written (one per process, reused).
_FILE = harness.scratch(TARGET) / "flight.toml"


def split(data: bytes) -> tuple[bytes, list[str]]:
    """The file's bytes and the overrides of an input (module docstring)."""
    lines, overrides = [], []
    for line in data.split(b"\n"):
        if line.startswith(OVERRIDE):
            overrides.append(os.fsdecode(line[len(OVERRIDE):]))
        else:
            lines.append(line)
    return b"\n".join(lines), overrides


def run(data: bytes) -> list[str]:
    """Load one input's file and overrides, checking the invariant (module docstring); what
    the loader said: its ConfigError, if any."""
    text, overrides = split(data)
    _FILE.write_bytes(text)
    try:
        config = load_config(_FILE, overrides)
    except ConfigError as error:
        blamed = str(error).split(": ", 1)[0]
        assert blamed == str(_FILE) or blamed.startswith("--set "), f"blames {blamed!r}"
        return [str(error)]
    dumped = dump_toml(config)
    dumped.encode("utf-8")
    assert config_from_toml(dumped, "the dump") == config, "the dump reads back otherwise"
    return []


def test_one_input(data: bytes) -> None:
    """libFuzzer's entry point: :func:`run`."""
    run(data)


if __name__ == "__main__":
    harness.fuzz(test_one_input)

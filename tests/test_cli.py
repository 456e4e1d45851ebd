"""The ``companion`` command as a user runs it: exit statuses, what lands on stdout and stderr."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest

import companion
from companion.cli import main
from companion.config import Config

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

SIM_TOML = Path(__file__).resolve().parent.parent / "config" / "sim.toml"


def companion_command(*args: str | Path) -> subprocess.CompletedProcess:
    """``companion ARGS`` through the console script's own :func:`companion.cli.main`, in this
    process (a new interpreter costs seconds of imports a test): exit status and output."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main([str(arg) for arg in args])
    return subprocess.CompletedProcess(args, status, out.getvalue(), err.getvalue())


@pytest.mark.parametrize("command", [[str(Path(sys.executable).parent / "companion")],
                                     [sys.executable, "-m", "companion"]],
                         ids=["console script", "python -m"])
def test_the_installed_commands_reach_the_same_main(command):
    """The console script (what systemd and the README run) and ``python -m companion``."""
    run = subprocess.run([*command, "--version"], capture_output=True, text=True, timeout=60)
    assert (run.returncode, run.stdout) == (0, f"companion {companion.__version__}\n")
    assert companion.__version__ == "0.1.0"


@pytest.mark.parametrize("command, mentions", [
    ((), "--log-level"),
    (("config",), "show"),
    (("config", "check"), "FILE: ok"),
    (("config", "show"), "--set SECTION.KEY=VALUE"),
    (("bench",), "rescale"),
    (("bench", "rescale"), "--size HxW"),
    (("depth",), "bench"),
    (("depth", "bench"), "--model FILE"),
    (("eval", "depth"), "--max-frames N"),
])
def test_every_command_has_help(command, mentions):
    run = companion_command(*command, "--help")
    assert run.returncode == 0
    assert run.stdout.startswith(f"usage: companion {' '.join(command)}".rstrip())
    assert mentions in run.stdout


@pytest.mark.parametrize("command", [(), ("config",), ("bench",)])
def test_missing_subcommand_prints_help_and_fails(command):
    run = companion_command(*command)
    assert run.returncode == 2
    assert run.stderr.startswith(f"usage: companion {' '.join(command)}".rstrip())


def test_config_check_accepts_the_simulator_default():
    run = companion_command("config", "check", SIM_TOML)
    assert (run.returncode, run.stdout, run.stderr) == (0, f"{SIM_TOML}: ok\n", "")


def test_config_check_reports_a_bad_file_in_one_line(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[rescale]\nkappa = -1\n", encoding="utf-8")
    run = companion_command("config", "check", path)
    assert (run.returncode, run.stdout) == (2, "")
    assert run.stderr == f"{path}: rescale.kappa: must be >= 0, got -1.0\n"


@pytest.mark.parametrize("args, expected", [
    (("missing.toml",), "missing.toml: no such file\n"),
    ((SIM_TOML, "--set", "rescale.kappa=-1"),
     "--set rescale.kappa=-1: rescale.kappa: must be >= 0, got -1.0\n"),
    ((SIM_TOML, "--set", "kappa"), "--set kappa: expected SECTION.KEY=VALUE, got 'kappa'\n"),
])
def test_config_check_failures_exit_2_without_a_traceback(args, expected):
    run = companion_command("config", "check", *args)
    assert (run.returncode, run.stderr) == (2, expected)
    assert "Traceback" not in run.stdout + run.stderr


def test_config_show_prints_every_key_of_the_defaults():
    run = companion_command("config", "show")
    assert run.returncode == 0
    shown = tomllib.loads(run.stdout)
    assert shown == json.loads(json.dumps(dataclasses.asdict(Config())))  # tuples as lists


def test_config_show_applies_file_then_overrides(tmp_path):
    path = tmp_path / "field.toml"
    path.write_text('[rescale]\nmethod = "poly2"\nkappa = 5\n', encoding="utf-8")
    run = companion_command("config", "show", path, "--set", "rescale.kappa=7")
    shown = tomllib.loads(run.stdout)["rescale"]
    assert (shown["method"], shown["kappa"]) == ("poly2", 7.0)


@pytest.mark.parametrize("args, complaint", [
    (("bench", "rescale", "--size", "480"), "expected HEIGHTxWIDTH, e.g. 480x640; got '480'"),
    (("bench", "rescale", "--repeats", "0"), "expected a positive integer, got '0'"),
    (("--log-level", "LOUD", "config", "show"), "invalid choice: 'LOUD'"),
    (("launch",), "invalid choice: 'launch'"),
])
def test_bad_arguments_exit_2_with_the_reason(args, complaint):
    run = companion_command(*args)
    assert run.returncode == 2
    assert complaint in run.stderr


@pytest.mark.parametrize("args, complaint", [
    (("fly",), "no mission: set [flight] waypoints in the config or give --goal X,Y,Z"),
    (("fly", "--goal", "10,0,1.5"), "[depth_network] model is empty"),
    (("fly", "--set", "flight.waypoints=['1,2']"), "flight.waypoints: expected 'x,y,z'"),
])
def test_fly_says_what_is_missing_before_touching_any_device(args, complaint):
    run = companion_command(*args)
    assert run.returncode in (1, 2)
    assert complaint in run.stderr

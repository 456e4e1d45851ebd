"""MAVLink signing keys (drivers/mavlink/signing.py and `companion signing keygen`): the key file
and each way it cannot be used, systemd's credentials directory, new keys, the spec's
timestamp, and what a refused frame says about its sender."""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import pytest

from autonomy.options import OptionError
from companion.cli import main
from companion.config import ConfigError, load_config
from drivers.mavlink.autopilot import MavlinkOptions
from drivers.mavlink.link import mavlink
from drivers.mavlink.signing import (SigningKeyError, key_file_path, load_key, read_key_file,
                                     refused_frame, signing_timestamp)
from drivers.sim.mock_px4 import Px4Options

KEY = bytes(range(32))


def key_file(tmp_path, text: str, mode: int = 0o600, name: str = "mavlink.key"):
    path = tmp_path / name
    path.write_text(text)
    path.chmod(mode)
    return path


def test_a_key_file_holds_64_hex_digits_whitespace_around_them_ignored(tmp_path):
    path = key_file(tmp_path, f"\n  {KEY.hex().upper()}\n\n")
    assert read_key_file(str(path)) == KEY
    assert load_key(MavlinkOptions(signing_key_file=str(path))) == KEY
    assert load_key(MavlinkOptions(signing_key=KEY.hex())) == KEY
    assert load_key(MavlinkOptions()) is None


def test_a_missing_key_file_says_how_to_make_one(tmp_path):
    with pytest.raises(SigningKeyError) as error:
        read_key_file(str(tmp_path / "absent.key"))
    assert str(error.value) == (f"MAVLink signing key file {tmp_path / 'absent.key'}: no such "
                                "file; make one with `companion signing keygen FILE` "
                                "(docs/operations.md, MAVLink signing)")


@pytest.mark.parametrize("mode", [0o640, 0o604, 0o620, 0o660, 0o700 | 0o001])
def test_a_key_file_others_may_use_is_refused_as_ssh_refuses_a_key(tmp_path, mode):
    path = key_file(tmp_path, KEY.hex(), mode)
    with pytest.raises(SigningKeyError, match=re.escape(
            f"permissions {mode:04o} let group or others at the key; `chmod 600 {path}`")):
        read_key_file(str(path))


def test_the_owner_only_modes_are_accepted(tmp_path):
    for mode in (0o600, 0o400):  # 0400: the copy systemd's LoadCredential= gives the service
        assert read_key_file(str(key_file(tmp_path, KEY.hex(), mode, f"{mode:o}.key"))) == KEY


@pytest.mark.parametrize("text", ["", KEY.hex()[:-2], KEY.hex() + "ab", "zz" * 32,
                                  KEY.hex()[:32] + " " + KEY.hex()[32:]])
def test_a_key_file_that_is_not_64_hex_digits_is_refused(tmp_path, text):
    path = key_file(tmp_path, text)
    with pytest.raises(SigningKeyError, match=re.escape(
            f"MAVLink signing key file {path}: must hold 64 hex digits")):
        read_key_file(str(path))


def test_a_directory_is_not_a_key_file(tmp_path):
    folder = tmp_path / "keys"
    folder.mkdir(mode=0o700)
    with pytest.raises(SigningKeyError, match="not a regular file"):
        read_key_file(str(folder))


def test_a_relative_key_file_is_looked_up_in_systemds_credentials_directory(tmp_path,
                                                                           monkeypatch):
    credentials = tmp_path / "credentials"
    credentials.mkdir()
    key_file(credentials, KEY.hex(), 0o400, "mavlink-signing.key")
    monkeypatch.chdir(tmp_path)  # the working directory has no such file
    environ = {"CREDENTIALS_DIRECTORY": str(credentials)}
    assert key_file_path("mavlink-signing.key", environ) == credentials / "mavlink-signing.key"
    assert read_key_file("mavlink-signing.key", environ) == KEY
    with pytest.raises(SigningKeyError, match="no such file"):
        read_key_file("mavlink-signing.key", {})  # without systemd: the working directory
    absolute = key_file(tmp_path, KEY.hex(), name="elsewhere.key")
    assert read_key_file(str(absolute), environ) == KEY  # an absolute path stays itself


def test_the_key_and_the_key_file_together_are_a_config_error(tmp_path):
    for table in (MavlinkOptions, Px4Options):
        with pytest.raises(OptionError) as error:
            table(signing_key=KEY.hex(), signing_key_file="mavlink.key")
        assert error.value.key == "signing_key_file" and "not both" in str(error.value)
    with pytest.raises(ConfigError, match="mavlink.signing_key_file: set signing_key_file or "
                                          "signing_key, not both"):
        load_config(None, ["mavlink.signing_key_file=mavlink.key",
                           f"mavlink.signing_key={KEY.hex()}"])


def test_the_signing_timestamp_counts_10_us_since_2015():
    new_year_2015 = 1420070400
    assert signing_timestamp(new_year_2015) == 0
    assert signing_timestamp(new_year_2015 + 1.5) == 150_000
    assert signing_timestamp(0) == 0  # before the epoch


def test_a_refused_frame_names_its_sender_and_whether_it_was_signed():
    sender = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    frame = sender.command_long_encode(1, 191, mavlink.MAV_CMD_MISSION_START, 0, *[0] * 7)
    unsigned = refused_frame(frame.pack(sender))
    assert (unsigned.kind, unsigned.system, unsigned.component, unsigned.message) == \
        ("unsigned", 255, 190, "COMMAND_LONG")
    sender.signing.secret_key, sender.signing.sign_outgoing = KEY, True
    signed = refused_frame(frame.pack(sender))
    assert signed.kind == "bad_signature"
    assert refused_frame(b"\xfd\x00") is None


# -------------------------------------------------------------------- companion signing keygen

def test_keygen_writes_64_hex_digits_readable_by_the_owner_only(tmp_path, capsys):
    path = tmp_path / "mavlink-signing.key"
    assert main(["signing", "keygen", str(path)]) == 0
    text = path.read_text()
    assert re.fullmatch(r"[0-9a-f]{64}\n", text)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert read_key_file(str(path)) == bytes.fromhex(text)
    out = capsys.readouterr().out
    assert "LoadCredential=mavlink-signing.key:/etc/companion/mavlink-signing.key" in out
    assert "companion signing provision" in out


def test_keygen_never_overwrites_a_key(tmp_path, capsys):
    path = tmp_path / "mavlink-signing.key"
    assert main(["signing", "keygen", str(path)]) == 0
    before = path.read_text()
    assert main(["signing", "keygen", str(path)]) == 1
    assert path.read_text() == before
    assert capsys.readouterr().err.strip() == (
        f"signing keygen: {path} exists: not overwriting a key that may be in use (move it "
        "away first to make a new one)")


def test_two_keygens_make_two_keys(tmp_path):
    first, second = tmp_path / "a.key", tmp_path / "b.key"
    assert main(["signing", "keygen", str(first)]) == main(["signing", "keygen", str(second)]) == 0
    assert read_key_file(str(first)) != read_key_file(str(second))


# -------------------------------------------------------------------- a key that cannot be used

CONFIG = Path(__file__).resolve().parent.parent / "config"
MISSING = ("MAVLink signing key file mavlink-signing.key: no such file; make one with "
           "`companion signing keygen FILE` (docs/operations.md, MAVLink signing)")


@pytest.fixture
def no_key_here(tmp_path, monkeypatch):
    """A working directory without the key file, and no systemd credentials."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("CREDENTIALS_DIRECTORY", raising=False)


@pytest.mark.parametrize("preset", ["orin-d455.toml", "orin-oak.toml"])
def test_a_vehicle_preset_without_its_key_file_does_not_fly(preset, no_key_here, capsys):
    """The presets sign; without the key the application stops at start-up with one line,
    before the network, the camera or the link opens, and never arms."""
    status = main(["fly", "--config", str(CONFIG / preset), "--goal", "0,0,1.5",
                   "--set", "depth_network.model=/nonexistent/model.onnx"])
    assert status == 1
    assert capsys.readouterr().err == f"fly: {MISSING}\n"


@pytest.mark.parametrize("command, table", [(["sim", "fly", "--no-plot"], "mavlink"),
                                            (["sim", "serve", "--duration", "1"], "px4")])
def test_the_simulator_refuses_a_missing_key_file_in_one_line(command, table, no_key_here,
                                                             capsys):
    status = main([*command, "--set", f"{table}.signing_key_file=mavlink-signing.key"])
    assert status == 1
    assert capsys.readouterr().err.splitlines()[-1] == f"{command[0]} {command[1]}: {MISSING}"


def test_a_flight_controller_signing_with_another_key_is_never_armed():
    """The fault matrix's key mismatch (docs/reliability.md): PX4 refuses a new key while
    armed, so a mismatch is met before the flight. Every PX4 message fails the companion's
    signature check, so there is no link: the preflight ends in ABORTED, naming the cause and
    the fix, and nothing was armed."""
    from companion.launch import simulated
    from companion.tools.fault_matrix import MATRIX_GOAL

    config = load_config(None, [f'mavlink.signing_key="{"a1" * 32}"',
                                f'px4.signing_key="{"b2" * 32}"'])
    summary = simulated.run(config, simulated.SimMission(world="dome", goal=MATRIX_GOAL))
    assert summary["final_state"] == "aborted" and summary["flight_time_s"] == 0.0
    [transition] = summary["transitions"]
    assert transition["from"] == "preflight"
    assert "signs with another key" in transition["reason"]
    assert "companion signing provision" in transition["reason"]
    assert summary["mavlink_signing"]["bad_signature"] > 0
    assert summary["path_length_m"] == 0.0

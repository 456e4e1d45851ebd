"""What an operator relies on in the service unit and the udev rules, checked on the files that
get installed: the unit is started, watched and restarted by systemd, runs as `companion` with
the groups that open the serial port, cameras and GPU, and no hardening option hides a device."""

import re
import shutil
import subprocess
from pathlib import Path

import pytest

SYSTEMD = Path(__file__).resolve().parent.parent / "systemd"
UNIT = SYSTEMD / "companion.service"
RULES = SYSTEMD / "99-companion.rules"
DEVICE_ALLOWLIST = SYSTEMD / "device-allowlist.conf"


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """Section -> key -> every value assigned, in order (systemd keys may repeat, and the last
    assignment of a single-valued key wins); comments and blank lines dropped, as systemd.syntax
    describes. A line that is neither is a ValueError naming it."""
    unit: dict[str, dict[str, list[str]]] = {}
    section = None
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            section = unit.setdefault(line[1:-1], {})
        elif "=" in line and section is not None and not line.endswith("\\"):
            key, value = line.split("=", 1)
            section.setdefault(key.strip(), []).append(value.strip())
        else:
            raise ValueError(f"line {number}: not a section, key=value or comment: {raw!r}")
    return unit


@pytest.fixture(scope="module")
def unit():
    return parse_unit(UNIT.read_text(encoding="utf-8"))


def one(unit, section, key) -> str:
    values = unit[section].get(key)
    assert values, f"{section}.{key} is not set"
    return values[-1]  # the last assignment wins in systemd


def seconds(span: str) -> float:
    match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*(ms|s|min)?", span)
    assert match, f"not a simple time span: {span!r}"
    return float(match[1]) * {"ms": 1e-3, "s": 1.0, "min": 60.0, None: 1.0}[match[2]]


def is_true(value: str) -> bool:
    return value.lower() in ("1", "yes", "true", "on")


def test_unit_parser_keeps_repeated_keys_and_rejects_stray_lines():
    parsed = parse_unit("[Service]\n# c\nEnvironment=A=1\n\nEnvironment=B=2\n")
    assert parsed["Service"]["Environment"] == ["A=1", "B=2"]
    with pytest.raises(ValueError, match="line 2"):
        parse_unit("[Service]\nType notify\n")


def test_started_watched_and_restarted_by_systemd(unit):
    assert one(unit, "Service", "Type") == "notify"
    assert one(unit, "Service", "NotifyAccess") == "main"
    assert 0 < seconds(one(unit, "Service", "WatchdogSec")) <= 5
    assert one(unit, "Service", "Restart") == "on-failure"
    assert seconds(one(unit, "Service", "RestartSec")) >= 1
    assert int(one(unit, "Unit", "StartLimitBurst")) >= 1
    assert seconds(one(unit, "Unit", "StartLimitIntervalSec")) > 0
    assert one(unit, "Install", "WantedBy") == "multi-user.target"


def test_stop_timeout_covers_stop_hold_and_landing_after_sigterm(unit):
    """SIGTERM in the air: the application stops, holds and lands; systemd must not kill it
    before the longest such sequence the flight options allow by default."""
    from autonomy.navigation.mission import FlightOptions

    o = FlightOptions()
    longest_s = o.stop_timeout_s + o.hold_before_land_s + o.land_timeout_s
    assert seconds(one(unit, "Service", "TimeoutStopSec")) >= longest_s + 10.0


def test_the_go_socket_directory_is_made_for_the_service_only(unit):
    from companion.flight.go import GoOptions

    assert one(unit, "Service", "RuntimeDirectory") == "companion"
    assert one(unit, "Service", "RuntimeDirectoryMode") == "0750"
    assert GoOptions().socket.startswith("/run/companion/")


def test_runs_the_flight_command_with_the_installed_config(unit):
    command = one(unit, "Service", "ExecStart").split()
    assert command[0].startswith("/") and command[0].endswith("/bin/companion")
    assert command[1:] == ["fly", "--config", "/etc/companion/flight.toml"]
    assert "PYTHONUNBUFFERED=1" in " ".join(unit["Service"]["Environment"])


def test_dedicated_user_with_the_device_groups(unit):
    assert one(unit, "Service", "User") == "companion"
    groups = " ".join(unit["Service"]["SupplementaryGroups"]).split()
    assert {"dialout", "video", "plugdev"} <= set(groups)


def test_the_signing_key_reaches_the_service_under_the_name_the_presets_give(unit):
    """LoadCredential= hands the service a private copy of root's key file in
    $CREDENTIALS_DIRECTORY, where the presets' relative signing_key_file is looked up."""
    from companion.config import load_config

    name, source = one(unit, "Service", "LoadCredential").split(":", 1)
    assert source == "/etc/companion/mavlink-signing.key"
    presets = sorted(SYSTEMD.parent.joinpath("config").glob("orin-*.toml"))
    assert presets
    for preset in presets:
        assert load_config(preset).mavlink.signing_key_file == name


def test_hardening_hides_no_device(unit):
    service = unit["Service"]
    assert not is_true(service.get("PrivateDevices", ["no"])[-1])
    assert service.get("DevicePolicy", ["auto"])[-1] == "auto"
    assert "DeviceAllow" not in service  # any entry closes every device not listed
    assert not is_true(service.get("ProtectClock", ["no"])[-1])  # implies a DeviceAllow
    assert one(unit, "Service", "ProtectSystem") == "strict"
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp", "ProtectKernelTunables",
                "ProtectControlGroups"):
        assert is_true(one(unit, "Service", key)), key
    families = set(one(unit, "Service", "RestrictAddressFamilies").split())
    assert {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"} <= families  # sd_notify, UDP, udev


def test_no_capability_and_no_system_call_a_flight_never_makes(unit):
    service = unit["Service"]
    assert one(unit, "Service", "CapabilityBoundingSet") == ""
    assert one(unit, "Service", "SystemCallArchitectures") == "native"
    denied = one(unit, "Service", "SystemCallFilter")
    assert denied.startswith("~")
    assert {"@clock", "@debug", "@module", "@mount", "@privileged", "@raw-io", "@reboot",
            "@swap"} <= set(denied[1:].split())
    # onnxruntime pins its threads and CUDA sets memory policy: @resources stays allowed
    assert "@resources" not in denied and "@system-service" not in denied
    # a call outside the filter fails with an error the code handles, not SIGSYS in flight
    assert one(unit, "Service", "SystemCallErrorNumber") == "EPERM"
    for key in ("RestrictRealtime", "RemoveIPC", "PrivateMounts"):
        assert is_true(one(unit, "Service", key)), key
    assert one(unit, "Service", "ProtectProc") == "invisible"
    assert int(one(unit, "Service", "UMask"), 8) & 0o007 == 0o007
    assert "ProcSubset" not in service  # onnxruntime and OpenCV read /proc/cpuinfo


def test_the_allocator_keeps_two_arenas_as_the_soak_measured(unit):
    """docs/reliability.md: two glibc arenas held about 100 MB less over a real-time soak."""
    assert "MALLOC_ARENA_MAX=2" in unit["Service"]["Environment"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed here")
def test_systemd_analyze_security_scores_the_unit_as_the_unit_says(tmp_path):
    stated = re.search(r"scores it (\d+\.\d) \(OK\)", UNIT.read_text(encoding="utf-8"))
    assert stated, "the unit's comment states its score"
    result = subprocess.run(["systemd-analyze", "security", "--offline=true", str(UNIT)],
                            capture_output=True, text=True, timeout=60)
    score = re.search(r"Overall exposure level for \S+: (\d+\.\d) (\w+)", result.stdout)
    assert score, result.stdout + result.stderr
    assert (score[1], score[2]) == (stated[1], "OK")


def test_the_opt_in_device_allowlist_opens_the_serial_ports_and_cameras_and_nothing_by_default():
    """The drop-in closes every device but those the flight needs; the serial ports and the
    cameras the udev rules name must be among them, read-write, or the link or the camera
    vanishes the day an operator installs it."""
    service = parse_unit(DEVICE_ALLOWLIST.read_text(encoding="utf-8"))["Service"]
    assert service["DevicePolicy"] == ["closed"]
    allowed = dict(entry.split() for entry in service["DeviceAllow"])
    for group in ("char-ttyTHS", "char-ttyACM", "char-ttyUSB", "char-video4linux",
                  "char-usb_device"):
        assert allowed.get(group) == "rw", group
    assert all(set(mode) <= set("rw") for mode in allowed.values())  # no mknod


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed here")
def test_the_unit_with_the_device_allowlist_installed_verifies(tmp_path):
    installed = tmp_path / "companion.service"
    installed.write_text(re.sub(r"^ExecStart=\S+", "ExecStart=/bin/true",
                                UNIT.read_text(encoding="utf-8"), flags=re.MULTILINE),
                         encoding="utf-8")
    (tmp_path / "companion.service.d").mkdir()
    shutil.copy(DEVICE_ALLOWLIST, tmp_path / "companion.service.d" / DEVICE_ALLOWLIST.name)
    verify = subprocess.run(["systemd-analyze", "verify", str(installed)],
                            capture_output=True, text=True, timeout=60)
    assert verify.returncode == 0 and not (verify.stdout + verify.stderr).strip(), \
        verify.stdout + verify.stderr
    security = subprocess.run(["systemd-analyze", "security", "--offline=true", str(installed)],
                              capture_output=True, text=True, timeout=60)
    assert "Service has a device ACL" in security.stdout  # the drop-in was read


def test_something_writable_under_protect_system_strict(unit):
    service = unit["Service"]
    assert any(k in service for k in ("StateDirectory", "LogsDirectory", "ReadWritePaths"))


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed here")
def test_systemd_analyze_verify_accepts_the_unit(tmp_path):
    # verify also checks that ExecStart's program exists; the venv lives on the vehicle only
    text = re.sub(r"^ExecStart=\S+", "ExecStart=/bin/true", UNIT.read_text(encoding="utf-8"),
                  flags=re.MULTILINE)
    copy = tmp_path / "companion.service"
    copy.write_text(text, encoding="utf-8")
    result = subprocess.run(["systemd-analyze", "verify", str(copy)], capture_output=True,
                            text=True, timeout=60)
    output = (result.stdout + result.stderr).strip()
    assert result.returncode == 0 and not output, output


RULE_TOKEN = re.compile(r'\s*([A-Z_]+)(\{[^}]+\})?\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*(,|$)')


def parse_rules(text: str) -> list[list[tuple[str, str, str, str]]]:
    """Each rule as (key, {attribute} or '', operator, value) tokens; a ValueError names a
    line that is not a well-formed rule."""
    rules = []
    for number, line in _logical_lines(text):
        tokens, position = [], 0
        while position < len(line):
            match = RULE_TOKEN.match(line, position)
            if not match:
                raise ValueError(f"line {number}: malformed at {line[position:]!r}")
            tokens.append(match.groups()[:4])
            position = match.end()
        rules.append([(k, a or "", op, v) for k, a, op, v in tokens])
    return rules


def _logical_lines(text: str):
    """(first line number, rule text) of each rule, continuation lines (a trailing backslash)
    joined, comments and blank lines skipped."""
    pending, start = "", 0
    for number, line in enumerate(text.splitlines(), 1):
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        start = start if pending else number
        if line.endswith("\\"):
            pending += line[:-1]
            continue
        yield start, pending + line
        pending = ""
    if pending:
        raise ValueError(f"line {start}: the file ends inside a continued rule")


def test_rules_parse_and_cover_the_serial_ports_and_cameras():
    rules = parse_rules(RULES.read_text(encoding="utf-8"))

    def find(**match):
        return [r for r in rules
                if all(any((k + a, v) == (key, value) for k, a, _, v in r)
                       for key, value in match.items())]

    assert any(("GROUP", "", "=", "dialout") in r for r in find(KERNEL="ttyTHS[0-9]*"))
    for vendor in ("26ac", "3162"):
        (pixhawk,) = find(**{"ATTRS{idVendor}": vendor, "SUBSYSTEM": "tty"})
        assert ("SYMLINK", "", "+=", "fcu-usb") in pixhawk
        assert ("ENV", "{ID_MM_DEVICE_IGNORE}", "=", "1") in pixhawk
    assert any(("GROUP", "", "=", "video") in r for r in find(SUBSYSTEM="video4linux"))


def test_rules_give_devices_only_to_groups_the_service_has(unit):
    groups = set(" ".join(unit["Service"]["SupplementaryGroups"]).split())
    for rule in parse_rules(RULES.read_text(encoding="utf-8")):
        for key, _, op, value in rule:
            if key == "GROUP":
                assert value in groups, rule


def test_rules_parser_rejects_malformed_lines():
    with pytest.raises(ValueError, match="line 2"):
        parse_rules('# ok\nKERNEL=="ttyTHS1" SYMLINK+="x"\n')
    with pytest.raises(ValueError, match="line 1: the file ends"):
        parse_rules('KERNEL=="ttyTHS1", \\\n')
    assert parse_rules('KERNEL=="a", \\\n  SYMLINK+="b"\n') == [
        [("KERNEL", "", "==", "a"), ("SYMLINK", "", "+=", "b")]]

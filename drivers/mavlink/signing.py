"""MAVLink 2 signing beyond the wire format: the key file, new keys, the spec's timestamp, and
what a signing link refused.

The key file holds the 32-byte secret as 64 hex digits (whitespace around them ignored), like
an ssh private key readable by its owner only: a secret must not sit in a config file that
lives in a repository. A relative path is looked up in ``$CREDENTIALS_DIRECTORY`` when systemd
set it (the unit's ``LoadCredential=``, which hands the service a private 0400 copy of a file
only root reads), else in the working directory. Every way it cannot be used is a
:class:`SigningKeyError` whose one line says what to do.

The timestamp is the MAVLink signing spec's: 10 µs units since 2015-01-01 00:00 UTC
(mavlink.io, "Message Signing", Timestamp), what SETUP_SIGNING's ``initial_timestamp`` carries.

A link that signs refuses unsigned messages (outside an allowlist) and messages whose signature
does not verify: pymavlink reports each as BAD_DATA "Invalid signature" carrying the whole frame
(its CRC already checked), whose header still names the sender. :class:`Refusals` sorts them
into ``unsigned`` and ``bad_signature`` by sender, because a rogue ground station, a PX4 without
the key and a PX4 with another key look different there and need different fixes.
"""

from __future__ import annotations

import os
import re
import secrets
import stat
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

from pymavlink.dialects.v20 import common as mavlink

from autonomy.options import OptionError

#: Bytes in a signing secret (the spec's, and PX4's key file's).
SECRET_KEY_LENGTH = 32
#: A secret as it is written: 64 hex digits, nothing between them.
HEX_KEY = re.compile(f"[0-9a-fA-F]{{{2 * SECRET_KEY_LENGTH}}}")
#: 2015-01-01 00:00:00 UTC as a Unix time: the MAVLink signing epoch.
SIGNING_EPOCH_UNIX_S = 1420070400
#: Signing timestamp units per second (10 µs each).
SIGNING_TICKS_PER_S = 100_000
#: pymavlink's BAD_DATA reason for a message a signing link refused.
REFUSED_REASON = "Invalid signature"
#: Mode bits that let anyone but the owner at the key (ssh's rule for a private key,
#: authfile.c sshkey_perm_ok: ``st_mode & 077``).
FOREIGN_ACCESS = 0o077
#: Most bytes read from a key file (64 hex digits and whitespace take far fewer).
KEY_FILE_MAX_BYTES = 4096
#: Refusal kinds.
UNSIGNED, BAD_SIGNATURE = "unsigned", "bad_signature"
#: What to run to make a key file, for the messages.
KEYGEN_HINT = "make one with `companion signing keygen FILE`"


def signing_secret(key_hex: str) -> bytes | None:
    """The secret written as 64 hex digits (a 32-byte key, what PX4 keeps on its SD card),
    None for "" (signing off); an :class:`~autonomy.options.OptionError` naming
    ``signing_key`` otherwise."""
    if not key_hex:
        return None
    if not HEX_KEY.fullmatch(key_hex):
        raise OptionError("signing_key", "must be 64 hex digits (a 32-byte key), "
                          f"got {len(key_hex)} characters")
    return bytes.fromhex(key_hex)


class SigningKeyError(OSError):
    """A signing key that cannot be used (missing, open to others, malformed, or given twice);
    the message names the file and the fix. An OSError, so that every command that already
    reports OSErrors as one line reports this one too."""


def signing_timestamp(unix_s: float | None = None) -> int:
    """The signing spec's timestamp (10 µs units since 2015-01-01 UTC) of the Unix time
    ``unix_s`` (default: now); 0 before 2015."""
    unix_s = time.time() if unix_s is None else unix_s
    return max(0, int((unix_s - SIGNING_EPOCH_UNIX_S) * SIGNING_TICKS_PER_S))


def new_key() -> bytes:
    """A fresh 32-byte secret from the operating system's CSPRNG (:mod:`secrets`)."""
    return secrets.token_bytes(SECRET_KEY_LENGTH)


def write_key_file(path: str | Path, key: bytes) -> Path:
    """Write ``key`` as 64 hex digits and a newline to a new file created with mode 0600
    (O_CREAT | O_EXCL: never an existing file, so a key in use is never overwritten);
    :class:`SigningKeyError` when it exists or cannot be made."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    except FileExistsError:
        raise SigningKeyError(f"{path} exists: not overwriting a key that may be in use "
                              "(move it away first to make a new one)") from None
    except OSError as error:
        raise SigningKeyError(f"{path}: cannot create it ({error.strerror or error})") from None
    with os.fdopen(fd, "w") as out:
        out.write(key.hex() + "\n")
    return path


def key_file_path(name: str, environ: Mapping[str, str] | None = None) -> Path:
    """Where the key file ``name`` is: itself when absolute; else in
    ``$CREDENTIALS_DIRECTORY`` when systemd set it (``LoadCredential=``), else relative to
    the working directory."""
    environ = os.environ if environ is None else environ
    path = Path(name)
    credentials = environ.get("CREDENTIALS_DIRECTORY")
    if path.is_absolute() or not credentials:
        return path
    return Path(credentials) / path


def read_key_file(name: str, environ: Mapping[str, str] | None = None) -> bytes:
    """The 32-byte secret in the key file ``name`` (:func:`key_file_path`); a
    :class:`SigningKeyError` saying what to do when it is missing, not a regular file, open to
    group or others, or not 64 hex digits."""
    path = key_file_path(name, environ)
    try:  # non-blocking: a FIFO put there must not hang start-up
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    except FileNotFoundError:
        raise SigningKeyError(f"MAVLink signing key file {path}: no such file; "
                              f"{KEYGEN_HINT} (docs/operations.md, MAVLink signing)") from None
    except OSError as error:
        raise SigningKeyError(f"MAVLink signing key file {path}: cannot open it "
                              f"({error.strerror or error})") from None
    try:
        _check_private(path, os.fstat(fd))
        text = os.read(fd, KEY_FILE_MAX_BYTES).decode("ascii", "replace").strip()
    finally:
        os.close(fd)
    if not HEX_KEY.fullmatch(text):
        raise SigningKeyError(f"MAVLink signing key file {path}: must hold 64 hex digits (a "
                              f"32-byte key), got {len(text)} characters; {KEYGEN_HINT}")
    return bytes.fromhex(text)


def _check_private(path: Path, status: os.stat_result) -> None:
    if not stat.S_ISREG(status.st_mode):
        raise SigningKeyError(f"MAVLink signing key file {path}: not a regular file")
    if status.st_mode & FOREIGN_ACCESS:
        raise SigningKeyError(f"MAVLink signing key file {path}: permissions "
                              f"{stat.S_IMODE(status.st_mode):04o} let group or others at the "
                              f"key; `chmod 600 {path}`")


def check_key_options(options) -> None:
    """Validate the ``signing_key`` and ``signing_key_file`` of an options table (``[mavlink]``,
    ``[px4]``) without reading the file: one of them at most, the first 64 hex digits;
    OptionError naming the key."""
    if options.signing_key and options.signing_key_file:
        raise OptionError("signing_key_file", "set signing_key_file or signing_key, not both "
                                              "(a secret belongs in the file, not the config)")
    signing_secret(options.signing_key)


def load_key(options, environ: Mapping[str, str] | None = None) -> bytes | None:
    """The secret an options table names: read from its ``signing_key_file`` when set, else
    its ``signing_key``; None for signing off. :class:`SigningKeyError` as
    :func:`read_key_file`."""
    if options.signing_key_file:
        return read_key_file(options.signing_key_file, environ)
    return signing_secret(options.signing_key)


@dataclass(frozen=True)
class Refused:
    """One refused message: ``kind`` (:data:`UNSIGNED` or :data:`BAD_SIGNATURE`), the sender's
    ids as its header claims them, and the message's name."""

    kind: str
    system: int
    component: int
    message: str

    def describe(self) -> str:
        what = "an unsigned" if self.kind == UNSIGNED else "a badly signed"
        return (f"{what} {self.message} from system {self.system} component "
                f"{self.component}")


def refused_frame(frame: bytes) -> Refused | None:
    """What a refused frame was (MAVLink 2, or a MAVLink 1 frame, which cannot be signed);
    None for bytes too short to have a header."""
    if len(frame) >= 10 and frame[0] == mavlink.PROTOCOL_MARKER_V2:
        signed = bool(frame[2] & mavlink.MAVLINK_IFLAG_SIGNED)
        system, component = frame[5], frame[6]
        message_id = frame[7] | frame[8] << 8 | frame[9] << 16
    elif len(frame) >= 6 and frame[0] == mavlink.PROTOCOL_MARKER_V1:
        signed, system, component, message_id = False, frame[3], frame[4], frame[5]
    else:
        return None
    kind = BAD_SIGNATURE if signed else UNSIGNED
    known = mavlink.mavlink_map.get(message_id)
    name = known.msgname if known is not None else f"message {message_id}"
    return Refused(kind, system, component, name)


class Refusals:
    """Messages a signing link refused, counted by kind and sender; ``last`` the newest."""

    def __init__(self) -> None:
        self.counts: Counter = Counter()  # (kind, system, component) -> messages
        self.last: Refused | None = None

    def add(self, frame: bytes) -> None:
        refused = refused_frame(bytes(frame))
        if refused is not None:
            self.counts[(refused.kind, refused.system, refused.component)] += 1
            self.last = refused

    def total(self, kind: str | None = None, sender: tuple[int, int] | None = None) -> int:
        """Refusals of ``kind`` (default: both) from ``sender`` (system, component; default:
        anyone)."""
        return sum(n for (k, system, component), n in self.counts.items()
                   if kind in (None, k) and sender in (None, (system, component)))

    def summary(self) -> dict[str, int]:
        """``{"unsigned": n, "bad_signature": n}`` over every sender."""
        return {UNSIGNED: self.total(UNSIGNED), BAD_SIGNATURE: self.total(BAD_SIGNATURE)}

"""An evaluation's records as JSON lines, each added as its task completes, read back to resume.

``eval nav`` (a flight per line) and ``eval vio-table`` (a scored recording per line) write
every record the moment its task finishes, so a run stopped by the machine or the operator
loses at most the line being written, and ``--resume`` goes on with the tasks the file lacks.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable

from companion.tools.eval.vio import EvaluationError


def write_records(records: list[dict], out: Path) -> Path:
    """``records`` as JSON lines at ``out`` (parent folders created), replacing it at once:
    written beside it, then renamed over it."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(out.name + ".partial")
    partial.write_text("".join(json.dumps(r) + "\n" for r in records))
    os.replace(partial, out)
    return out


def append_record(record: dict, out: Path) -> None:
    """Add one task's record to ``out`` as it completes: one line in one write, flushed to
    the disk, so an interruption loses at most the line being written (:func:`read_resumable`
    drops such a torn last line)."""
    with open(out, "a") as stream:
        stream.write(json.dumps(record) + "\n")
        stream.flush()
        os.fsync(stream.fileno())


def read_resumable(path: Path, parse: Callable[[str, str], dict]
                   ) -> tuple[list[dict], str | None]:
    """The records of an interrupted run's file (none if it does not exist or is empty), each
    read by ``parse(line, "FILE:LINE")``, and a note when its last line was torn by the
    interruption and left out. Any other unreadable line is the EvaluationError ``parse``
    raises."""
    path = Path(path)
    if not path.exists():
        return [], None
    numbered = numbered_lines(path)
    note = None
    if numbered:
        try:
            json.loads(numbered[-1][1])
        except json.JSONDecodeError:
            note = f"{path}:{numbered[-1][0]}: a torn last record (the interruption) left out"
            numbered.pop()
    return [parse(line, f"{path}:{n}") for n, line in numbered], note


def reopen(path: Path, parse: Callable[[str, str], dict]) -> tuple[list[dict], str | None]:
    """:func:`read_resumable`'s records and note, the file rewritten without a torn last line,
    so that the records added next follow the last whole one."""
    done, note = read_resumable(path, parse)
    write_records(done, path)
    return done, note


def numbered_lines(path: Path) -> list[tuple[int, str]]:
    """The non-blank lines of a records file with their line numbers (from 1)."""
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise EvaluationError(f"{path}: cannot read: {error}") from None
    return [(n, line) for n, line in enumerate(lines, 1) if line.strip()]


def parse_object(line: str, where: str, what: str) -> dict:
    """One line's JSON object; EvaluationError naming ``where`` and ``what`` it should be
    for anything else."""
    try:
        record = json.loads(line)
    except json.JSONDecodeError as error:
        raise EvaluationError(f"{where}: not JSON: {error.msg}") from None
    if not isinstance(record, dict):
        raise EvaluationError(f"{where}: not a {what} (a JSON object)")
    return record

"""Where recordings go (companion/recording/storage.py): one file per flight named by its
start, a clear error before arming when none can be made, the oldest deleted for the quota."""

from __future__ import annotations

from datetime import datetime

import pytest

from companion.recording.options import RecorderOptions
from companion.recording.storage import RecordingError, enforce_quota, flights, prepare

START = datetime(2026, 11, 25, 10, 15, 0)


def fill(path, size: int):
    path.write_bytes(b"\0" * size)
    return path


def test_each_flight_gets_a_new_file_named_by_its_start(tmp_path):
    options = RecorderOptions(directory=str(tmp_path / "recordings" / "vehicle-1"))
    paths = [prepare(options, now=START) for _ in range(3)]
    assert [path.name for path in paths] == ["flight-20261125-101500.mcap",
                                             "flight-20261125-101500-2.mcap",
                                             "flight-20261125-101500-3.mcap"]
    assert all(path.is_file() for path in paths)  # made, so the name is taken
    later = prepare(options, now=datetime(2026, 11, 25, 10, 16, 0))
    assert flights(later.parent) == [*paths, later]


def test_a_directory_that_cannot_be_made_is_a_clear_error(tmp_path):
    (tmp_path / "not-a-folder").write_text("")
    options = RecorderOptions(directory=str(tmp_path / "not-a-folder" / "recordings"))
    with pytest.raises(RecordingError, match="cannot create the recordings directory "
                                             ".*not-a-folder/recordings: Not a directory"):
        prepare(options)


def test_a_disk_below_the_reserve_is_a_clear_error(tmp_path):
    options = RecorderOptions(directory=str(tmp_path), reserve_mb=1e15)
    with pytest.raises(RecordingError, match=r"only \d+ MB free for recordings in .*; "
                                             r"\[recorder\] reserve_mb needs 1000000000000000 MB"):
        prepare(options)
    assert flights(tmp_path) == []


def test_the_quota_deletes_the_oldest_flights_first(tmp_path):
    names = ["flight-20261125-101500.mcap", "flight-20261125-101500-2.mcap",
             "flight-20261125-101500-10.mcap", "flight-20261126-090000.mcap"]
    for name in names:
        fill(tmp_path / name, 1000)
    other = fill(tmp_path / "notes.mcap", 5000)  # not the recorder's: neither counted nor deleted
    removed = enforce_quota(tmp_path, 2500)
    assert [path.name for path in removed] == names[:2]
    assert [path.name for path in flights(tmp_path)] == names[2:] and other.exists()
    assert enforce_quota(tmp_path, 2500) == []


def test_the_quota_never_deletes_the_flight_being_recorded(tmp_path):
    current = fill(tmp_path / "flight-20261125-101500.mcap", 3000)
    newer = fill(tmp_path / "flight-20261125-111500.mcap", 1000)
    assert enforce_quota(tmp_path, 1500, keep=current) == [newer]
    assert current.exists()


def test_a_new_flight_makes_room_under_the_quota(tmp_path):
    old = [fill(tmp_path / f"flight-2026112{day}-101500.mcap", 600_000) for day in (1, 2, 3)]
    options = RecorderOptions(directory=str(tmp_path), quota_mb=1.0, reserve_mb=0.0)
    path = prepare(options, now=START)
    assert flights(tmp_path) == [old[2], path]

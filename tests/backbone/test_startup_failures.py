"""Every start-up failure of `gcs serve` is one line on stderr and a non-zero exit, never a
traceback (issue 30): a database path that is a directory, a zero-length or foreign database, a
schema from a newer version, a dropped table or column, a bad fleet.key or agent keys file. A
zero-length database is refused unless the operator asks for a new fleet (--new-fleet); a fresh
data directory still starts as a new fleet."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path

import pytest
from pydantic import ValidationError

from gcs.core.config import DaemonConfig
from gcs.storage.store import Store
from tests.support.processes import run_serve


def _database(data: Path) -> Path:
    return data / "fleetgcs.sqlite"


def _with_store(data: Path, sql: str) -> None:
    """A database this daemon made, then changed by ``sql`` behind its back."""
    store = Store(_database(data))
    assert store.cid_for("drone-1", {}) == 1
    store.close()
    db = sqlite3.connect(_database(data))
    db.executescript(sql)
    db.close()


def _directory(data: Path) -> None:
    _database(data).mkdir(parents=True)


def _zero_length(data: Path) -> None:
    _with_store(data, "")
    _database(data).write_bytes(b"")  # emptied (a bad restore, a full disk): CIDs would restart at 1


def _foreign(data: Path) -> None:
    data.mkdir()
    db = sqlite3.connect(_database(data))
    db.executescript("CREATE TABLE photos (name TEXT); INSERT INTO photos VALUES ('a.jpg');")
    db.close()


def _empty_sqlite(data: Path) -> None:
    data.mkdir()
    sqlite3.connect(_database(data)).execute("PRAGMA journal_mode=WAL").fetchall()


def _bad_key(content: bytes) -> Callable[[Path], None]:
    def make(data: Path) -> None:
        data.mkdir()
        (data / "fleet.key").write_bytes(content)

    return make


def _key_is_directory(data: Path) -> None:
    (data / "fleet.key").mkdir(parents=True)


def _empty_api_token(data: Path) -> None:
    data.mkdir()
    (data / "api.token").write_text("  \n")  # an empty token would let an empty 'Bearer ' through


CASES: dict[str, tuple[Callable[[Path], None], str]] = {
    "database path is a directory": (_directory, "is a directory"),
    "zero-length database": (_zero_length, "is empty (zero bytes)"),
    "foreign SQLite database": (_foreign, "not a fleetgcs database"),
    "empty SQLite file": (_empty_sqlite, "not a fleetgcs database"),
    "schema from a newer version": (lambda d: _with_store(d, "PRAGMA user_version=99;"), "schema version 99"),
    "dropped table": (
        lambda d: _with_store(d, "DROP TABLE vehicle_holds;"),
        "table vehicle_holds is missing",
    ),
    "dropped column": (
        lambda d: _with_store(d, "ALTER TABLE events DROP COLUMN data;"),
        "table events lacks column(s) data",
    ),
    "fleet.key not hex": (_bad_key(b"not a key\n"), "fleet.key is unusable"),
    "fleet.key too short": (_bad_key(b"abcd\n"), "at least 16 bytes"),
    "fleet.key binary": (_bad_key(b"\xff\xfe" * 32), "not ASCII hex"),
    "fleet.key a directory": (_key_is_directory, "cannot read the key file"),
    "api.token empty": (_empty_api_token, "api.token is empty"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_start_up_failure_is_one_line_and_a_non_zero_exit(tmp_path: Path, case: str) -> None:
    make, expected = CASES[case]
    data = tmp_path / "data"
    make(data)
    result = run_serve(data)
    assert not result.started, result.stderr
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("gcs serve: cannot start: ") and expected in lines[0], lines[0]


def test_a_zero_length_database_becomes_a_new_fleet_only_when_asked(tmp_path: Path) -> None:
    data = tmp_path / "data"
    _zero_length(data)
    assert not run_serve(data).started  # refused (above)
    result = run_serve(data, "--new-fleet")
    assert result.started, result.stderr
    assert "Traceback" not in result.stderr
    store = Store(_database(data))
    assert store.cid_of("drone-1") is None  # a new fleet: the operator said so
    store.close()


def test_a_fresh_data_directory_still_starts_a_new_fleet(tmp_path: Path) -> None:
    data = tmp_path / "fresh"
    result = run_serve(data)
    assert result.started, result.stderr
    assert "Traceback" not in result.stderr
    assert _database(data).stat().st_size > 0 and (data / "fleet.key").exists()
    again = run_serve(data)  # and starts again on what it made
    assert again.started, again.stderr


def test_a_bad_configured_fleet_key_is_refused_by_the_configuration() -> None:
    """FLEETGCS_FLEET_KEY_HEX / fleet_key_hex: checked with the rest of the configuration (one
    line, `gcs serve: daemon.fleet_key_hex: ...`), not when the daemon first uses it."""
    with pytest.raises(ValidationError, match="a key must be hex digits"):
        DaemonConfig(fleet_key_hex="not hex")
    with pytest.raises(ValidationError, match="at least 16 bytes"):
        DaemonConfig(fleet_key_hex="abcd")
    assert DaemonConfig(fleet_key_hex="ab" * 32).fleet_key_hex == "ab" * 32


def test_a_stored_running_mission_that_no_longer_validates_is_aborted_not_fatal(tmp_path: Path) -> None:
    """A running mission stored by another version (its task no longer validates) must not keep the
    daemon, and with it the rest of the fleet, from starting: it is ended as aborted with the reason,
    and an error event says so."""
    data = tmp_path / "data"
    data.mkdir()
    store = Store(_database(data), allow_new=True)
    store.add_mission("m-old", "old survey", '{"name": "old survey", "plans": "not a list"}', ["drone-1"])
    store.close()
    result = run_serve(data)
    assert result.started, result.stderr
    assert "Traceback" not in result.stderr
    store = Store(_database(data))
    stored = store.mission("m-old")
    events = [e for e in store.events() if e.kind == "mission_restore_failed"]
    store.close()
    assert stored is not None and stored.state == "aborted", stored
    assert stored.result.startswith("not restored after restart: ") and "plans" in stored.result
    assert len(events) == 1 and events[0].severity == "error" and events[0].mission_id == "m-old"

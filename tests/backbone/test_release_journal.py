"""The release journal (gcs/release_journal.py): a release journaled but not yet in the database
(the daemon died between the two) is in the database, with its event, once the store opens again."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gcs.release_journal import TRUNCATE_AT_BYTES
from gcs.store import Store, StoreError


def _store_with_mission(path: Path) -> Store:
    store = Store(path)
    store.add_mission("m-1", "survey", "{}", ["a1", "a2"])
    return store


def _released_events(store: Store) -> list[dict[str, object]]:
    return [e.data for e in store.events(kind="sync_released")]


def test_a_journaled_release_is_recovered_once_with_its_event(tmp_path: Path) -> None:
    db = tmp_path / "fleetgcs.sqlite"
    store = _store_with_mission(db)
    at = store.journal_release("m-1", 0)  # journaled, then "killed" before its row was written
    store.journal_release("m-1", 1)
    store.record_release("m-1", 1)  # this one made it
    store.close()

    reopened = Store(db)
    assert reopened.released_steps("m-1") == {0, 1}
    assert _released_events(reopened) == [{"step": 0, "recovered": True}]
    row = reopened._db.execute("SELECT released_at FROM releases WHERE step=0").fetchone()
    assert row == (at,)  # the journaled time, not the recovery's
    assert Path(str(db) + "-releases").read_bytes() == b""  # emptied once recovered
    reopened.close()

    again = Store(db)  # nothing left to recover: no second event
    assert _released_events(again) == [{"step": 0, "recovered": True}]
    again.close()


def test_torn_and_foreign_lines_are_skipped(tmp_path: Path) -> None:
    db = tmp_path / "fleetgcs.sqlite"
    _store_with_mission(db).close()
    journal = Path(str(db) + "-releases")
    lines = [
        json.dumps({"m": "m-unknown", "s": 3, "t": 1.0}),  # a mission this database never had
        json.dumps({"m": "m-1", "s": 2, "t": 2.0}),
        '{"m": "m-1", "s": 4, "t"',  # torn by a power cut mid-write
    ]
    journal.write_text("\n".join(lines))
    store = Store(db)
    assert store.released_steps("m-1") == {2}
    assert store.released_steps("m-unknown") == set()
    store.close()


def test_the_journal_is_emptied_only_when_every_line_is_in_the_database(tmp_path: Path) -> None:
    store = _store_with_mission(tmp_path / "fleetgcs.sqlite")
    journal = store.journal
    assert journal is not None
    steps = 0
    while journal.path.stat().st_size < TRUNCATE_AT_BYTES:  # bounded: ~40-byte lines up to 64 KiB
        store.journal_release("m-1", steps)
        steps += 1
    store.journal_release("m-1", steps)  # one more, its row not yet written
    for step in range(steps):  # the rows of all but the newest are written
        store.record_release("m-1", step)
        store.release_recorded()
    assert journal.path.stat().st_size >= TRUNCATE_AT_BYTES  # one line is still only in the journal
    store.record_release("m-1", steps)
    store.release_recorded()
    assert journal.path.stat().st_size == 0
    store.close()


def test_an_unreadable_journal_stops_the_store_from_opening(tmp_path: Path) -> None:
    """Refusing to start beats forgetting a release the agents acted on."""
    db = tmp_path / "fleetgcs.sqlite"
    _store_with_mission(db).close()
    journal = Path(str(db) + "-releases")
    journal.unlink()
    journal.mkdir()  # not a file: reading it fails
    with pytest.raises(StoreError, match="the release journal"):
        Store(db)


def test_a_journal_that_cannot_be_written_falls_back_to_the_database(tmp_path: Path) -> None:
    store = _store_with_mission(tmp_path / "fleetgcs.sqlite")
    assert store.journal is not None
    store.journal.close()  # its descriptor gone: the append fails like a full disk would
    store.journal_release("m-1", 0)
    assert store.released_steps("m-1") == {0}  # durable all the same, before it is sent
    store.journal = None
    store.close()

"""The release journal (gcs/missions/release_journal.py): a release journaled but not yet in the database
(the daemon died between the two) is in the database, with its event, once the store opens again,
and only if the database agrees (every member had finished the step). A damaged or hostile journal
never crashes the store, never floods the log, and never releases a barrier nobody reached."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from gcs.missions.release_journal import TRUNCATE_AT_BYTES
from gcs.storage.store import Store, StoreError
from protocol.packets import Resume, SyncSignal
from protocol.session import ClientHandshake
from protocol.stream import open_client
from tests.backbone.helpers import new_key, running_daemon, survey_mission
from tests.support.polling import wait_for
from tests.support.processes import run_serve


def _store_with_mission(path: Path, completed: int = -1) -> Store:
    """A store holding mission m-1 of a1 and a2, both at ``completed`` as stored."""
    store = Store(path)
    store.add_mission("m-1", "survey", "{}", ["a1", "a2"])
    for agent in ("a1", "a2"):
        store.set_completed_step("m-1", agent, completed)
    return store


def _line(mission_id: str, step: int, at: float) -> str:
    return json.dumps({"m": mission_id, "s": step, "t": at}, separators=(",", ":"))


def _released_events(store: Store) -> list[dict[str, object]]:
    return [e.data for e in store.events(kind="sync_released")]


def test_a_journaled_release_is_recovered_once_with_its_event(tmp_path: Path) -> None:
    db = tmp_path / "fleetgcs.sqlite"
    store = _store_with_mission(db, completed=1)  # both finished steps 0 and 1
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
    _store_with_mission(db, completed=4).close()
    journal = Path(str(db) + "-releases")
    lines = [
        _line("m-unknown", 3, 1.0),  # a mission this database never had
        _line("m-1", 2, 2.0),
        '{"m":"m-1","s":4,"t"',  # torn by a power cut mid-write
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


NESTED = "[" * 100_000 + "]" * 100_000
HOSTILE_LINES = {  # what each line tried, as the issue found them (a traceback or a false release)
    "step Infinity": '{"m":"m-1","s":Infinity,"t":1.0}',
    "step 1e999": '{"m":"m-1","s":1e999,"t":1.0}',
    "step NaN": '{"m":"m-1","s":NaN,"t":1.0}',
    "step 2^63": '{"m":"m-1","s":9223372036854775808,"t":1.0}',
    "step as a string": '{"m":"m-1","s":"6","t":1.0}',
    "step as a float": '{"m":"m-1","s":6.9,"t":1.0}',
    "negative step": '{"m":"m-1","s":-1,"t":1.0}',
    "step beyond any action": '{"m":"m-1","s":1000001,"t":1.0}',
    "time 1e999": '{"m":"m-1","s":6,"t":1e999}',
    "time Infinity": '{"m":"m-1","s":6,"t":Infinity}',
    "nested 100,000 deep": NESTED,
    "nested under the step": '{"m":"m-1","s":' + NESTED + ',"t":1.0}',
    "mission id not a string": '{"m":["m-1"],"s":6,"t":1.0}',
    "extra key": '{"m":"m-1","s":6,"t":1.0,"x":1}',
    "a JSON list": '["m-1",6,1.0]',
}


def _open_with_journal(tmp_path: Path, lines: list[str], completed: int = 10) -> tuple[Store, Path]:
    db = tmp_path / "fleetgcs.sqlite"
    _store_with_mission(db, completed=completed).close()
    journal = Path(str(db) + "-releases")
    journal.write_text("\n".join(lines) + "\n")
    return Store(db), journal


@pytest.mark.parametrize("case", sorted(HOSTILE_LINES))
def test_a_hostile_line_is_skipped_with_one_warning_naming_it(
    tmp_path: Path, case: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Each line the issue found crashing the start-up (OverflowError, RecursionError) or read as
    a release ("6", 6.9) is skipped; the good line after it is still recovered."""
    with caplog.at_level(logging.WARNING, logger="gcs.missions.release_journal"):
        store, journal = _open_with_journal(tmp_path, [HOSTILE_LINES[case], _line("m-1", 2, 2.0)])
    assert store.released_steps("m-1") == {2}
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "line 1 skipped" in warnings[0], warnings
    assert len(warnings[0]) < 400  # the line is not echoed back
    assert journal.read_bytes() == b""  # the skipped lines are set aside, not warned about again
    assert Path(str(journal) + ".rejected").read_text().startswith(HOSTILE_LINES[case][:50])
    store.close()


def test_a_future_barrier_nobody_reached_is_not_recovered(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A well-formed line releasing step 5 while a2 has finished only step 3 (as stored): not
    recovered, one warning saying so; recovering it let a drone fly past a barrier another had not
    reached."""
    db = tmp_path / "fleetgcs.sqlite"
    store = _store_with_mission(db, completed=5)
    store.set_completed_step("m-1", "a1", 5)
    store._db.execute("UPDATE mission_agents SET completed_step=3 WHERE agent='a2'")
    store.close()
    Path(str(db) + "-releases").write_text(_line("m-1", 3, 3.0) + "\n" + _line("m-1", 5, 5.0) + "\n")
    with caplog.at_level(logging.WARNING, logger="gcs.missions.release_journal"):
        reopened = Store(db)
    assert reopened.released_steps("m-1") == {3}  # step 3 agrees with the database; 5 does not
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, warnings
    assert "line 2" in warnings[0] and "step 5" in warnings[0] and "NOT recovered" in warnings[0]
    assert "a2" in warnings[0] and "a1" not in warnings[0]
    reopened.close()


def test_an_excluded_member_does_not_hold_a_recovered_release_back(tmp_path: Path) -> None:
    db = tmp_path / "fleetgcs.sqlite"
    store = _store_with_mission(db, completed=5)
    store._db.execute("UPDATE mission_agents SET completed_step=1 WHERE agent='a2'")
    store.exclude_agent("m-1", "a2")  # out of the mission's barriers: only a1 must have arrived
    store.close()
    Path(str(db) + "-releases").write_text(_line("m-1", 5, 5.0) + "\n")
    reopened = Store(db)
    assert reopened.released_steps("m-1") == {5}
    reopened.close()


def test_400000_lines_of_an_unknown_mission_give_a_bounded_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The issue's 400,000 lines wrote 44 MB of warnings: now the first few, then one summary."""
    from gcs.missions.release_journal import WARN_LINES

    db = tmp_path / "fleetgcs.sqlite"
    _store_with_mission(db, completed=5).close()
    Path(str(db) + "-releases").write_bytes((_line("m-nobody", 1, 1.0) + "\n").encode() * 400_000)
    with caplog.at_level(logging.WARNING, logger="gcs.missions.release_journal"):
        store = Store(db)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == WARN_LINES + 1, len(warnings)
    assert "line 1 skipped" in warnings[0] and "m-nobody" in warnings[0]
    assert "399990 more lines skipped (400000 in all" in warnings[-1]
    assert store.released_steps("m-1") == set()
    store.close()


def test_a_journal_far_beyond_its_size_stops_the_store_with_one_line(tmp_path: Path) -> None:
    from gcs.missions.release_journal import MAX_JOURNAL_BYTES

    db = tmp_path / "fleetgcs.sqlite"
    _store_with_mission(db).close()
    with open(str(db) + "-releases", "wb") as handle:
        handle.truncate(MAX_JOURNAL_BYTES + 1)  # sparse: nothing written
    with pytest.raises(StoreError, match=r"release journal .* is refused: .* bytes") as caught:
        Store(db)
    assert "\n" not in str(caught.value)


def test_gcs_serve_starts_cleanly_past_every_hostile_line(tmp_path: Path) -> None:
    """The daemon itself, as the operator runs it: starts, no traceback, a bounded log."""
    data = tmp_path / "data"
    db = data / "fleetgcs.sqlite"
    store = _store_with_mission(db, completed=2)
    store.finish_mission("m-1", "aborted", "test")  # its task "{}" is not one to resume
    store.close()
    lines = [*HOSTILE_LINES.values(), _line("m-1", 5, 5.0)] * 3  # 5: nobody finished it
    Path(str(db) + "-releases").write_text("\n".join(lines) + "\n")
    result = run_serve(data)
    assert result.started, f"gcs serve did not start: {result.stderr[-2000:]}"
    stderr = result.stderr
    assert "Traceback" not in stderr
    skipped = [line for line in stderr.splitlines() if "release journal" in line]
    assert len(skipped) == 11 and "more lines skipped" in skipped[-1], skipped  # WARN_LINES, a summary
    reopened = Store(db)
    assert reopened.released_steps("m-1") == set()
    reopened.close()


async def test_a_release_not_recovered_is_given_again_once_every_member_says_it_got_there(
    tmp_path: Path,
) -> None:
    """The crash window: release of step 1 journaled, then the daemon died before its row, with
    a2's arrival at step 1 not yet stored. The store does not recover it (the database does not
    agree); a1, which heard it and flew on, and a2, which did not and still waits at step 1,
    rejoin: their own reports are the arrivals, and a2 is released instead of timing out."""
    key = new_key()
    task = survey_mission(["a1", "a2"], sync_legs=3)
    store = Store(tmp_path / "fleetgcs.sqlite")
    store.add_mission("m-crash", task.name, task.model_dump_json(), ["a1", "a2"])
    store.record_release("m-crash", 0)
    store.set_completed_step("m-crash", "a1", 1)
    store.set_completed_step("m-crash", "a2", 0)  # its "finished 1" was in memory only
    store.journal_release("m-crash", 1)
    store.close()
    async with running_daemon(tmp_path, key, lost_after_periods=300.0) as daemon:  # silent clients
        assert daemon.store.released_steps("m-crash") == {0}  # not recovered: a2 had not arrived
        ahead, _ = await open_client(
            "127.0.0.1",
            daemon.listen_port,
            ClientHandshake("a1", bytes.fromhex(key)),
            resume=Resume(mission_id="m-crash", completed_step=2, waiting_step=2, queue_depth=2),
        )
        behind, _ = await open_client(
            "127.0.0.1",
            daemon.listen_port,
            ClientHandshake("a2", bytes.fromhex(key)),
            resume=Resume(mission_id="m-crash", completed_step=1, waiting_step=1, queue_depth=3),
        )
        try:
            released = None
            for _ in range(50):  # bounded: keepalives and other frames until the release
                body = (await behind.read_frame(timeout=10.0)).body
                if isinstance(body, SyncSignal) and body.kind == "release":
                    released = body
                    break
            assert released is not None and released.step == 1, released
            await wait_for(lambda: 1 in daemon.store.released_steps("m-crash"), 5, "release of step 1 stored")
            assert 2 not in daemon.store.released_steps("m-crash")  # a2 has not finished step 2
        finally:
            await ahead.close()
            await behind.close()


def test_gcs_log_reads_without_recovering_or_migrating(tmp_path: Path) -> None:
    """`gcs log` beside a (possibly running) daemon only reads: a journaled release stays for the
    daemon to recover with its event; the database and the journal are not touched."""
    import subprocess
    import sys

    db = tmp_path / "fleetgcs.sqlite"
    store = _store_with_mission(db, completed=0)
    store.journal_release("m-1", 0)  # journaled, the row never written (the daemon was killed)
    store.close()
    journal = Path(str(db) + "-releases")
    before = (db.read_bytes(), journal.read_bytes())
    listed = subprocess.run(
        [str(Path(sys.executable).parent / "gcs"), "log", "agents", "--database", str(db)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert listed.returncode == 0, listed.stderr
    assert (db.read_bytes(), journal.read_bytes()) == before
    reopened = Store(db)  # the daemon's own open still recovers it, once
    assert reopened.released_steps("m-1") == {0}
    assert _released_events(reopened) == [{"step": 0, "recovered": True}]
    reopened.close()

"""The event loop takes the store's write lock ahead of the telemetry writer (Store.insert_telemetry).

A barrier release is persisted before it is sent; it must not wait for the writer's whole
chunk. Here the chunk is 50,000 rows (about a quarter of a second of inserts or more): the
loop's turn comes after a part of it, committed, not after all of it.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from gcs.storage import store as store_module
from gcs.storage.store import Store
from tests.backbone.helpers import telemetry_row

ROWS = 50_000


@pytest.mark.parametrize("explicit", [True, False], ids=["write_priority", "plain-state-write"])
def test_the_loop_gets_the_write_lock_within_the_writers_chunk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, explicit: bool
) -> None:
    monkeypatch.setattr(store_module, "TELEMETRY_CHUNK", ROWS)  # one chunk: without yielding, all or nothing
    store = Store(tmp_path / "fleet.db")
    store.add_mission("m-1", "barrier", "{}", ["drone-1"])
    db = store.writer()
    rows = [telemetry_row("drone-1", 1000.0 + i * 0.1, 2000.0 + i * 0.1) for i in range(ROWS)]
    started = threading.Event()

    def write() -> None:
        started.set()
        store_module.insert_telemetry(db, rows, store.write_lock, store.write_wanted)

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    assert started.wait(10)
    time.sleep(0.02)  # the writer is inside its chunk (50,000 rows take far longer)
    if explicit:  # the barrier's way: the lock held through persist and burst
        with store.write_priority():
            seen = store._db.execute("SELECT COUNT(*) FROM telemetry").fetchone()[0]
            store.record_release("m-1", 0)  # the loop's own write goes through while it holds the lock
    else:  # any state write of the store (an event, a completed step) gets the same priority
        store.record_release("m-1", 0)
        seen = store._db.execute("SELECT COUNT(*) FROM telemetry").fetchone()[0]
    writer.join(60)
    assert not writer.is_alive()
    assert 0 < seen < ROWS, f"the loop waited for the whole chunk ({seen} rows committed first)"
    assert store._db.execute("SELECT COUNT(*) FROM telemetry").fetchone()[0] == ROWS  # nothing lost
    assert store.released_steps("m-1") == {0}
    db.close()

"""The release journal: a barrier release made durable with one ``write`` before anyone hears of it.

Why: a release must be stored before it is sent (an agent released by a daemon that then dies
must not be told to wait at that barrier again after the restart). Stored in SQLite, that meant
waiting for the write lock (the telemetry writer's row and commit) and a transaction on the
event loop before the first datagram went out: 0.4-1.7 ms at the median, several ms at p99 with
1,000 agents (docs/performance.md, round 7). The journal is one append of one line to a file
beside the database (``<database>-releases``): no lock, no transaction, durable across a
``kill -9`` like SQLite's own WAL at ``synchronous=NORMAL`` (the page cache survives the
process; a power cut may lose the newest lines of either). The release row and its event go into
SQLite right after the burst; a release journaled but not yet in the database is recovered when
the store opens (:meth:`gcs.store.Store.recover_releases`).

Line format: ``{"m": mission_id, "s": step, "t": unix_time}`` as JSON, one per line. A torn
last line (a power cut mid-write) is skipped when read.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

TRUNCATE_AT_BYTES = 64 << 10
"""The journal is emptied once it is this long and every line in it is in the database."""


class ReleaseJournal:
    """Append-only file of releases not yet known to be in the database."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        self._size = os.fstat(self._fd).st_size
        self.unrecorded = 0  # lines appended whose database row has not been written yet

    def append(self, mission_id: str, step: int, at: float) -> None:
        """Make the release of ``step`` durable: one ``write`` of one line (atomic for an append)."""
        line = json.dumps({"m": mission_id, "s": step, "t": at}, separators=(",", ":")).encode() + b"\n"
        os.write(self._fd, line)
        self._size += len(line)
        self.unrecorded += 1

    def recorded(self) -> None:
        """The newest appended release is in the database; empty the file once it is long and all are."""
        self.unrecorded = max(0, self.unrecorded - 1)
        if self.unrecorded == 0 and self._size >= TRUNCATE_AT_BYTES:
            self.clear()

    def entries(self) -> list[tuple[str, int, float]]:
        """Every well-formed line: (mission_id, step, time); a torn or foreign line is skipped."""
        out: list[tuple[str, int, float]] = []
        try:
            text = self.path.read_bytes()
        except FileNotFoundError:
            return out
        for raw in text.splitlines():
            try:
                item = json.loads(raw)
                out.append((str(item["m"]), int(item["s"]), float(item["t"])))
            except (ValueError, KeyError, TypeError):
                log.warning("release journal %s: skipped an unreadable line %r", self.path, raw[:80])
        return out

    def clear(self) -> None:
        os.ftruncate(self._fd, 0)
        self._size = 0
        self.unrecorded = 0

    def close(self) -> None:
        os.close(self._fd)

"""Telemetry logging: every agent's status reports into the daemon's SQLite file, and flight logs out.

Samples are batched and written every ``flush_s`` by a writer thread on its own SQLite
connection (transactions of at most ``gcs.storage.store.TELEMETRY_CHUNK`` rows), optionally downsampled
to one per ``period_s`` per agent, and pruned after ``retention_s`` (in chunks, in the same
thread). The event loop only appends each status tick's rows, as NumPy columns
(:class:`TickRows`; the writer thread makes the tuples), to the writer's bounded buffer: when the thread
falls ``max_queued_rows`` behind, the oldest waiting rows are dropped and counted
(``dropped``), the loop never waits. A daemon killed with ``kill -9`` loses at most the last
``flush_s`` of samples. Steps, sync releases, missions and events are written at once, not
batched. History pages are read in a worker thread on a read-only connection
(:meth:`TelemetryRecorder.history_page`).

Replayed (``buffered``) reports of a version-2 agent are acknowledged once they are durable: each
block carries, per agent, the newest replayed report time it holds, and after the writer thread
committed the block the recorder sends the agent a type 3 ``replay_stored`` with that time
(docs/protocol.md section 2), so the agent keeps its replay until then and a daemon killed in
between loses none of it. The store ignores a replayed row it already has (same agent and
time), so a replay sent again is not stored twice. A replayed report lost on the way (a hook
queue or the row buffer overflowed, a failed write) stops the acknowledgements of the agents it
may concern until the daemon restarts: an acknowledgement covers every earlier time, so it must
never be sent over a hole; those agents keep replaying their reports (bounded) on each rejoin.

Flight logs: CSV (one row per sample, the columns of :data:`CSV_COLUMNS`) and GeoJSON (one
LineString per flight), with flights split at each arm...landed-and-disarmed cycle.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import csv
import io
import itertools
import json
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from gcs.core.config import TelemetryConfig
from gcs.link.agents_table import StatusTick
from gcs.observe.memory import release_free_memory
from gcs.storage.store import Store, checkpoint, insert_telemetry, prune_telemetry, telemetry_page_json
from protocol.packets import StatusReport
from protocol.status_binary import ARMED, BUFFERED, HAS_POSITION, LANDED

if TYPE_CHECKING:
    from gcs.core.context import ServiceContext

log = logging.getLogger("gcs.observe.telemetry")

CSV_COLUMNS = (
    "time", "gps_fix", "satellites", "lat", "lon", "alt_rel", "alt_amsl", "vn", "ve", "vd", "heading_deg",
    "battery_pct", "voltage_v", "current_a", "mode", "armed", "landed", "step", "mission_id",
)  # fmt: skip
# gps_fix is the GPS fix type (0-1 none, 2 2D, 3 3D, 4 DGPS, 5 RTK float, 6 RTK fixed): a position
# without a 3D fix is not a place the vehicle was, so readers can drop or flag those rows.


def status_row(agent: str, status: StatusReport, received: float) -> tuple[Any, ...]:
    """One telemetry row in ``gcs.storage.store.TELEMETRY_COLUMNS`` order."""
    p, v, b = status.position, status.velocity, status.battery
    if p is None:
        raise ValueError(f"{agent}: a status without a position (no 3-D fix yet) makes no telemetry row")
    return (
        agent, status.time, received, p.lat, p.lon, p.alt_rel, p.alt_amsl, v.vn, v.ve, v.vd,
        status.heading_deg, b.pct, b.voltage_v, b.current_a, status.mode, int(status.armed),
        int(status.landed), status.gps.fix, status.gps.satellites, status.step, status.mission_id,
        int(status.buffered),
    )  # fmt: skip


class TickRows:
    """A status tick's telemetry rows, kept as NumPy columns until the writer thread makes tuples
    of them (:meth:`rows`): a row waiting for the writer costs ~140 bytes here against ~570 as a
    tuple of Python floats, and the tuples are made off the event loop, a chunk at a time."""

    __slots__ = ("cols", "decoded", "identities", "modes", "received")

    def __init__(self, tick: StatusTick, received: float) -> None:
        index = np.flatnonzero(tick.cols["flags"] & HAS_POSITION)
        at = index.tolist()
        owners = tick.owners
        self.cols = tick.cols[index]  # a copy: the tick's buffers are reused
        self.identities = [owners[i].identity for i in at]
        self.modes = [tick.mode_mission(i) for i in at]
        self.received = received
        # A report that came decoded (JSON) may hold what a column cannot: its own row.
        self.decoded: dict[int, tuple[Any, ...]] = {}
        for n, i in enumerate(at):
            report = tick.decoded(i)
            if report is not None:
                self.decoded[n] = status_row(owners[i].identity, report, received)

    def __len__(self) -> int:
        return len(self.identities)

    def rows(self) -> Iterator[tuple[Any, ...]]:
        """The rows in ``TELEMETRY_COLUMNS`` order, as :func:`status_row` gives them."""
        c, modes, count = self.cols, self.modes, len(self.identities)
        if not count:
            return iter(())
        flags = c["flags"]

        def optional(name: str) -> list[Any]:
            values = c[name]
            out = values.astype(object)
            out[np.isnan(values)] = None
            return out.tolist()

        rows = zip(
            self.identities, c["time"].tolist(), [self.received] * count,
            c["lat"].tolist(), c["lon"].tolist(), c["alt_rel"].tolist(), c["alt_amsl"].tolist(),
            c["vn"].tolist(), c["ve"].tolist(), c["vd"].tolist(), c["heading_deg"].tolist(),
            optional("battery_pct"), optional("voltage_v"), optional("current_a"), [m[0] for m in modes],
            ((flags & ARMED) != 0).astype(int).tolist(), ((flags & LANDED) != 0).astype(int).tolist(),
            c["fix"].tolist(), c["satellites"].tolist(), c["step"].tolist(), [m[1] for m in modes],
            ((flags & BUFFERED) != 0).astype(int).tolist(),
            strict=True,
        )  # fmt: skip
        if not self.decoded:
            return rows
        decoded = self.decoded
        return (decoded.get(n, row) for n, row in enumerate(rows))


RowBlock = TickRows | list[tuple[Any, ...]]
"""What the writer queues: a tick's rows as columns, or rows already made."""
Acks = dict[str, float]
"""Per agent identity, the newest replayed report time a block holds (acknowledged once written)."""


def _rows_of(block: RowBlock) -> Iterable[tuple[Any, ...]]:
    return block.rows() if isinstance(block, TickRows) else block


TRIM_EVERY_S = 5.0
"""How often the writer thread returns the allocator's free memory (gcs/observe/memory.py)."""
MAX_QUEUED_ROWS = 500_000
"""Rows waiting for the writer thread before the oldest are dropped (about 100 s at 500 agents x 10 Hz)."""
HISTORY_QUERIES = 1
"""History pages read at once; more requests wait their turn (off the loop, not blocking it).
One: each is CPU-bound, and every extra thread competes with the event loop for the GIL."""


class TelemetryWriter:
    """One thread that owns the telemetry inserts and pruning, fed through a bounded row buffer."""

    def __init__(
        self,
        store: Store,
        config: TelemetryConfig,
        max_rows: int = MAX_QUEUED_ROWS,
        on_stored: Callable[[Acks], None] | None = None,
    ) -> None:
        self._store = store
        self.config = config
        self._on_stored = on_stored  # called (on the writer's thread) with the acks of what was committed
        self.withheld: set[str] = set()  # agents whose replayed rows went unwritten: never acknowledged
        self._blocks: collections.deque[tuple[RowBlock, Acks | None]] = collections.deque()
        self._queued = 0  # rows in _blocks
        self._max_rows = max_rows
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._done = threading.Condition()
        self._requested = 0  # flush requests made / completed (under _done)
        self._completed = 0
        self._stopping = False
        self.written = 0
        self.dropped = 0
        self.failed_batches = 0
        self._thread = threading.Thread(target=self._run, name="telemetry-writer", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def add(self, row: tuple[Any, ...]) -> None:
        """Queue one row; O(1), never blocks on SQLite."""
        self.add_block([row])

    def add_block(self, block: RowBlock, acks: Acks | None = None) -> None:
        """Queue a block of rows (a tick's columns, or tuples); when the buffer is full the oldest
        blocks go, counted in ``dropped`` (whole blocks: at most one tick's rows more than needed).
        ``acks`` are reported to ``on_stored`` once this block and every one before it is written."""
        size = len(block)
        if not size and not acks:
            return
        with self._lock:
            self._blocks.append((block, acks))
            self._queued += size
            while self._queued > self._max_rows and len(self._blocks) > 1:
                gone, lost = self._blocks.popleft()
                self._queued -= len(gone)
                self.dropped += len(gone)
                if lost:
                    self.withheld.update(lost)

    @property
    def pending(self) -> int:
        return self._queued

    def flush(self, timeout: float = 30.0) -> bool:
        """Write everything queued so far and wait for it (blocking: tests, shutdown, CLI)."""
        if not self._thread.is_alive():  # not started (in-memory store) or stopped: write here
            self._write(self._store.add_telemetry)
            return True
        with self._done:
            self._requested += 1
            target = self._requested
        self._wake.set()
        with self._done:
            return self._done.wait_for(lambda: self._completed >= target, timeout)

    def stop(self, timeout: float = 30.0) -> None:
        """Write what is left and end the thread (blocking; call it off the loop)."""
        self._stopping = True
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        db = self._store.writer()
        wanted = self._store.write_wanted
        last_prune = last_trim = 0.0
        try:
            while True:
                self._wake.wait(self.config.flush_s)
                self._wake.clear()
                with self._done:
                    target = self._requested
                if self._write(lambda rows: insert_telemetry(db, rows, self._store.write_lock, wanted)):
                    checkpoint(db)
                with self._done:
                    self._completed = max(self._completed, target)
                    self._done.notify_all()
                if self._stopping:
                    return
                now = time.monotonic()
                if now - last_trim >= TRIM_EVERY_S:
                    last_trim = now
                    release_free_memory()  # the blocks' tuples just freed: give the pages back
                if now - last_prune >= self.config.prune_every_s:
                    last_prune = now
                    self._prune(db)
        finally:
            db.close()

    def _write(self, insert: Callable[[Iterable[tuple[Any, ...]]], object]) -> bool:
        """Write what is queued (its tuples made here, a block at a time); True if anything was."""
        with self._lock:
            blocks = list(self._blocks)
            count = self._queued
            self._blocks.clear()
            self._queued = 0
        if not blocks:
            return False
        acks: Acks = {}
        for _, block_acks in blocks:
            for identity, until in (block_acks or {}).items():
                acks[identity] = max(until, acks.get(identity, until))
        try:
            insert(itertools.chain.from_iterable(_rows_of(block) for block, _ in blocks))
            self.written += count
        except sqlite3.Error:  # a full disk or a locked file costs this batch, not the daemon
            self.failed_batches += 1
            self.withheld.update(acks)
            log.exception("telemetry: could not write %d samples", count)
            return False
        stored = {identity: until for identity, until in acks.items() if identity not in self.withheld}
        if stored and self._on_stored is not None:
            self._on_stored(stored)
        return count > 0

    def _prune(self, db: sqlite3.Connection) -> None:
        try:
            removed = prune_telemetry(db, time.time() - self.config.retention_s, self._store.write_lock)
        except sqlite3.Error:
            log.exception("telemetry: pruning failed")
            return
        if removed:
            log.info("pruned %d telemetry samples older than %.0f s", removed, self.config.retention_s)


class TelemetryRecorder:
    """A daemon service: logs status reports through the writer thread; serves history pages."""

    name = "telemetry"

    def __init__(self, config: TelemetryConfig) -> None:
        self.config = config
        self._store: Store | None = None
        self._writer: TelemetryWriter | None = None
        self._last_kept: dict[str, float] = {}
        self._queries = asyncio.Semaphore(HISTORY_QUERIES)
        self._ctx: ServiceContext | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._hook_drops = 0  # ticks this service's hook queue dropped, as of the last check
        self.acks_off = False  # a tick was dropped: replayed reports are no longer acknowledged
        self.acks_sent = 0

    async def start(self, ctx: ServiceContext) -> None:
        self._ctx, self._loop = ctx, asyncio.get_running_loop()
        if not self.config.enabled:  # nothing is stored, so nothing to keep: replays acknowledged at once
            ctx.agents.on_status_tick.append(self._ack_only)
            return
        self._store = ctx.store
        self._writer = TelemetryWriter(ctx.store, self.config, on_stored=self._stored)
        if ctx.store.path != ":memory:":
            self._writer.start()  # an in-memory store is written on flush, on its one connection
        ctx.agents.on_status_tick.append(self._on_tick)

    async def stop(self) -> None:
        if self._writer is not None:
            await asyncio.to_thread(self._writer.stop)
            self._writer.flush()  # the thread has ended: writes what a late hook added

    @property
    def written(self) -> int:
        return self._writer.written if self._writer else 0

    @property
    def dropped(self) -> int:
        return self._writer.dropped if self._writer else 0

    def _replay_acks(self, tick: StatusTick) -> Acks | None:
        """Per version-2 agent, the newest replayed report time in ``tick`` (None: no replayed reports).

        None as well once any tick was dropped on the way here: an acknowledgement covers every
        earlier report, and a dropped one was not stored.
        """
        replayed = np.flatnonzero(tick.cols["flags"] & BUFFERED)
        if not len(replayed) or self.acks_off or self._ctx is None:
            return None
        mine = type(self).__name__
        drops = sum(s.dropped for s in self._ctx.agents.hook_stats() if s.name.startswith(mine))
        if drops != self._hook_drops:
            self._hook_drops, self.acks_off = drops, True
            log.warning("telemetry: status ticks were dropped; replayed reports are no longer acknowledged")
            return None
        acks: Acks = {}
        times = tick.cols["time"]
        for i in replayed.tolist():
            owner = tick.owners[i]
            if owner.version >= 2:
                acks[owner.identity] = max(float(times[i]), acks.get(owner.identity, float(times[i])))
        return acks or None

    def _stored(self, acks: Acks) -> None:
        """The writer committed replayed reports (its thread): acknowledge them on the loop."""
        loop = self._loop
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop has closed: the daemon is gone
                loop.call_soon_threadsafe(self._acknowledge, acks)

    def _acknowledge(self, acks: Acks) -> None:
        """Tell each agent (its current session, version 2) up to which time its replay is stored."""
        if self._ctx is None:
            return
        for identity, until in acks.items():
            session = self._ctx.agents.session(identity)
            if session is None or session.version < 2:
                continue
            if self._ctx.commands.acknowledge_replay(identity, until):  # through the command port
                self.acks_sent += 1

    async def _ack_only(self, tick: StatusTick) -> None:
        """Telemetry off: replayed reports are acknowledged as they arrive (nothing will store them)."""
        acks = self._replay_acks(tick)
        if acks:
            self._acknowledge(acks)

    async def _on_tick(self, tick: StatusTick) -> None:
        """A status tick's rows, straight from its columns (one lock, no report objects)."""
        if self._writer is None:
            return
        block = TickRows(tick, time.time())
        acks = self._replay_acks(tick)
        if acks and self._store is not None and self._store.path == ":memory:":
            self._acknowledge(acks)  # nothing in memory outlives the process: no reason to keep them
            acks = None
        if self.config.period_s <= 0:
            self._writer.add_block(block, acks)  # tuples are made by the writer thread
            return
        kept, period, last_kept = [], self.config.period_s, self._last_kept
        for row in block.rows():  # downsampled: one row per agent per period_s
            last = last_kept.get(row[0])
            if last is not None and 0 <= row[1] - last < period:
                continue
            last_kept[row[0]] = row[1]
            kept.append(row)
        self._writer.add_block(kept, acks)

    def flush(self) -> None:
        """Write every queued sample now (blocks until written: tests and tools, not the loop)."""
        if self._writer is not None:
            self._writer.flush()

    def history(self, identity: str, since: float = 0.0, limit: int = 1000) -> list[dict[str, Any]]:
        """Logged samples of ``identity`` since ``since`` (agent time), oldest first, queue flushed.

        Blocking (flush and query on the calling thread): for tests and tools. The API uses
        :meth:`history_page`.
        """
        self.flush()
        if self._store is None:
            return []
        return self._store.telemetry(identity, since, limit=limit)

    async def history_json(self, identity: str, since: float, until: float, limit: int, every: int) -> bytes:
        """The newest ``limit`` logged samples in [since, until], every ``every``-th, oldest first.

        A JSON array of ``gcs.observe.live.StatusSample``, built by SQLite in a worker thread on its own
        read-only connection (at most ``HISTORY_QUERIES`` at once), so the event loop keeps
        serving agents while it runs. Samples still waiting for the writer (the last
        ``flush_s``) are not included.
        """
        store = self._store
        if store is None:
            return b"[]"
        if store.path == ":memory:":
            return telemetry_page_json(store._db, identity, since, until, limit, every)
        async with self._queries:
            return await asyncio.to_thread(_read_page, store, identity, since, until, limit, every)


def _read_page(store: Store, identity: str, since: float, until: float, limit: int, every: int) -> bytes:
    db = store.reader()
    try:
        return telemetry_page_json(db, identity, since, until, limit, every)
    finally:
        db.close()


def split_flights(samples: list[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    """Cut a sample list into flights: from arming to being landed and disarmed again."""
    flights: list[list[dict[str, Any]]] = []
    current: list[dict[str, Any]] = []
    for sample in samples:
        if sample["armed"]:
            current.append(sample)
        elif current:
            current.append(sample)  # the landed-and-disarmed sample closes the flight
            flights.append(current)
            current = []
    if current:
        flights.append(current)
    return flights


def to_csv(samples: Iterable[dict[str, Any]]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for s in samples:
        writer.writerow(["" if s[c] is None else s[c] for c in CSV_COLUMNS])
    return out.getvalue()


def to_geojson(agent: str, flights: list[list[dict[str, Any]]]) -> dict[str, Any]:
    features = []
    for index, flight in enumerate(flights):
        fixed = [s for s in flight if s["gps_fix"] >= 3 and s["lat"] is not None]
        coordinates = [[s["lon"], s["lat"], s["alt_rel"]] for s in fixed]
        if len(coordinates) < 2:
            continue
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "LineString", "coordinates": coordinates},
                "properties": {
                    "agent": agent,
                    "flight": index,
                    "start": flight[0]["time"],
                    "end": flight[-1]["time"],
                    "missions": sorted({s["mission_id"] for s in flight if s["mission_id"]}),
                    "gps_fix": [s["gps_fix"] for s in fixed],  # one per coordinate
                    "samples_without_3d_fix": len(flight) - len(fixed),
                },
            }
        )
    return {"type": "FeatureCollection", "features": features}


def to_geojson_text(agent: str, flights: list[list[dict[str, Any]]]) -> str:
    return json.dumps(to_geojson(agent, flights), indent=1)

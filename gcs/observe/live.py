"""Live view of the fleet for the API and the dashboard: status rings, event ring, stream fan-out.

The agent manager keeps only each agent's latest status; operators also need a short history
(flown tracks, link age, coverage so far) and a push stream. :class:`LiveHub` hooks
``on_status_tick`` and subscribes to the event bus once, keeps a bounded ring per agent, and
hands each message, serialised once, to every WebSocket client's bounded queue. A slow client
loses its oldest messages (counted), never slows the daemon or the other clients.

Why the tick: with the API on, an ``on_status`` hook made the daemon build a ``StatusReport``
for every report of every agent (and the hub a ``StatusSample`` on top). From the tick's columns
the ring keeps each compact report as the bytes it came in (a report that came decoded as its
object); a ``StatusReport`` is built only for a WebSocket client that wants that agent's status
now (once per report, whatever the number of clients) and for history pages and tracks when
they are read.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import struct
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from pydantic import BaseModel, TypeAdapter

from gcs.link.agents_table import FIXED_DTYPE, MAX_BODY, ROW_BYTES, StatusTick
from gcs.observe.events import Event
from gcs.observe.metrics import DaemonMetrics
from protocol import status_binary
from protocol.packets import Geofence, StatusReport

if TYPE_CHECKING:
    from gcs.core.context import DaemonParts, ServiceContext
    from gcs.link.session import AgentSession

log = logging.getLogger("gcs.observe.live")


class StatusSample(BaseModel):
    """One status report with the daemon's receive time (UNIX s)."""

    received: float
    status: StatusReport


_SAMPLES = TypeAdapter(list[StatusSample])

Payload = bytes | StatusReport
"""A ring entry's report: the compact body as it came (decoded when read), or the report object
of one that came decoded (JSON, tail, replayed)."""
Entry = tuple[float, Payload, str | None]
"""One sample in an agent's ring: daemon receive time (UNIX s), the report, its mission id."""
_LAT_LON = struct.Struct("<dd")
_LAT_LON_ALT = struct.Struct("<ddd")  # lat, lon, alt_rel are consecutive in the fixed part
_LAT_AT = FIXED_DTYPE.fields["lat"][1]  # type: ignore[index]
assert FIXED_DTYPE.fields["lon"][1] == _LAT_AT + 8  # type: ignore[index]
assert FIXED_DTYPE.fields["alt_rel"][1] == _LAT_AT + 16  # type: ignore[index]


def sample_report(payload: Payload) -> StatusReport:
    """The report of a ring entry (a compact body is decoded, and checked, here)."""
    return payload if isinstance(payload, StatusReport) else status_binary.decode(payload)


def _position3(payload: Payload) -> tuple[float, float, float] | None:
    """(lat, lon, alt_rel) of a ring entry, or None (the coverage map needs the height)."""
    if isinstance(payload, StatusReport):
        p = payload.position
        return None if p is None else (p.lat, p.lon, p.alt_rel)
    if not payload[1] & status_binary.HAS_POSITION:
        return None
    lat, lon, alt = _LAT_LON_ALT.unpack_from(payload, _LAT_AT)
    return float(lat), float(lon), float(alt)


def _position(payload: Payload) -> tuple[float, float] | None:
    """(lat, lon) of a ring entry, or None; no report built for a compact body."""
    if isinstance(payload, StatusReport):
        p = payload.position
        return None if p is None else (p.lat, p.lon)
    if not payload[1] & status_binary.HAS_POSITION:
        return None
    lat, lon = _LAT_LON.unpack_from(payload, _LAT_AT)
    return float(lat), float(lon)


@dataclass(eq=False)
class StreamClient:
    """One WebSocket subscriber: filters, a minimum interval per agent, a bounded queue of JSON texts."""

    status: bool = True
    events: bool = True
    coverage: bool = True
    agents: frozenset[str] | None = None
    min_interval_s: float = 0.0
    queue_size: int = 5000
    max_bytes: int = 1 << 20
    queue: asyncio.Queue[str] = field(init=False)
    dropped: int = 0
    queued_bytes: int = 0
    _last_sent: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.queue = asyncio.Queue(self.queue_size)

    def offer(self, text: str) -> None:
        # Bounded in count and bytes; drop the oldest: a live view wants the newest state.
        while self.queue.full() or (
            self.queued_bytes + len(text) > self.max_bytes and not self.queue.empty()
        ):
            self.queued_bytes -= len(self.queue.get_nowait())
            self.dropped += 1
        self.queue.put_nowait(text)
        self.queued_bytes += len(text)

    def wants_status(self, identity: str, now: float) -> bool:
        """Whether this client gets ``identity``'s report received at ``now`` (filters, rate)."""
        if not self.status or (self.agents is not None and identity not in self.agents):
            return False
        if self.min_interval_s > 0:
            if now - self._last_sent.get(identity, 0.0) < self.min_interval_s:
                return False
            self._last_sent[identity] = now
        return True

    async def next_batch(self, max_items: int = 500) -> str:
        """Wait for at least one message; return everything queued (up to ``max_items``) as a JSON array."""
        items = [await self.queue.get()]
        while len(items) < max_items and not self.queue.empty():
            items.append(self.queue.get_nowait())
        self.queued_bytes -= sum(len(item) for item in items)
        return "[" + ",".join(items) + "]"


class CoverageSource(Protocol):
    """What builds the ``coverage`` messages (gcs/missions/live_coverage.py: ``CoverageFeed``)."""

    async def messages(self) -> list[tuple[str, str]]: ...


COVERAGE_INTERVAL_S = 1.0
"""The coverage messages' period: a raster per survey mission per second at most, off the loop."""
HISTORY_BUDGET = 200_000
"""Status entries the live rings hold over the whole fleet (~60 MB); see ``LiveHub.ring_size``."""
MIN_RING = 50
"""Entries an agent's ring keeps however large the fleet (5 s at 10 Hz)."""


class LiveHub:
    """Rings and fan-out for one daemon; also the daemon's metrics and the operator's last geofence."""

    name = "live-hub"

    def __init__(
        self,
        daemon: DaemonParts,
        history_size: int = 3000,
        event_ring: int = 2000,
        history_budget: int = HISTORY_BUDGET,
    ) -> None:
        self._daemon = daemon
        self.metrics = DaemonMetrics(daemon)
        self.history: dict[str, collections.deque[Entry]] = {}
        self.recent_events: collections.deque[Event] = collections.deque(maxlen=event_ring)
        self.clients: set[StreamClient] = set()
        self.geofence: Geofence | None = None
        self.plans: dict[str, Any] = {}  # mission id -> PlanPreview of missions started from a plan
        self._history_size = history_size  # per agent, for a small fleet (5 min at 10 Hz)
        self.history_budget = history_budget  # entries over the whole fleet (set before agents join)
        self._ring_size = history_size  # what new rings get now (the budget shared by the fleet)
        self._events_queue: asyncio.Queue[Event] | None = None
        self._pump: asyncio.Task[None] | None = None
        self.coverage_source: CoverageSource | None = None  # set by the HTTP app (create_app)
        self.coverage_interval_s = COVERAGE_INTERVAL_S
        self.coverage_latest: dict[str, str] = {}  # mission id -> its newest coverage message
        self._coverage_pump: asyncio.Task[None] | None = None
        daemon.agents.on_status_tick.append(self._on_tick)
        daemon.agents.on_sync.append(self._on_sync)

    # --- lifecycle (a Service: the daemon stops it with its other services) ------------------------

    async def start(self, ctx: ServiceContext | None = None) -> None:
        if self._pump is None:
            self._events_queue = self._daemon.events.subscribe()
            self._pump = asyncio.create_task(self._pump_events(), name="live-hub-events")
        if self._coverage_pump is None:
            self._coverage_pump = asyncio.create_task(self._pump_coverage(), name="live-hub-coverage")

    async def stop(self) -> None:
        if self._coverage_pump is not None:
            self._coverage_pump.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._coverage_pump
            self._coverage_pump = None
        if self._pump is not None:
            self._pump.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._pump
            self._pump = None
        if self._events_queue is not None:
            self._daemon.events.unsubscribe(self._events_queue)
            self._events_queue = None

    # --- inputs -----------------------------------------------------------------------------------

    async def _on_tick(self, tick: StatusTick) -> None:
        """A status tick: each row into its agent's ring, the metrics, and the stream clients."""
        count = len(tick)
        if not count:
            return
        raw = tick.cols.view(np.uint8).reshape(count, ROW_BYTES)
        sizes = raw[:, MAX_BODY].tolist()
        paused = ((tick.cols["flags"] & status_binary.PAUSED) != 0).tolist()
        received = tick.received.tolist()
        streaming = bool(self.clients)
        for i, session in enumerate(tick.owners):
            report = tick.decoded(i)
            if report is not None:
                self._record(session, received[i], report, report.mission_id, report.paused, streaming)
                continue
            payload = raw[i, : sizes[i]].tobytes()
            mission = tick.mode_mission(i)[1]
            self._record(session, received[i], payload, mission, paused[i], streaming, tick, i)

    def _record(
        self,
        session: AgentSession,
        received: float,
        payload: Payload,
        mission: str | None,
        paused: bool,
        streaming: bool,
        tick: StatusTick | None = None,
        index: int = 0,
    ) -> None:
        """One report: ring, metrics, and (built once, only if a client wants it) the stream message."""
        identity = session.identity
        ring = self.history.get(identity)
        if ring is None:
            ring = self._new_ring(identity)
        ring.append((received, payload, mission))
        self.metrics.on_report(identity, paused)
        if not streaming:
            return
        text: str | None = None
        for client in self.clients:
            if client.wants_status(identity, received):
                if text is None:
                    status = tick.report(index) if tick is not None else sample_report(payload)
                    text = (
                        f'{{"type":"status","agent":{json.dumps(identity)},"cid":{session.cid},'
                        f'"received":{received!r},"status":{status.model_dump_json(exclude_none=True)}}}'
                    )
                client.offer(text)

    def ring_size(self, agents: int) -> int:
        """Ring length per agent for a fleet of ``agents``: ``history_size`` while the fleet's
        rings fit ``history_budget`` entries, then the budget shared (at least ``MIN_RING``).
        Older history pages come from the telemetry log, so a large fleet loses nothing; the
        rings only bound the daemon's memory (an entry is ~290 bytes: 3,000 of them for each of
        2,000 drones would be 1.7 GB)."""
        return max(MIN_RING, min(self._history_size, self.history_budget // max(1, agents)))

    def _new_ring(self, identity: str) -> collections.deque[Entry]:
        """A ring for a new agent; when the fleet has grown past the budget by half again, every
        ring is cut to the new share (its newest entries kept; rare: the share halves at most
        once per doubling of the fleet)."""
        size = self.ring_size(len(self.history) + 1)
        if size * 3 < self._ring_size * 2:
            for name, old in self.history.items():
                self.history[name] = collections.deque(old, maxlen=size)
            self._ring_size = size
        ring = self.history[identity] = collections.deque(maxlen=self._ring_size)
        return ring

    async def remote_status(self, session: AgentSession, status: StatusReport) -> None:
        """A status of a drone linked to another daemon of the cluster (gcs/cluster/node.py): the
        dashboard's stream, history and metrics show the whole fleet."""
        self._record(session, time.time(), status, status.mission_id, status.paused, bool(self.clients))

    async def _on_sync(self, session: AgentSession, signal: Any) -> None:
        self.metrics.on_sync(session, signal)

    async def _pump_events(self) -> None:
        assert self._events_queue is not None
        while True:
            event = await self._events_queue.get()
            self.recent_events.append(event)
            self.metrics.on_event(event)
            if self.clients:
                text = f'{{"type":"event","event":{event.model_dump_json()}}}'
                for client in self.clients:
                    if client.events and (
                        client.agents is None or event.agent is None or event.agent in client.agents
                    ):
                        client.offer(text)

    async def _pump_coverage(self) -> None:
        """Every ``coverage_interval_s`` while someone streams: one message per running survey
        (built in a worker thread by the source), sent only when it changed; a new client gets the
        newest of each at once (:meth:`subscribe`)."""
        while True:
            await asyncio.sleep(self.coverage_interval_s)
            if self.coverage_source is None or not any(c.coverage for c in self.clients):
                continue
            try:
                messages = await self.coverage_source.messages()
            except Exception:  # a bad raster costs one period, not the feed
                log.exception("coverage messages failed")
                continue
            running = {mission for mission, _ in messages}
            for mission in [m for m in self.coverage_latest if m not in running]:
                del self.coverage_latest[mission]
            for mission, text in messages:
                if self.coverage_latest.get(mission) == text:
                    continue
                self.coverage_latest[mission] = text
                for client in self.clients:
                    if client.coverage:
                        client.offer(text)

    # --- reads ------------------------------------------------------------------------------------

    async def history_json(
        self, identity: str, since: float = 0.0, until: float | None = None, limit: int = 1000, every: int = 1
    ) -> bytes:
        """The newest ``limit`` samples after ``since`` (every ``every``-th), oldest first, as JSON.

        Recent history comes from the in-memory ring (``since`` and ``until`` compare with the
        daemon's receive time); a ``since`` older than the ring reads the telemetry log (agent
        time) in a worker thread. Building and serialising the page also runs off the loop: the
        caller bounds ``limit`` and ``limit * every`` (see gcs/http/routes/history.py).
        """
        ring = self.history.get(identity, ())
        telemetry = getattr(self._daemon, "telemetry", None)
        older = since > 0 and (not ring or since < ring[0][0])
        if older and telemetry is not None and hasattr(telemetry, "history_json"):
            encoded: bytes = await telemetry.history_json(
                identity, since, until if until is not None else float("inf"), limit, every
            )
            return encoded
        end = until if until is not None else float("inf")
        recent = [entry for entry in ring if since < entry[0] <= end]
        if every > 1:
            recent = recent[::-1][::every][::-1]
        return await asyncio.to_thread(_encode_entries, recent[-limit:])

    def track(self, identity: str, mission_id: str | None = None) -> list[tuple[float, float]]:
        return [
            point
            for _, payload, mission in self.history.get(identity, ())
            if (mission_id is None or mission == mission_id) and (point := _position(payload)) is not None
        ]

    def track3d(self, identity: str, mission_id: str | None = None) -> list[tuple[float, float, float]]:
        """The flown (lat, lon, alt_rel) samples of ``identity`` (in ``mission_id``), oldest first."""
        return [
            point
            for _, payload, mission in self.history.get(identity, ())
            if (mission_id is None or mission == mission_id) and (point := _position3(payload)) is not None
        ]

    def subscribe(self, client: StreamClient) -> None:
        self.clients.add(client)
        if client.coverage:
            for text in self.coverage_latest.values():
                client.offer(text)
        self.metrics.ws_clients.set(len(self.clients))

    def unsubscribe(self, client: StreamClient) -> None:
        self.clients.discard(client)
        self.metrics.ws_clients.set(len(self.clients))


ENCODE_CHUNK = 500
"""Samples serialised per call: pydantic's Rust core keeps the GIL for a whole call, so a long
page is encoded in slices that each hold it for a few milliseconds (the event loop thread gets
its turn in between)."""


def _encode_entries(entries: list[Entry]) -> bytes:
    """Ring entries as a JSON array of :class:`StatusSample` (in a worker thread: the compact
    bodies are decoded here, off the event loop)."""
    samples = []
    for received, payload, _ in entries:
        try:
            samples.append(StatusSample(received=received, status=sample_report(payload)))
        except status_binary.StatusBodyError:  # the tick let it through: cannot happen; skipped
            continue
    return _encode_samples(samples)


def _encode_samples(samples: list[StatusSample]) -> bytes:
    parts = [
        _SAMPLES.dump_json(samples[i : i + ENCODE_CHUNK])[1:-1] for i in range(0, len(samples), ENCODE_CHUNK)
    ]
    return b"[" + b",".join(p for p in parts if p) + b"]"

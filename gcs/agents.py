"""Agent manager: TCP sessions, the authenticated handshake, CIDs, liveness, frame routing.

One protocol object per connection (:class:`_Connection`) and, for the handshake only, one
task; each session's outbound frames go through its outbox (gcs/outbox.py: a bounded queue
with an urgent lane, written by a task that runs only while there is work). The handshake reads
frames through the shared :class:`protocol.stream.FramedStream` and is
:class:`protocol.session.ServerHandshake` (versions negotiated, refusals with codes). A
connection must complete it within ``handshake_timeout_s`` with frames under 1 KiB, and at
most ``max_handshakes`` run at once, ``max_handshakes_per_source`` from one address
(:class:`PreAuthLimits`, which also rate-limits enrollment); until then no other packet is
accepted. Refusals that do not depend on the key are decided after the agent's proof, so
the session layer proves them to the agent (``refusal_proof``). Any protocol
error closes only that connection (type 6 ``protocol_error`` first), never the daemon or
other agents.

Nothing is awaited on the read path. After the handshake the connection's frames are handled
in its protocol's ``buffer_updated`` from the manager's one shared read buffer (no read task, no
allocation per read; a partial frame waits in the connection's decoder): a compact status
body (``compact_status``, negotiated by the session layer) is CRC- and rate-checked, its layout
checked whole (``status_binary.check_layout``: lengths, UTF-8, no stray bytes; a bad one closes
the session) and copied as it is into the agent's row of the fleet status table
(gcs/agents_table.py). The status tick (at most every ``STATUS_TICK_S``) checks the dirty rows'
fixed fields as NumPy columns (the schema's ranges and the plausibility bounds of
gcs/status_limits.py; a row that fails is looked at on its own) and hands the newest report of
each agent to the hook consumers (gcs/dispatch.py): as columns to
``on_status_tick`` (a ``StatusTick``, reports built on demand), the reports whose state changed
to ``on_status_changes``, and every report to ``on_status`` (built only if such hooks exist);
consumers run these and ``on_join`` / ``on_sync`` / ``on_lost`` in one task per hook owner. JSON
status, failsafe or failure reports, replayed status, ``finished`` and close are decoded and
handled at once, behind the agent's report still waiting for the tick, so each consumer sees
one agent's events in the order they arrived.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import ipaddress
import logging
import math
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gcs.agents_table import MAX_BODY, ROW_BYTES, StatusTable, StatusTick
from gcs.config import DaemonConfig
from gcs.dispatch import ConsumerStats, HookDispatcher, HookKind, HookList
from gcs.events import EventBus
from gcs.keys import KeyRing
from gcs.outbox import Outbox
from gcs.status_limits import ImplausibleStatus, StatusLimits, refusal
from gcs.store import CidExhausted, Store
from protocol.packets import (
    PROTOCOL_VERSION,
    AgentParameters,
    Body,
    Capabilities,
    Close,
    CloseReason,
    GeoPoint,
    PacketType,
    RequestCid,
    Resume,
    SetParameters,
    StatusReport,
    SyncSignal,
    packet_type_of,
)
from protocol.session import Code, Refused, ServerHandshake, close_for
from protocol.status_binary import ARMED, BUFFERED, HAS_TAIL, LANDED, StatusBodyError, check_layout
from protocol.stream import FramedStream
from protocol.wire import (
    COMPACT,
    PRE_AUTH_MAX_BODY,
    STATUS_COMPACT,
    Frame,
    FrameDecoder,
    ProtocolError,
    decode_body,
    encode,
)

log = logging.getLogger("gcs.agents")


STATUS_TICK_S = 0.01
"""Status reports reach the hooks in one batch per tick: the newest per agent since the last tick,
at most every 10 ms (sooner after a quiet spell: once the event loop has run what it had ready).
Failsafe, failure, replayed status, sync signals and closes are handed over at once."""
TICK_SLICE = 128
"""A tick's rows reach the tick hooks in slices of this many: a consumer yields between two
slices once its step budget is spent (gcs/dispatch.py), so a whole fleet's tick never holds the
loop for one service, and its loop time is counted without what ran in between."""
READ_BUFFER_BYTES = 256 << 10
"""Every served connection reads into the manager's one buffer of this size (asyncio's own read size)."""
HANDSHAKE_READ_LIMIT = 1 << 16  # a connection's StreamReader during the handshake (flow control)
BUSY_RETRY_S = 1.0
"""The wait a ``busy`` (handshake slots full) answer names: slots free up within a handshake."""
ENROLLMENT_SOURCES = 4096
"""Source addresses whose enrollment allowance is remembered; refilled ones are forgotten first."""
FREEZE_MIN_AGENTS = 200  # smaller fleets: full collections are short anyway (and tests run many daemons)
_SLOW_FLAGS = 0x80 | HAS_TAIL | BUFFERED  # a compact body with these is decoded at once (rare or bad)
REFUSAL_EVENT_S = 10.0
"""At most one ``status_refused`` event per agent this often (the first at once): an agent whose
every report is implausible must not fill the event log at its status rate."""


class ProbeAnswered(ConnectionError):
    """A probe (``agent doctor``) was authenticated and answered; the connection simply ends."""


class RateLimited(Exception):
    """An authenticated peer sent frames faster than its allowance."""


class RetireRefused(Exception):
    """Why an agent cannot leave the fleet list now: ``status`` 404 (not on it) or 409 (in use)."""

    def __init__(self, status: int, title: str, detail: str) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail


class TokenBucket:
    """``rate`` tokens per second, at most ``burst`` saved up; one token per frame."""

    __slots__ = ("burst", "rate", "stamp", "tokens")

    def __init__(self, rate: float, burst: int) -> None:
        self.rate, self.burst = rate, float(burst)
        self.tokens = float(burst)
        self.stamp = time.monotonic()

    def take(self, now: float) -> bool:
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def wait(self, now: float) -> float:
        """Seconds until the next token (0 if one is there)."""
        tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        return max(0.0, (1.0 - tokens) / self.rate)

    def refilled(self, now: float) -> bool:
        """Full again: nothing spent that still counts (the bucket can be forgotten)."""
        return self.tokens + (now - self.stamp) * self.rate >= self.burst


class PreAuthLimits:
    """What one source address may hold or do before it is known: handshake slots and enrollments.

    At most ``max_handshakes_per_source`` of the ``max_handshakes`` slots go to one source (an
    IPv6 /64), so one host holding silent connections cannot keep agents from other addresses
    out; its extra connections are answered ``busy`` with a short wait. New identities (a new
    CID) are limited to ``enroll_per_s`` per source with a burst of ``enroll_burst``.
    """

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.pending = 0  # handshakes in progress, every source
        self.busy_refusals = 0
        self._held: dict[str, int] = {}  # handshakes in progress per source
        self._enrollments: dict[str, TokenBucket] = {}  # enrollment allowance per source

    def take_slot(self, source: str) -> None:
        """A handshake slot for a connection from ``source``, or Refused ``busy``."""
        per_source = self.config.max_handshakes_per_source
        held = self._held.get(source, 0)
        if held >= per_source:
            self.busy_refusals += 1
            raise Refused(
                Code.BUSY, f"{per_source} handshakes in progress from {source}; retry later", BUSY_RETRY_S
            )
        if self.pending >= self.config.max_handshakes:
            self.busy_refusals += 1
            raise Refused(
                Code.BUSY, f"{self.config.max_handshakes} handshakes in progress; retry later", BUSY_RETRY_S
            )
        self.pending += 1
        self._held[source] = held + 1

    def release_slot(self, source: str) -> None:
        self.pending -= 1
        held = self._held.get(source, 0) - 1
        if held > 0:
            self._held[source] = held
        else:
            self._held.pop(source, None)

    def enroll(self, source: str) -> None:
        """One new identity from ``source`` within the enrollment rate, or Refused ``busy`` with the wait."""
        now = time.monotonic()
        bucket = self._enrollments.get(source)
        if bucket is None:
            if len(self._enrollments) >= ENROLLMENT_SOURCES:  # forget sources whose allowance refilled
                for key in [k for k, b in self._enrollments.items() if b.refilled(now)]:
                    del self._enrollments[key]
                if len(self._enrollments) >= ENROLLMENT_SOURCES:
                    self._enrollments.clear()
            bucket = self._enrollments[source] = TokenBucket(
                self.config.enroll_per_s, self.config.enroll_burst
            )
        if not bucket.take(now):
            self.busy_refusals += 1
            raise Refused(
                Code.BUSY,
                f"more than {self.config.enroll_per_s:g} new identities/s (burst {self.config.enroll_burst}) "
                f"enrolled from {source}; retry later",
                round(bucket.wait(now) + 0.05, 2),
            )


@dataclass(eq=False, slots=True)
class AgentSession:
    """One authenticated connection of one agent identity.

    Outbound frames go through the session's :class:`~gcs.outbox.Outbox` (its own bounded queue
    and a writer task while it has work), so a peer that does not read stalls only itself.
    """

    identity: str
    cid: int
    capabilities: Capabilities
    home: GeoPoint | None
    writer: asyncio.StreamWriter
    peer: str
    outbox: Outbox
    connected_at: float = field(default_factory=time.time)
    last_rx: float = field(default_factory=time.monotonic)
    _status: StatusReport | None = field(default=None, repr=False)  # as of the last status tick
    status_count: int = 0
    replayed_count: int = 0  # buffered status reports received (counted apart from live ones)
    open: bool = True
    version: int = PROTOCOL_VERSION
    exception_names: frozenset[str] = frozenset()
    exception_budget: TokenBucket | None = None
    exceptions_suppressed: int = 0
    compact_status: bool = False  # negotiated: status may come as the compact binary body
    refused_count: int = 0  # implausible status reports dropped (gcs/status_limits.py)
    refused_reported: int = 0  # of them, counted in a status_refused event already
    refused_event_at: float = -math.inf  # monotonic time of its last status_refused event
    release_beacon: bool = False  # v2 offer: the agent listens for release beacons (protocol/beacon.py)
    row: int = -1  # its row in the manager's status table while the session is served
    table: StatusTable | None = field(default=None, repr=False)

    @property
    def status(self) -> StatusReport | None:
        """The newest live status report: decoded on demand from the status table (the tick builds
        reports only for the hooks that want objects), cached until the next report."""
        table = self.table
        if table is not None and table.buf[self.row * ROW_BYTES + MAX_BODY]:
            with contextlib.suppress(StatusBodyError, ImplausibleStatus):  # the tick refuses it
                self._status = table.report(self.row)
        return self._status

    @status.setter
    def status(self, report: StatusReport | None) -> None:
        self._status = report

    @property
    def last_tx(self) -> float:
        """When a frame was last handed to the socket (monotonic)."""
        return self.outbox.last_tx

    def post(self, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue one packet without waiting; False if the session is closed or its queue overflowed.

        ``urgent=None`` picks the lane from the packet (:func:`gcs.outbox.is_urgent`).
        """
        if not self.open:
            return False
        return self.outbox.post(body, urgent)

    async def send(
        self,
        body: Body,
        timeout: float | None = None,
        max_pending: int | None = None,
        *,
        urgent: bool | None = None,
    ) -> bool:
        """Send one packet and wait until it is written and drained; False (session cut off) if not.

        ``timeout`` bounds the whole wait (queue included); ``max_pending`` is kept for callers
        of the old signature, the session's outbox has its own byte bound.
        """
        del max_pending
        if not self.open:
            return False
        return await self.outbox.send(body, urgent, timeout)

    async def close(
        self, reason: CloseReason, message: str, timeout: float = 1.0, *, code: Code | None = None
    ) -> None:
        """Tell the peer why (urgent, bounded wait), then close the transport."""
        if self.outbox.open:
            self.open = False  # no new frames from here on; the close itself still goes out
            code = code or _REASON_CODES.get(reason)
            body = Close(reason=reason, message=message[:500], code=code.value if code else None)
            await self.outbox.send(body, True, timeout)
        self.close_transport()

    def close_transport(self) -> None:
        self.open = False
        self.outbox.close()
        with contextlib.suppress(Exception):
            self.writer.close()


JoinHook = Callable[[AgentSession, Resume | None], Awaitable[None]]
StatusHook = Callable[[AgentSession, StatusReport], Awaitable[None]]
TickHook = Callable[[StatusTick], Awaitable[None]]
SyncHook = Callable[[AgentSession, SyncSignal], Awaitable[None]]
FinishedHook = Callable[[AgentSession, SyncSignal], bool]
LostHook = Callable[[str], Awaitable[None]]


class AgentManager:
    """Owns every agent connection; other services talk to agents only through it."""

    def __init__(self, config: DaemonConfig, store: Store, events: EventBus, keys: KeyRing) -> None:
        self.config = config
        self._store = store
        self._events = events
        self._keys = keys
        self.sessions: dict[str, AgentSession] = {}
        self.lost: set[str] = set()
        # Plain lists to the services that append/remove hooks; HookList only counts changes.
        self.on_join: HookList[JoinHook] = HookList()
        self.on_status: HookList[StatusHook] = HookList()  # every report (built for them: costs ~6 us each)
        self.on_status_changes: HookList[StatusHook] = HookList()  # reports whose state changed (STATE_BYTES)
        self.on_status_tick: HookList[TickHook] = HookList()  # each tick's reports as columns (StatusTick)
        self.on_sync: HookList[SyncHook] = HookList()
        # The barrier's direct path (gcs/missions.py): a 'finished' is handed to it from the frame's
        # buffer_updated, before the on_sync hooks get it, unless its owner's consumer still holds
        # a join, sync or lost of that agent (_finished).
        self.on_finished: FinishedHook | None = None
        self.on_lost: HookList[LostHook] = HookList()
        self._hooks = HookDispatcher(
            {
                "join": self.on_join,
                "status": self.on_status,
                "changes": self.on_status_changes,
                "tick": self.on_status_tick,
                "sync": self.on_sync,
                "lost": self.on_lost,
            }
        )
        self._tasks: set[asyncio.Task[None]] = set()  # handshakes and session ends under way
        self._serving = 0  # sessions whose frames are served (their end is still to come)
        self._read_buffer = memoryview(bytearray(READ_BUFFER_BYTES))  # every connection reads into it
        limits = StatusLimits(max_clock_skew_s=config.max_clock_skew_s)
        self.table = StatusTable(limits=limits)  # every served session's newest status (gcs/agents_table.py)
        self.status_tick_s = STATUS_TICK_S
        self._tick_due = False
        self._last_tick = 0.0
        self._frozen_at = 0  # fleet size at the last gc.freeze() (0: none by this manager)
        self.ingest_probe: Callable[[bytes], None] | None = None  # benchmarks: sees each table write
        self._hooks_closed = False
        self.pre_auth = PreAuthLimits(config)  # handshake slots and enrollments per source address
        self.ingest_frames = 0  # frames recorded by the frame loops
        self.ingest_busy_s = 0.0  # event-loop time recording them took (checks, record, publish)
        self.tick_count = 0
        self.tick_busy_s = 0.0  # event-loop time of the status ticks (decode dirty rows, publish)
        self.accepting = True  # False: handshakes are refused with code `starting`
        # Cluster mode (gcs/cluster): agents linked to other daemons, and the shared CID registry.
        self.remote: dict[str, AgentSession] = {}
        self.assign_cid: Callable[[str], Awaitable[int]] | None = None

    # --- queries --------------------------------------------------------------------------------

    def session(self, identity: str) -> AgentSession | None:
        session = self.sessions.get(identity)
        if session is not None and session.open:
            return session
        return self.remote.get(identity)  # linked to another daemon of the cluster (or None)

    def connected(self) -> list[AgentSession]:
        return [s for s in self.sessions.values() if s.open]

    def retire(self, identity: str, mission: str | None = None) -> AgentSession:
        """Take a disconnected agent off the fleet list (a ghost, a drone gone for good).

        ``mission`` is the mission it still flies, if any: then it stays. Its CID stays reserved in
        the store, so if it ever comes back it re-joins as before. Raises :class:`RetireRefused`.
        """
        session = self.sessions.get(identity)
        if session is None:
            raise RetireRefused(404, "no such agent", f"agent {identity!r} is not on the fleet list")
        if session.open:
            raise RetireRefused(409, "agent connected", f"{identity} is connected: stop its agent first")
        if mission is not None:
            raise RetireRefused(
                409, "agent in a mission", f"{identity} flies mission {mission}: abort it first"
            )
        del self.sessions[identity]
        self.lost.discard(identity)
        return session

    async def send(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue ``body`` for ``identity`` and wait until it is written and drained.

        True once the frame is on its way; False if the agent is not connected or was cut off
        (it overflowed its queue or did not drain within ``send_timeout_s``). ``urgent`` puts the
        frame ahead of queued mission traffic; ``None`` picks the lane from the packet.
        """
        session = self.session(identity)
        if session is None:
            return False
        return await session.send(body, urgent=urgent)

    def post(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue ``body`` for ``identity`` without waiting; False if it is not connected (or overflowed)."""
        session = self.session(identity)
        if session is None:
            return False
        return session.post(body, urgent=urgent)

    def burst(self, identities: list[str], body: Body) -> int:
        """Send ``body`` to every connected agent of ``identities`` in one pass; how many got it.

        Encoded once per protocol version; each agent's socket is written right away (behind
        what its outbox still holds), with no task switch per agent: a barrier release reaches
        1,000 agents in one go.
        """
        frames: dict[int, bytes] = {}
        ptype = packet_type_of(body)
        sent = 0
        now = time.monotonic()
        for identity in identities:
            session = self.session(identity)
            if session is None:
                continue
            if identity in self.remote:  # linked to another daemon of the cluster: forwarded there
                sent += session.post(body)
                continue
            frame = frames.get(session.version)
            if frame is None:
                frame = frames[session.version] = encode(body, 0, session.version)
            if session.outbox.write_now(frame, ptype, now):
                sent += 1
        return sent

    # --- connections ----------------------------------------------------------------------------

    def connection(self) -> _Connection:
        """The protocol factory of the agent listener (``loop.create_server``): one object per connection."""
        return _Connection(self)

    async def handle_connection(self, conn: _Connection) -> None:
        """The connection's one task, for its handshake only: once the session is served its frames
        are handled by the protocol (:class:`_Connection`) and this task ends."""
        writer = conn.writer
        peer = _peer_name(writer)
        reader = conn.reader
        assert reader is not None
        # Before the agent is known a frame is small: a handshake packet is well under 1 KiB.
        stream = FramedStream(reader, writer, max_body=PRE_AUTH_MAX_BODY, version=PROTOCOL_VERSION)
        handshake = ServerHandshake(self._keys.key_for)
        source = source_of(writer.get_extra_info("peername"))
        served = False
        try:
            self.pre_auth.take_slot(source)
            try:
                await asyncio.wait_for(
                    self._handshake(stream, handshake, conn, peer, source), self.config.handshake_timeout_s
                )
            finally:
                self.pre_auth.release_slot(source)
            served = True
            self._serve(conn, stream)
            return
        except Exception as exc:  # a bug must cost one connection, never the daemon
            if served:  # a frame that came right behind the proof ended it
                conn.finish(exc)
                return
            await self._refuse(stream, handshake, peer, exc, conn.session)
        finally:
            if not served:  # never served: a session created for it is dropped
                if conn.session is not None:
                    await self._disconnected(conn.session)
                with contextlib.suppress(Exception):
                    writer.close()

    async def _refuse(
        self,
        stream: FramedStream,
        handshake: ServerHandshake,
        peer: str,
        exc: BaseException,
        session: AgentSession | None,
    ) -> None:
        """A handshake that failed: the event, and the refusal sent to the peer (bounded)."""
        if isinstance(exc, TimeoutError):
            self._events.publish(
                "handshake_timeout", f"{peer} did not complete the handshake in time", severity="warning"
            )
            await stream.close(close_for(Code.HANDSHAKE_TIMEOUT, "handshake timeout"))
        elif isinstance(exc, Refused):
            busy = self.pre_auth.busy_refusals
            if exc.code != Code.BUSY or busy == 1 or busy % 100 == 0:
                self._events.publish("agent_refused", f"{peer}: {exc} ({exc.code})", severity="warning")
            known = {c.value for c in Code}
            code = Code(exc.code) if exc.code in known else Code.PROTOCOL_ERROR
            await stream.close(*handshake.refusal(code, str(exc), exc.retry_after_s))
        elif isinstance(exc, ProtocolError):
            who = session.identity if session else peer
            self._events.publish(
                "protocol_error",
                f"{who}: {exc}",
                severity="warning",
                agent=session.identity if session else None,
            )
            await stream.close(close_for(Code.PROTOCOL_ERROR, str(exc)))
        elif not isinstance(exc, (ConnectionError, OSError, asyncio.IncompleteReadError)):
            log.error("unexpected error on connection from %s", peer, exc_info=exc)

    async def _end(self, conn: _Connection, exc: BaseException | None) -> None:
        """A served session is over (``exc``: what ended it): tell the peer why, then clean up."""
        session = conn.session
        assert session is not None
        try:
            if isinstance(exc, RateLimited):
                self._events.publish("agent_cut_off", str(exc), severity="error", agent=session.identity)
                await session.close(CloseReason.PROTOCOL_ERROR, str(exc), code=Code.RATE_LIMITED)
            elif isinstance(exc, ProtocolError):
                self._events.publish(
                    "protocol_error", f"{session.identity}: {exc}", severity="warning", agent=session.identity
                )
                await session.close(CloseReason.PROTOCOL_ERROR, str(exc), code=Code.PROTOCOL_ERROR)
            elif exc is not None and not isinstance(
                exc, (ConnectionError, OSError, asyncio.IncompleteReadError)
            ):
                log.error("unexpected error on connection from %s", session.peer, exc_info=exc)
        finally:
            self._serving -= 1
            await self._disconnected(session)
            with contextlib.suppress(Exception):
                conn.writer.close()

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run ``coro`` as a task the manager waits for on shutdown (a session's end)."""
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _admit(self, request: RequestCid, writer: asyncio.StreamWriter) -> None:
        """Refusals that depend on the daemon, not on the key (Refused with a code)."""
        if not self.accepting:
            raise Refused(Code.STARTING, "the daemon is starting; retry later", 2.0)
        if request.identity in self.config.banned_agents:
            raise Refused(Code.BANNED, f"{request.identity!r} is banned by the operator")
        bound = certificate_identities(writer.get_extra_info("peercert"))
        if bound is not None and request.identity not in bound:
            raise Refused(
                Code.CERTIFICATE_MISMATCH,
                f"the client certificate is for {sorted(bound)}, not {request.identity!r}",
            )
        if (
            not request.probe
            and len(self.connected()) >= self.config.max_agents
            and request.identity not in self.sessions
        ):
            raise Refused(Code.FLEET_FULL, f"fleet full: {self.config.max_agents} agents connected", 30.0)

    def _allocate_cid(self, request: RequestCid) -> int:
        known = self._store.cid_of(request.identity)
        if known is None and not self.config.enroll_new_agents:
            raise Refused(
                Code.ENROLLMENT_CLOSED,
                f"{request.identity!r} is not enrolled and enrollment of new agents is off",
            )
        try:
            return self._store.cid_for(request.identity, request.capabilities.model_dump())
        except CidExhausted as exc:
            raise Refused(Code.CID_EXHAUSTED, str(exc), 300.0) from None

    async def _handshake(
        self, stream: FramedStream, handshake: ServerHandshake, conn: _Connection, peer: str, source: str
    ) -> AgentSession:
        hello = (await stream.read_frame()).body
        challenge = handshake.on_hello(hello)
        stream.version = handshake.version
        await stream.send(challenge)
        authenticated = handshake.on_proof((await stream.read_frame()).body)
        request = authenticated.request
        # Decided only now, once the agent proved its key, so the refusal can be proved in turn
        # (refusal_proof): the agent stops for good only on a refusal it can check.
        self._admit(request, stream.writer)
        if authenticated.probe:  # authenticated only: no CID, no session, never a member
            answer = handshake.accept(None, self._parameters(), time.time())
            await stream.send(answer, close_for(Code.NORMAL, "probe answered"))
            self._events.publish("agent_probe", f"{request.identity} probed from {peer}")
            raise ProbeAnswered(request.identity)
        if not request.probe and self._store.cid_of(request.identity) is None:  # known ones are not counted
            self.pre_auth.enroll(source)
        if self.assign_cid is not None:  # cluster mode: the shared registry assigns CIDs once
            await self.assign_cid(request.identity)
        cid = self._allocate_cid(request)
        stream.decoder.max_body = self.config.max_body_bytes  # authenticated: mission-sized frames
        outbox = Outbox(
            stream.writer,
            request.identity,
            self.config.send_timeout_s,
            self.config.max_pending_bytes,
            first_seq=stream.seq,
            version=stream.version,
            on_cut_off=self._cut_off,
        )
        session = AgentSession(
            identity=request.identity,
            cid=cid,
            capabilities=request.capabilities,
            home=request.home,
            writer=stream.writer,
            peer=peer,
            outbox=outbox,
            version=stream.version,
            compact_status=handshake.compact_status,
            release_beacon=stream.version >= 2 and request.release_beacon is True,
        )
        conn.session = session
        was_lost = request.identity in self.lost
        accepted = handshake.accept(cid, self._parameters(), time.time(), lost=was_lost)
        previous = self.sessions.get(request.identity)
        if previous is not None and previous.open:
            await previous.close(
                CloseReason.REPLACED, f"replaced by a new session from {peer}", code=Code.REPLACED
            )
            self._events.publish(
                "agent_replaced", f"session from {previous.peer} replaced by {peer}", agent=request.identity
            )
        self.sessions[request.identity] = session
        if not await session.send(accepted, self.config.send_timeout_s):
            raise ConnectionError("agent left during the handshake")
        self.lost.discard(request.identity)
        self._events.publish(
            "agent_joined",
            f"cid {cid} from {peer}, protocol v{stream.version}"
            + (" (back after being lost)" if was_lost else ""),
            agent=request.identity,
            data={
                "cid": cid,
                "version": stream.version,
                "resume": request.resume.model_dump() if request.resume else None,
            },
        )
        # Join hooks run in their services' consumers, outside this handshake's time budget.
        self._publish("join", session.identity, session, request.resume)
        return session

    def _parameters(self) -> AgentParameters:
        return self.config.agent_parameters.model_copy(
            update={"status_period_s": self.config.status_period_s}
        )

    def _serve(self, conn: _Connection, stream: FramedStream) -> None:
        """Serve the session's frames from now on in the protocol's ``buffer_updated`` (:meth:`_ingest`):
        no task and no stream objects per connection. Frames that came right behind the proof come
        first; raises what ends the session among them (protocol error, rate limit)."""
        session = conn.session
        assert session is not None and conn.reader is not None
        reader, conn.reader = conn.reader, None  # from here on the protocol ingests what arrives
        conn.decoder = stream.decoder
        session.row = self.table.attach(conn)
        session.table = self.table
        self._serving += 1
        while stream.backlog:
            frame = stream.backlog.popleft()
            self._take(conn, frame, time.monotonic())
            self._handle(session, frame)
            if not session.open:
                conn.finish()
                return
        buffered: bytearray = reader._buffer  # type: ignore[attr-defined]  # read after the proof
        if buffered:
            leftover = bytes(buffered)
            buffered.clear()
            conn.ingest(leftover)
        transport = conn.transport
        if reader.at_eof() or reader.exception() is not None or transport.is_closing():
            conn.finish()
        elif not transport.is_reading():  # the reader paused it (a backlog of pipelined frames)
            transport.resume_reading()

    def _take(self, conn: _Connection, frame: Frame, now: float) -> None:
        """The rate limit of a decoded frame (live frames and replayed status have separate budgets).

        Live frames and replayed (``buffered``) status reports are counted in separate buckets,
        so an agent catching up after an outage is not cut off for it (docs/protocol.md).
        """
        session = conn.session
        assert session is not None  # only served connections get here
        session.last_rx = now  # complete packets count as life, stray bytes do not
        replayed = isinstance(frame.body, StatusReport) and frame.body.buffered
        bucket = conn.live
        if replayed:
            if conn.replay is None:  # only an agent that replays status needs this budget (full at first)
                conn.replay = TokenBucket(self.config.replay_frames_per_s, self.config.replay_burst)
            bucket = conn.replay
        if not bucket.take(now):
            raise self._over_budget(replayed)

    def _over_budget(self, replayed: bool) -> RateLimited:
        """The refusal of a frame over its budget (live frames, or replayed status reports)."""
        kind = "replayed status reports" if replayed else "frames"
        rate, burst = (
            (self.config.replay_frames_per_s, self.config.replay_burst)
            if replayed
            else (self.config.max_frames_per_s, self.config.frame_burst)
        )
        return RateLimited(f"more than {rate:g} {kind}/s (burst {burst}); cut off")

    def _ingest(self, conn: _Connection, data: bytes | memoryview) -> bool:
        """Every frame ``data`` completes; False once the session is over.

        The hot path: a compact status body without tail (not replayed) is copied into the
        session's table row as it is, nothing decoded. Anything else is decoded and handled
        (:meth:`_handle`) at once, behind the reports already received.
        """
        started = time.perf_counter()
        session, table, frames = conn.session, self.table, 0
        assert session is not None  # only served connections get here
        probe = self.ingest_probe
        try:
            for ptype, seq, payload in conn.decoder.split(data):
                frames += 1
                now = time.monotonic()
                size = len(payload)
                if (
                    ptype == STATUS_COMPACT
                    and size <= MAX_BODY
                    and size > 1
                    and not payload[1] & _SLOW_FLAGS
                    and session.compact_status
                ):
                    session.last_rx = now
                    if not conn.live.take(now):
                        raise self._over_budget(replayed=False)
                    try:  # the whole variable part, before a byte reaches the table (fixed: the tick)
                        check_layout(payload)
                    except StatusBodyError as exc:
                        raise conn.decoder.fail(ProtocolError(str(exc), packet_type=ptype)) from None
                    row = session.row
                    start = row * ROW_BYTES
                    buf = table.buf
                    buf[start : start + size] = payload
                    buf[start + MAX_BODY] = size
                    table.objects[row] = None
                    table.dirty[row] = 1
                    table.rx[row] = time.time()
                    session.status_count += 1
                    if not self._tick_due:
                        self._schedule_tick(now)
                    if probe is not None:
                        probe(payload)
                    continue
                try:
                    body = decode_body(ptype, payload)
                except ProtocolError as exc:
                    raise conn.decoder.fail(exc) from None
                frame = Frame(PacketType(ptype & ~COMPACT), seq, body, ptype == STATUS_COMPACT)
                self._take(conn, frame, now)
                self._handle(session, frame)
                if not session.open:
                    return False
            return True
        finally:
            self.ingest_frames += frames
            self.ingest_busy_s += time.perf_counter() - started

    def _handle(self, session: AgentSession, frame: Frame) -> None:
        """Record what a decoded frame says and hand it to the hook consumers; nothing is awaited here."""
        body = frame.body
        if isinstance(body, StatusReport):
            if frame.compact and not session.compact_status:
                raise ProtocolError("compact status body (type 0x82) sent without negotiating it")
            reason = refusal(body, time.time(), self.table.limits, replayed=body.buffered)
            if reason is not None:
                session.status_count += 1
                self._refused(session, reason)
                return
            self._exception_events(session, body)
            session.status_count += 1
            if body.buffered:  # history: it never overwrites the newer live state; in order, at once
                session.replayed_count += 1
                self._flush_row(session)
                self._hand_over([(session, body)])
                return
            urgent = body.failsafe is not None or body.failure is not None
            if urgent:  # safety news goes to the hooks now, behind the report still waiting for the tick
                self._flush_row(session)
            self.table.put_report(session.row, body, time.time())
            if urgent:
                self._flush_row(session)
            elif not self._tick_due:
                self._schedule_tick(time.monotonic())
        elif isinstance(body, SyncSignal):
            if body.kind != "finished":
                raise ProtocolError("agents may only send 'finished' sync signals")
            self._finished(session, body)
        elif isinstance(body, Close):
            self._events.publish(
                "agent_closed",
                f"agent closed its session: {body.reason.value} {body.message}",
                agent=session.identity,
            )
            session.close_transport()
        else:
            raise ProtocolError(
                f"type {frame.packet_type.value} ({frame.packet_type.name}) "
                "is not valid from an agent after the handshake"
            )

    def _finished(self, session: AgentSession, signal: SyncSignal) -> None:
        """A 'finished' sync signal: to the barrier at once, then to every ``on_sync`` hook.

        The last arrival of a barrier releases it from here, in this ``buffer_updated`` call (no
        hook queue and no task switch in between): ``on_finished`` records the arrival and, when
        it completes the barrier, persists and bursts the release. Not while the consumer of its
        owner still holds a join or lost of the agent (``on_finished`` itself declines while the
        agent's newest report carries a failsafe or a failure): then the owner's ``on_sync`` hook
        takes the arrival, in order. A plain status report still waiting for the tick (flushed
        below, for the other hooks) says nothing the barrier depends on.
        """
        direct = self.on_finished
        if (
            direct is not None
            and not self._hooks_closed
            and not self._hooks.queued_for(direct, session.identity)
        ):
            try:
                direct(session, signal)
            except Exception:  # a bug costs this arrival (as a failing hook would), not the session
                log.exception("barrier arrival of %s failed", session.identity)
        self._publish("sync", session.identity, session, signal)

    # --- the status tick ------------------------------------------------------------------------

    def _schedule_tick(self, now: float) -> None:
        """The first report since the last tick: the next tick runs ``status_tick_s`` after the last
        one, or when the event loop has run the callbacks it has ready if that was longer ago."""
        self._tick_due = True
        loop = asyncio.get_running_loop()
        delay = self._last_tick + self.status_tick_s - now
        if delay > 0:
            loop.call_later(delay, self._run_tick)
        else:
            loop.call_soon(self._run_tick)

    def _run_tick(self) -> None:
        self._tick_due = False
        self._last_tick = time.monotonic()
        try:
            self.tick()
        except Exception:  # a bug must cost one tick, never the status flow
            log.exception("status tick failed")

    def tick(self) -> int:
        """Hand the newest report of every agent that sent one since the last tick to the status
        hooks, as one batch; how many. Rows are screened first (:meth:`_screen`): a body that breaks
        the protocol's ranges ends its session, an implausible report is dropped, the rest go on.
        """
        started = time.perf_counter()
        table = self.table
        rows = table.take_dirty()
        if not len(rows):
            return 0
        cols = table.columns(rows)
        changed = table.changed(rows)
        keep, sessions, reports = self._screen(rows, cols)
        if len(keep) != len(rows):  # (whole rows: cols[keep] would drop mode and mission)
            cols, changed, rows = table.pick(cols, keep), changed[keep], rows[keep]
        # On the ground and disarmed the authority drops automatic holds with every report, as
        # before (a hold placed on a landed drone ends at its next report, not at a change).
        changed |= (cols["flags"] & (LANDED | ARMED)) == LANDED
        tick = StatusTick(sessions, cols, table.arrivals(rows), reports)
        if sessions and not self._hooks_closed:
            hooks = self._hooks
            decoded = np.fromiter((r is not None for r in reports), dtype=bool, count=len(reports))
            if hooks.has("status"):  # every report as an object: built here (the API's and extensions' view)
                hooks.publish_batch([(s, tick.report(i)) for i, s in enumerate(sessions)])
            if hooks.has("changes"):  # a changed state (or a report that came decoded) only
                moved = np.flatnonzero(changed | decoded).tolist()  # (decoded: before building any here)
                hooks.publish_batch([(sessions[i], tick.report(i)) for i in moved], "changes")
            for start in range(0, len(sessions), TICK_SLICE):  # the consumers yield between slices
                hooks.publish_tick(
                    tick.slice(start, start + TICK_SLICE), min(TICK_SLICE, len(sessions) - start)
                )
        self._freeze_fleet_heap(len(table))
        self.tick_count += 1
        self.tick_busy_s += time.perf_counter() - started
        return len(sessions)

    def _screen(
        self, rows: np.ndarray[Any, np.dtype[np.intp]], cols: np.ndarray[Any, Any]
    ) -> tuple[list[int], list[AgentSession], list[StatusReport | None]]:
        """Which of a tick's ``rows`` go to the hooks: their indexes, sessions and reports (None:
        built on demand from the columns).

        Every row is checked at once on the columns (the schema's ranges, ``StatusTable.check``,
        and the plausibility bounds, gcs/status_limits.py); only a row that fails is looked at on
        its own (the reference decoder and :func:`~gcs.status_limits.refusal` name what is wrong),
        so one bad row costs only itself: a body out of the protocol's ranges closes that session
        (``protocol_error``), an implausible report is dropped with a ``status_refused`` event.
        """
        table = self.table
        ok = table.check(cols) & table.plausible(cols, rows)
        owners, objects = table.owners, table.objects
        keep: list[int] = []
        sessions: list[AgentSession] = []
        reports: list[StatusReport | None] = []
        for i, (row, passed) in enumerate(zip(rows.tolist(), ok.tolist(), strict=True)):
            conn = owners[row]
            if conn is None:
                continue
            report = objects[row]  # came decoded and checked (JSON), or an API call decoded it already
            if not passed and report is None:
                try:  # the reference decoder and the plausibility bounds name what is wrong
                    report = table.report(row)
                except StatusBodyError as exc:
                    conn.finish(ProtocolError(str(exc), packet_type=PacketType.STATUS))
                    continue
                except ImplausibleStatus as exc:
                    table.unsee(row)  # its next accepted report counts as a change
                    self._refused(conn.session, str(exc))
                    continue
            keep.append(i)
            sessions.append(conn.session)
            reports.append(report)
        return keep, sessions, reports

    def _refused(self, session: AgentSession, reason: str) -> None:
        """An implausible status report of ``session`` was dropped: counted, and a ``status_refused``
        event (warning) naming the agent and the reason, at most one per :data:`REFUSAL_EVENT_S`."""
        session.refused_count += 1
        now = time.monotonic()
        if now - session.refused_event_at < REFUSAL_EVENT_S:
            return
        since = session.refused_count - session.refused_reported
        session.refused_event_at, session.refused_reported = now, session.refused_count
        more = f" ({since} refused since the last such event)" if since > 1 else ""
        self._events.publish(
            "status_refused",
            f"status report refused: {reason}{more}",
            severity="warning",
            agent=session.identity,
            data={"refused": session.refused_count},
        )

    def _freeze_fleet_heap(self, agents: int) -> None:
        """Keep the per-agent state of a large fleet out of the full garbage collections.

        A full collection scans every tracked object; with thousands of agents that took 50-170
        ms of event loop (docs/performance.md). When the fleet has grown by a quarter (from
        ``FREEZE_MIN_AGENTS`` agents on), what is alive is frozen (``gc.freeze``): per-report
        garbage is still freed by reference counting and by the young generations. When it has
        shrunk by a quarter the heap is unfrozen, so the state of agents that left is collected.
        """
        if agents < FREEZE_MIN_AGENTS and not self._frozen_at:
            return
        if agents >= max(FREEZE_MIN_AGENTS, self._frozen_at * 1.25):
            gc.freeze()
            self._frozen_at = agents
        elif agents < self._frozen_at * 0.75:
            gc.unfreeze()
            self._frozen_at = agents if agents >= FREEZE_MIN_AGENTS else 0

    def _flush_row(self, session: AgentSession) -> None:
        """Hand the session's report waiting for the tick to the hooks now (before a rarer event)."""
        table = session.table
        if table is None or not table.dirty[session.row]:
            return
        table.clean(session.row)
        table.unsee(session.row)
        try:
            report = table.report(session.row)
        except StatusBodyError as exc:
            raise ProtocolError(str(exc), packet_type=PacketType.STATUS) from None
        except ImplausibleStatus as exc:
            self._refused(session, str(exc))
            return
        session._status = report
        self._hand_over([(session, report)])

    def _hand_over(self, pairs: list[tuple[AgentSession, StatusReport]]) -> None:
        """Reports handed over outside the tick (rare packets): to every kind of status hook."""
        if not self._hooks_closed:
            self._hooks.publish_batch(pairs)
            self._hooks.publish_batch(pairs, "changes")
            if self._hooks.has("tick"):
                self._hooks.publish_tick(StatusTick.of_reports(pairs, time.time()), len(pairs))

    def _publish(self, kind: HookKind, agent: str, *args: object) -> None:
        """Publish a non-status event behind the agent's report still waiting for the tick."""
        session = self.sessions.get(agent)
        if session is not None:
            with contextlib.suppress(ProtocolError):
                self._flush_row(session)
        if not self._hooks_closed:
            self._hooks.publish(kind, agent, *args)

    def _exception_events(self, session: AgentSession, status: StatusReport) -> None:
        """Turn exceptions that appear in a status report into events (once each, bounded).

        At most ``max_exception_events`` per agent per minute are published; beyond that they
        are counted, with one warning per suppressed run, so an agent cycling through new names
        cannot fill the database.
        """
        if not status.exceptions and not session.exception_names:
            return  # the common case: nothing raised before or now
        before = session.exception_names
        names = frozenset(e.split(":", 1)[0] for e in status.exceptions)
        session.exception_names = names
        if session.exception_budget is None:
            cap = self.config.max_exception_events
            session.exception_budget = TokenBucket(cap / 60.0, cap)
        now = time.monotonic()
        for text in status.exceptions:
            name = text.split(":", 1)[0]
            if name in before:
                continue
            if not session.exception_budget.take(now):
                session.exceptions_suppressed += 1
                if session.exceptions_suppressed == 1 or session.exceptions_suppressed % 1000 == 0:
                    self._events.publish(
                        "agent_exceptions_suppressed",
                        f"more than {self.config.max_exception_events} new exceptions a minute; "
                        f"{session.exceptions_suppressed} not logged",
                        severity="warning",
                        agent=session.identity,
                    )
                continue
            if name not in before:
                self._events.publish(
                    "agent_exception",
                    text,
                    severity="warning",
                    agent=session.identity,
                    data={"exception": name},
                )

    def _cut_off(self, outbox: Outbox, reason: str) -> None:
        """A session's outbox gave up on the peer (overflow or no drain): the session ends."""
        session = self.sessions.get(outbox.identity)
        if session is None or session.outbox is not outbox or not session.open:
            return
        session.open = False
        self._events.publish("agent_cut_off", f"{reason}; cut off", severity="error", agent=session.identity)

    async def _disconnected(self, session: AgentSession) -> None:
        session.close_transport()
        if session.table is not None:  # its last report still goes to the hooks, then the row is free
            with contextlib.suppress(ProtocolError):
                self._flush_row(session)
            _ = session.status  # kept as the session's last word once its row is free
            session.table.release(session.row)
            session.table = None
        if self.sessions.get(session.identity) is session:
            self._events.publish(
                "agent_disconnected", f"connection from {session.peer} ended", agent=session.identity
            )

    # --- liveness -------------------------------------------------------------------------------

    async def watch_liveness(self) -> None:
        """Mark agents lost when silent (or gone) for longer than ``lost_after_s``; runs until cancelled."""
        period = max(0.05, min(self.config.status_period_s, self.config.keepalive_s) / 2)
        keepalive = SetParameters()  # an empty type 3 changes nothing: it only proves we are here
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            due = [
                s.identity
                for s in self.connected()
                if s.outbox.idle and now - s.last_tx >= self.config.keepalive_s
            ]
            if due:  # encoded once, written in one pass: a stuck peer never delays this loop
                # At most about twice a pass's fair share, so a fleet that joined at once does
                # not get all its keepalives in the same pass every second (one long stall).
                share = 2 * len(self.sessions) * period / self.config.keepalive_s
                self.burst(due[: max(64, int(share))], keepalive)
            for identity, session in list(self.sessions.items()):
                if identity in self.lost or now - session.last_rx <= self.config.lost_after_s:
                    continue
                self.lost.add(identity)
                session.close_transport()
                self._events.publish(
                    "agent_lost",
                    f"no packet for {now - session.last_rx:.1f} s (limit {self.config.lost_after_s:.1f} s)",
                    severity="warning",
                    agent=identity,
                )
                self._publish("lost", identity, identity)
            await self._hooks.prune()

    async def close_all(self, reason: CloseReason, message: str) -> None:
        sessions = self.connected()
        await asyncio.gather(*(s.close(reason, message) for s in sessions))
        deadline = time.monotonic() + 2.0  # closed transports end every session; a moment to clean up
        while (self._tasks or self._serving) and time.monotonic() < deadline:
            if self._tasks:
                await asyncio.wait(list(self._tasks), timeout=max(0.0, deadline - time.monotonic()))
            else:  # a transport's connection_lost (which ends its session) is still to come
                await asyncio.sleep(0.01)
        self._hooks_closed = True  # a tick still scheduled must not start new consumers
        await self._hooks.close()

    # --- hook consumers -------------------------------------------------------------------------

    async def drain_hooks(self, timeout: float = 10.0) -> bool:
        """Wait until every hook consumer has handled everything queued; False after ``timeout``.

        For tests and services that need "everything received so far has been seen by the hooks".
        """
        self.tick()
        return await self._hooks.drain(timeout)

    def hook_stats(self) -> list[ConsumerStats]:
        """Per consumer: queued, delivered, coalesced, dropped, overflow, failed (for metrics)."""
        return self._hooks.stats()


class _Connection(asyncio.BufferedProtocol):
    """One agent connection from accept to close: the only object per connection besides the session.

    During the handshake the bytes feed a ``StreamReader`` that the connection's one task reads
    through :class:`~protocol.stream.FramedStream`. Once the session is served
    (:meth:`AgentManager._serve`) that task and the reader are gone: every read lands in the
    manager's one shared buffer (``get_buffer``) and ``buffer_updated`` hands it to
    :meth:`AgentManager._ingest`, which consumes it at once (a partial frame stays in the
    connection's decoder), so no read allocates. Writes go through a ``StreamWriter`` whose flow
    control is this object's (``pause_writing``/``resume_writing``/``_drain_helper``), which is what
    the session's outbox drains on. A session's end runs in a task started only then (:meth:`finish`).
    """

    __slots__ = (
        "_drain_waiters",
        "_manager",
        "_paused",
        "decoder",
        "ended",
        "live",
        "lost",
        "reader",
        "replay",
        "session",
        "transport",
        "writer",
    )

    def __init__(self, manager: AgentManager) -> None:
        config = manager.config
        self._manager = manager
        self.session: AgentSession | None = None  # set once the peer is authenticated
        self.reader: asyncio.StreamReader | None = None  # the handshake's bytes (None once served)
        self.decoder: FrameDecoder  # the handshake stream's, once served
        self.live = TokenBucket(config.max_frames_per_s, config.frame_burst)
        self.replay: TokenBucket | None = None  # replayed status reports' budget (made on first use)
        self.ended = False
        self.lost = False
        self._paused = False
        self._drain_waiters: list[asyncio.Future[None]] | None = None

    # --- asyncio protocol: the connection -------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        loop = asyncio.get_running_loop()
        self.transport = transport
        self.reader = asyncio.StreamReader(limit=HANDSHAKE_READ_LIMIT, loop=loop)
        self.reader.set_transport(transport)
        self.writer = asyncio.StreamWriter(transport, self, None, loop)
        self._manager._spawn(self._manager.handle_connection(self))

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._manager._read_buffer

    def buffer_updated(self, nbytes: int) -> None:
        data = self._manager._read_buffer[:nbytes]
        if self.reader is not None:  # the handshake: its task reads the bytes (copied)
            self.reader.feed_data(data)
        else:
            self.ingest(data)

    def ingest(self, data: bytes | memoryview) -> None:
        """Handle the frames ``data`` completes, synchronously (``data`` may be the shared buffer)."""
        if self.ended:
            return
        try:
            if not self._manager._ingest(self, data):
                self.finish()
        except Exception as exc:  # ends this session only (AgentManager._end deals with it)
            self.finish(exc)

    def finish(self, exc: BaseException | None = None) -> None:
        """The served session is over (``exc``: why); its end runs in a task of its own, once."""
        if self.ended or self.reader is not None:  # not served yet: the handshake task ends it
            return
        self.ended = True
        self._manager._spawn(self._manager._end(self, exc))

    def eof_received(self) -> bool:
        if self.reader is not None:  # as asyncio's stream protocol: half-closed, a refusal still goes out
            self.reader.feed_eof()
            return self.transport.get_extra_info("sslcontext") is None  # (TLS cannot half-close)
        self.finish()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost = True
        self._wake_drainers()
        if self.reader is None:
            self.finish()
        elif exc is None:
            self.reader.feed_eof()
        else:
            self.reader.set_exception(exc)

    # --- write flow control (what StreamWriter.drain() waits on) --------------------------------

    def pause_writing(self) -> None:
        self._paused = True

    def resume_writing(self) -> None:
        self._paused = False
        self._wake_drainers()

    def _wake_drainers(self) -> None:
        waiters, self._drain_waiters = self._drain_waiters, None
        for waiter in waiters or ():
            if not waiter.done():
                waiter.set_result(None)

    async def _drain_helper(self) -> None:
        """Return once the transport takes more (``StreamWriter.drain``); raises once it is lost."""
        if self.lost:
            raise ConnectionResetError("Connection lost")
        if not self._paused:
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        if self._drain_waiters is None:
            self._drain_waiters = []
        self._drain_waiters.append(waiter)
        await waiter
        if self.lost:
            raise ConnectionResetError("Connection lost")


_REASON_CODES = {
    CloseReason.NORMAL: Code.NORMAL,
    CloseReason.REPLACED: Code.REPLACED,
    CloseReason.SHUTDOWN: Code.SHUTDOWN,
    CloseReason.PROTOCOL_ERROR: Code.PROTOCOL_ERROR,
}


def certificate_identities(peercert: object) -> set[str] | None:
    """The names a verified client certificate carries (subject CN, DNS SANs); None without one.

    With mutual TLS an agent may only present an identity its certificate names, so a
    certificate issued for one drone cannot log in as another.
    """
    if not isinstance(peercert, dict) or not peercert:
        return None
    names: set[str] = set()
    for rdn in peercert.get("subject", ()):
        for key, value in rdn:
            if key == "commonName":
                names.add(str(value))
    for kind, value in peercert.get("subjectAltName", ()):
        if kind == "DNS":
            names.add(str(value))
    return names


def source_of(peername: object) -> str:
    """The source a connection counts against: its IPv4 address, or the /64 of an IPv6 address.

    One host of an IPv6 network usually holds a whole /64, so per-address limits would not bind.
    """
    if not isinstance(peername, tuple) or not peername:
        return str(peername)
    try:
        address = ipaddress.ip_address(str(peername[0]).split("%", 1)[0])
    except ValueError:
        return str(peername[0])
    if isinstance(address, ipaddress.IPv6Address):
        if address.ipv4_mapped is not None:
            return str(address.ipv4_mapped)
        return str(ipaddress.IPv6Network((address, 64), strict=False))
    return str(address)


def _peer_name(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    if isinstance(peer, tuple) and len(peer) >= 2:
        return f"{peer[0]}:{peer[1]}"
    return str(peer)


__all__ = ["AgentManager", "AgentSession", "PacketType", "certificate_identities", "source_of"]

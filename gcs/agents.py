"""Agent manager: TCP sessions, the authenticated handshake, CIDs, liveness, frame routing.

One read task per connection and one writer task per session (gcs/outbox.py: a bounded
outbound queue with an urgent lane). A connection must complete the type-0/1 handshake within
``handshake_timeout_s``; until then no other packet is accepted. Any protocol error closes
only that connection (type 6 ``protocol_error`` first), never the daemon or other agents.

Nothing is awaited on the read path: the frame loop decodes, records (``session.status``...)
and publishes to the hook consumers (gcs/dispatch.py), which run ``on_join`` / ``on_status`` /
``on_sync`` / ``on_lost`` hooks in one task per hook owner, outside the handshake budget.
Status reports are handed over in one batch per event-loop iteration (everything every frame
loop received in it); any other event first flushes the batch, so each consumer still sees one
agent's events in the order they arrived.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from gcs.config import DaemonConfig
from gcs.dispatch import ConsumerStats, HookDispatcher, HookKind
from gcs.events import EventBus
from gcs.keys import KeyRing
from gcs.outbox import Outbox
from gcs.store import Store
from protocol import auth
from protocol.packets import (
    PROTOCOL_VERSION,
    Body,
    Capabilities,
    Close,
    CloseReason,
    GeoPoint,
    PacketType,
    RequestCid,
    ResponseCid,
    Resume,
    SetParameters,
    StatusReport,
    SyncSignal,
    packet_type_of,
)
from protocol.wire import Frame, FrameDecoder, ProtocolError, encode

log = logging.getLogger("gcs.agents")

READ_CHUNK = 65_536


class HandshakeRefused(Exception):
    """The peer failed the handshake; the message goes back to it in the refusal."""


class ProbeAnswered(ConnectionError):
    """A probe (``agent doctor``) was authenticated and answered; the connection simply ends."""


class RateLimited(Exception):
    """An authenticated peer sent frames faster than its allowance."""


class TokenBucket:
    """``rate`` tokens per second, at most ``burst`` saved up; one token per frame."""

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


@dataclass(eq=False)
class AgentSession:
    """One authenticated connection of one agent identity.

    Outbound frames go through the session's :class:`~gcs.outbox.Outbox` (its own bounded queue
    and writer task), so a peer that does not read stalls only itself.
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
    status: StatusReport | None = None
    status_count: int = 0
    open: bool = True
    compact_status: bool = False  # negotiated: status may come as the compact binary body

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

    async def close(self, reason: CloseReason, message: str, timeout: float = 1.0) -> None:
        """Tell the peer why (urgent, bounded wait), then close the transport."""
        if self.outbox.open:
            self.open = False  # no new frames from here on; the close itself still goes out
            await self.outbox.send(Close(reason=reason, message=message[:500]), True, timeout)
        self.close_transport()

    def close_transport(self) -> None:
        self.open = False
        self.outbox.close()
        with contextlib.suppress(Exception):
            self.writer.close()


JoinHook = Callable[[AgentSession, Resume | None], Awaitable[None]]
StatusHook = Callable[[AgentSession, StatusReport], Awaitable[None]]
SyncHook = Callable[[AgentSession, SyncSignal], Awaitable[None]]
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
        self.on_join: list[JoinHook] = []
        self.on_status: list[StatusHook] = []
        self.on_sync: list[SyncHook] = []
        self.on_lost: list[LostHook] = []
        self._hooks = HookDispatcher(
            {"join": self.on_join, "status": self.on_status, "sync": self.on_sync, "lost": self.on_lost}
        )
        self._tasks: set[asyncio.Task[None]] = set()
        self._status_batch: list[tuple[AgentSession, StatusReport]] = []
        self._flush_scheduled = False
        self._hooks_closed = False
        self._pending_handshakes = 0
        self.ingest_frames = 0  # frames decoded and recorded by the frame loops
        self.ingest_busy_s = 0.0  # event-loop time they took (decode, checks, record, publish)

    # --- queries --------------------------------------------------------------------------------

    def session(self, identity: str) -> AgentSession | None:
        session = self.sessions.get(identity)
        return session if session is not None and session.open else None

    def connected(self) -> list[AgentSession]:
        return [s for s in self.sessions.values() if s.open]

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

        Encoded once; each agent's socket is written right away (behind what its outbox still
        holds), with no task switch per agent: a barrier release reaches 1,000 agents in one go.
        """
        frame = encode(body, 0)
        ptype = packet_type_of(body)
        sent = 0
        for identity in identities:
            session = self.session(identity)
            if session is not None and session.outbox.write_now(frame, ptype):
                sent += 1
        return sent

    # --- connections ----------------------------------------------------------------------------

    async def handle_connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """asyncio.start_server callback: handshake, then the frame loop, then cleanup."""
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        peer = _peer_name(writer)
        decoder = FrameDecoder(self.config.max_body_bytes)
        session: AgentSession | None = None
        try:
            session = await asyncio.wait_for(
                self._handshake(reader, writer, decoder, peer), self.config.handshake_timeout_s
            )
            await self._frame_loop(session, reader, decoder)
        except TimeoutError:
            self._events.publish(
                "handshake_timeout", f"{peer} did not complete the handshake in time", severity="warning"
            )
            await _close_raw(writer, CloseReason.PROTOCOL_ERROR, "handshake timeout")
        except HandshakeRefused as exc:
            self._events.publish("agent_refused", f"{peer}: {exc}", severity="warning")
            await _close_raw(writer, CloseReason.REFUSED, str(exc), refusal=True)
        except RateLimited as exc:
            assert session is not None
            self._events.publish("agent_cut_off", str(exc), severity="error", agent=session.identity)
            await session.close(CloseReason.PROTOCOL_ERROR, str(exc))
        except ProtocolError as exc:
            who = session.identity if session else peer
            self._events.publish(
                "protocol_error",
                f"{who}: {exc}",
                severity="warning",
                agent=session.identity if session else None,
            )
            if session is not None:
                await session.close(CloseReason.PROTOCOL_ERROR, str(exc))
            else:
                await _close_raw(writer, CloseReason.PROTOCOL_ERROR, str(exc)[:500])
        except (ConnectionError, OSError, asyncio.IncompleteReadError):
            pass
        except asyncio.CancelledError:
            raise
        except Exception:  # a bug must cost one connection, never the daemon
            log.exception("unexpected error on connection from %s", peer)
        finally:
            if session is not None:
                await self._disconnected(session)
            with contextlib.suppress(Exception):
                writer.close()
            if task is not None:
                self._tasks.discard(task)

    async def _read_frame(
        self, reader: asyncio.StreamReader, decoder: FrameDecoder, backlog: list[Frame]
    ) -> Frame:
        while not backlog:
            data = await reader.read(READ_CHUNK)
            if not data:
                raise ConnectionError("peer closed the connection")
            backlog.extend(decoder.feed(data))
        return backlog.pop(0)

    async def _handshake(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, decoder: FrameDecoder, peer: str
    ) -> AgentSession:
        backlog: list[Frame] = []
        hello = await self._read_frame(reader, decoder, backlog)
        if not isinstance(hello.body, RequestCid):
            raise ProtocolError(f"expected a type 0 request first, got type {hello.packet_type.value}")
        request = hello.body
        if request.protocol_version != PROTOCOL_VERSION:
            raise HandshakeRefused(
                f"protocol version {request.protocol_version} not supported "
                f"(daemon speaks {PROTOCOL_VERSION})"
            )
        key = self._keys.key_for(request.identity)
        if key is None:
            raise HandshakeRefused(f"unknown agent {request.identity!r}: no key is configured for it")
        probing = request.probe
        if (
            not probing
            and len(self.connected()) >= self.config.max_agents
            and request.identity not in self.sessions
        ):
            raise HandshakeRefused(f"fleet full: {self.config.max_agents} agents connected")
        server_nonce = auth.new_nonce()
        writer.write(encode(ResponseCid(outcome="challenge", server_nonce=server_nonce), 1))
        await writer.drain()
        answer = await self._read_frame(reader, decoder, backlog)
        proof_request = answer.body
        if not isinstance(proof_request, RequestCid) or proof_request.identity != request.identity:
            raise ProtocolError("expected the type 0 request with proof for the same identity")
        if proof_request.client_nonce != request.client_nonce or proof_request.proof is None:
            raise HandshakeRefused("proof missing or client nonce changed")
        expected = auth.agent_proof(key, request.identity, server_nonce, request.client_nonce)
        if not auth.proofs_equal(proof_request.proof, expected):
            raise HandshakeRefused(f"authentication failed for {request.identity!r}: wrong key")
        if probing or proof_request.probe:  # authenticated only: no CID, no session, never a member
            await _answer_probe(writer, request, key, server_nonce, self.config, self._events)
        cid = self._store.cid_for(request.identity, proof_request.capabilities.model_dump())
        outbox = Outbox(
            writer,
            request.identity,
            self.config.send_timeout_s,
            self.config.max_pending_bytes,
            first_seq=1,  # the challenge was frame 1
        )
        session = AgentSession(
            identity=request.identity,
            cid=cid,
            capabilities=proof_request.capabilities,
            home=proof_request.home,
            writer=writer,
            peer=peer,
            outbox=outbox,
        )
        session.compact_status = bool(proof_request.compact_status)
        outbox.on_cut_off = lambda reason: self._cut_off(session, reason)
        outbox.start()
        parameters = self.config.agent_parameters.model_copy(
            update={"status_period_s": self.config.status_period_s}
        )
        accepted = ResponseCid(
            outcome="accepted",
            cid=cid,
            server_nonce=server_nonce,
            server_proof=auth.daemon_proof(key, request.identity, request.client_nonce, server_nonce),
            parameters=parameters,
            server_time=time.time(),
            compact_status=True if session.compact_status else None,
        )
        previous = self.sessions.get(request.identity)
        if previous is not None and previous.open:
            await previous.close(CloseReason.REPLACED, f"replaced by a new session from {peer}")
            self._events.publish(
                "agent_replaced", f"session from {previous.peer} replaced by {peer}", agent=request.identity
            )
        self.sessions[request.identity] = session
        if not await session.send(accepted, self.config.send_timeout_s):
            raise ConnectionError("agent left during the handshake")
        was_lost = request.identity in self.lost
        self.lost.discard(request.identity)
        self._events.publish(
            "agent_joined",
            f"cid {cid} from {peer}" + (" (back after being lost)" if was_lost else ""),
            agent=request.identity,
            data={"cid": cid, "resume": proof_request.resume.model_dump() if proof_request.resume else None},
        )
        # Join hooks run in their services' consumers, outside this handshake's time budget.
        self._publish("join", session.identity, session, proof_request.resume)
        # Frames that arrived right behind the proof are handled as the frame loop would.
        for frame in backlog:
            self._handle(session, frame)
        return session

    async def _frame_loop(
        self, session: AgentSession, reader: asyncio.StreamReader, decoder: FrameDecoder
    ) -> None:
        """Serve the session's frames until it ends; raises what ended it (protocol error, rate limit).

        After the handshake the connection's protocol is swapped for a :class:`_FrameProtocol`, so
        frames are decoded in the transport's ``data_received`` callback: no task wake-up and no
        ``StreamReader`` buffer copy per read, which at 10 Hz from thousands of agents was most
        of the per-report cost. The stream protocol stays behind it for write flow control.
        """
        transport = session.writer.transport
        stream_protocol = transport.get_protocol()
        bucket = TokenBucket(self.config.max_frames_per_s, self.config.frame_burst)
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        frames = _FrameProtocol(self, session, decoder, bucket, stream_protocol, done)
        transport.set_protocol(frames)
        buffered: bytearray = reader._buffer  # type: ignore[attr-defined]  # read after the handshake
        if buffered:
            leftover = bytes(buffered)
            buffered.clear()
            frames.data_received(leftover)
        if reader.at_eof() or transport.is_closing():
            frames.finish()
        await done

    def _ingest(self, session: AgentSession, decoder: FrameDecoder, bucket: TokenBucket, data: bytes) -> bool:
        """Decode and handle every frame ``data`` completes; False once the session is over."""
        started = time.perf_counter()
        try:
            for frame in decoder.feed(data):
                session.last_rx = time.monotonic()  # complete packets count as life, stray bytes do not
                if not bucket.take(session.last_rx):
                    raise RateLimited(
                        f"more than {self.config.max_frames_per_s:g} frames/s "
                        f"(burst {self.config.frame_burst}); cut off"
                    )
                self.ingest_frames += 1
                self._handle(session, frame)
                if not session.open:
                    return False
            return True
        finally:
            self.ingest_busy_s += time.perf_counter() - started

    def _handle(self, session: AgentSession, frame: Frame) -> None:
        """Record what the frame says and hand it to the hook consumers; nothing is awaited here."""
        body = frame.body
        if isinstance(body, StatusReport):
            if frame.compact and not session.compact_status:
                raise ProtocolError("compact status body (type 0x82) sent without negotiating it")
            self._exception_events(session, body)
            session.status = body
            session.status_count += 1
            self._status_batch.append((session, body))
            if not self._flush_scheduled:
                self._flush_scheduled = True
                asyncio.get_running_loop().call_soon(self._flush_statuses)
        elif isinstance(body, SyncSignal):
            if body.kind != "finished":
                raise ProtocolError("agents may only send 'finished' sync signals")
            self._publish("sync", session.identity, session, body)
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

    def _flush_statuses(self) -> None:
        """Hand the reports received since the last flush to the status consumers, as one batch."""
        self._flush_scheduled = False
        batch, self._status_batch = self._status_batch, []
        if not self._hooks_closed:
            self._hooks.publish_batch(batch)

    def _publish(self, kind: HookKind, agent: str, *args: object) -> None:
        """Publish a non-status event behind every status already received (per-agent order)."""
        if self._status_batch:
            self._flush_statuses()
        if not self._hooks_closed:
            self._hooks.publish(kind, agent, *args)

    def _exception_events(self, session: AgentSession, status: StatusReport) -> None:
        """Turn exceptions that appear in a status report into events (once each)."""
        if not status.exceptions:
            return
        before = {e.split(":", 1)[0] for e in session.status.exceptions} if session.status else set()
        for text in status.exceptions:
            name = text.split(":", 1)[0]
            if name not in before:
                self._events.publish(
                    "agent_exception",
                    text,
                    severity="warning",
                    agent=session.identity,
                    data={"exception": name},
                )

    def _cut_off(self, session: AgentSession, reason: str) -> None:
        """The session's outbox gave up on the peer (overflow or no drain): the session ends."""
        if not session.open:
            return
        session.open = False
        self._events.publish("agent_cut_off", f"{reason}; cut off", severity="error", agent=session.identity)

    async def _disconnected(self, session: AgentSession) -> None:
        session.close_transport()
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
            for session in self.connected():  # only posts: a stuck peer never delays this loop
                if session.outbox.idle and now - session.last_tx >= self.config.keepalive_s:
                    session.post(keepalive, urgent=False)
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
        if self._tasks:  # closed transports end every frame loop; give them a moment to clean up
            await asyncio.wait(list(self._tasks), timeout=2.0)
        self._hooks_closed = True  # a flush still scheduled must not start new consumers
        await self._hooks.close()

    # --- hook consumers -------------------------------------------------------------------------

    async def drain_hooks(self, timeout: float = 10.0) -> bool:
        """Wait until every hook consumer has handled everything queued; False after ``timeout``.

        For tests and services that need "everything received so far has been seen by the hooks".
        """
        if self._status_batch:
            self._flush_statuses()
        return await self._hooks.drain(timeout)

    def hook_stats(self) -> list[ConsumerStats]:
        """Per consumer: queued, delivered, coalesced, dropped, overflow, failed (for metrics)."""
        return self._hooks.stats()


class _FrameProtocol(asyncio.Protocol):
    """An agent connection after its handshake: frames decoded as bytes arrive (see ``_frame_loop``).

    Write flow control (``pause_writing`` / ``resume_writing``) and ``connection_lost`` are
    passed on to the stream protocol the connection started with, so ``StreamWriter.drain()``
    in the session's outbox keeps working.
    """

    def __init__(
        self,
        manager: AgentManager,
        session: AgentSession,
        decoder: FrameDecoder,
        bucket: TokenBucket,
        stream_protocol: asyncio.BaseProtocol,
        done: asyncio.Future[None],
    ) -> None:
        self._manager, self._session, self._decoder, self._bucket = manager, session, decoder, bucket
        self._stream = stream_protocol
        self._done = done

    def finish(self, exc: BaseException | None = None) -> None:
        if not self._done.done():
            if exc is None:
                self._done.set_result(None)
            else:
                self._done.set_exception(exc)

    def data_received(self, data: bytes) -> None:
        if self._done.done():
            return
        try:
            if not self._manager._ingest(self._session, self._decoder, self._bucket, data):
                self.finish()
        except Exception as exc:  # ends this session only: handle_connection deals with it
            self.finish(exc)

    def eof_received(self) -> bool:
        self.finish()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self.finish()
        self._stream.connection_lost(exc)

    def pause_writing(self) -> None:
        self._stream.pause_writing()

    def resume_writing(self) -> None:
        self._stream.resume_writing()


def _peer_name(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    if isinstance(peer, tuple) and len(peer) >= 2:
        return f"{peer[0]}:{peer[1]}"
    return str(peer)


async def _close_raw(
    writer: asyncio.StreamWriter, reason: CloseReason, message: str, refusal: bool = False
) -> None:
    """Tell a peer without a session why it is being dropped, then drop it."""
    with contextlib.suppress(Exception):
        if refusal:
            writer.write(encode(ResponseCid(outcome="refused", reason=message[:500]), 1))
        writer.write(encode(Close(reason=reason, message=message[:500]), 2))
        await asyncio.wait_for(writer.drain(), 1.0)
    with contextlib.suppress(Exception):
        writer.close()


async def _answer_probe(
    writer: asyncio.StreamWriter,
    request: RequestCid,
    key: bytes,
    server_nonce: str,
    config: DaemonConfig,
    events: EventBus,
) -> None:
    """Answer an authenticated probe (``agent doctor``): accepted without a CID, then closed."""
    answer = ResponseCid(
        outcome="accepted",
        server_nonce=server_nonce,
        server_proof=auth.daemon_proof(key, request.identity, request.client_nonce, server_nonce),
        parameters=config.agent_parameters.model_copy(update={"status_period_s": config.status_period_s}),
        server_time=time.time(),
    )
    writer.write(encode(answer, 2))
    writer.write(encode(Close(reason=CloseReason.NORMAL, message="probe answered"), 3))
    await writer.drain()
    events.publish("agent_probe", f"{request.identity} probed from {_peer_name(writer)}")
    raise ProbeAnswered(request.identity)


__all__ = ["AgentManager", "AgentSession", "HandshakeRefused", "PacketType"]

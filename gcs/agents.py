"""Agent manager: TCP sessions, the authenticated handshake, CIDs, liveness, frame routing.

One asyncio task per connection. A connection must complete the type-0/1 handshake within
``handshake_timeout_s``; until then no other packet is accepted. Any protocol error closes
only that connection (type 6 ``protocol_error`` first), never the daemon or other agents.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from gcs.config import DaemonConfig
from gcs.events import EventBus
from gcs.keys import KeyRing
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
    """One authenticated connection of one agent identity."""

    identity: str
    cid: int
    capabilities: Capabilities
    home: GeoPoint | None
    writer: asyncio.StreamWriter
    peer: str
    connected_at: float = field(default_factory=time.time)
    last_rx: float = field(default_factory=time.monotonic)
    last_tx: float = field(default_factory=time.monotonic)
    status: StatusReport | None = None
    status_count: int = 0
    open: bool = True
    _seq: int = 0
    _send_lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    async def send(self, body: Body, timeout: float, max_pending: int = 1 << 62) -> bool:
        """Send one packet; False (and the session closed) if the peer is gone or too slow.

        A peer that does not read (its socket buffer full and ``max_pending`` bytes queued here)
        is cut off rather than letting the daemon's memory grow.
        """
        if not self.open:
            return False
        async with self._send_lock:
            self._seq += 1
            try:
                if self.writer.transport.get_write_buffer_size() > max_pending:
                    raise ConnectionError(
                        f"more than {max_pending} bytes waiting for a peer that does not read"
                    )
                self.writer.write(encode(body, self._seq))
                self.last_tx = time.monotonic()
                async with asyncio.timeout(timeout):
                    await self.writer.drain()
            except (OSError, TimeoutError, ConnectionError) as exc:
                log.warning("send to %s failed: %s", self.identity, exc)
                self.close_transport()
                return False
        return True

    def close_transport(self) -> None:
        self.open = False
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
        self._tasks: set[asyncio.Task[None]] = set()
        self._pending_handshakes = 0

    # --- queries --------------------------------------------------------------------------------

    def session(self, identity: str) -> AgentSession | None:
        session = self.sessions.get(identity)
        return session if session is not None and session.open else None

    def connected(self) -> list[AgentSession]:
        return [s for s in self.sessions.values() if s.open]

    async def send(self, identity: str, body: Body) -> bool:
        session = self.session(identity)
        if session is None:
            return False
        return await session.send(body, self.config.send_timeout_s, self.config.max_pending_bytes)

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
            await session.send(Close(reason=CloseReason.PROTOCOL_ERROR, message=str(exc)), 1.0)
            session.close_transport()
        except ProtocolError as exc:
            who = session.identity if session else peer
            self._events.publish(
                "protocol_error",
                f"{who}: {exc}",
                severity="warning",
                agent=session.identity if session else None,
            )
            if session is not None:
                await session.send(Close(reason=CloseReason.PROTOCOL_ERROR, message=str(exc)[:500]), 1.0)
                session.close_transport()
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
        session = AgentSession(
            identity=request.identity,
            cid=cid,
            capabilities=proof_request.capabilities,
            home=proof_request.home,
            writer=writer,
            peer=peer,
        )
        session._seq = 1
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
        )
        previous = self.sessions.get(request.identity)
        if previous is not None and previous.open:
            await previous.send(
                Close(reason=CloseReason.REPLACED, message=f"replaced by a new session from {peer}"), 1.0
            )
            previous.close_transport()
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
        for hook in self.on_join:
            await hook(session, proof_request.resume)
        # Frames that arrived right behind the proof are handled by the frame loop.
        for frame in backlog:
            await self._dispatch(session, frame)
        return session

    async def _frame_loop(
        self, session: AgentSession, reader: asyncio.StreamReader, decoder: FrameDecoder
    ) -> None:
        bucket = TokenBucket(self.config.max_frames_per_s, self.config.frame_burst)
        while session.open:
            data = await reader.read(READ_CHUNK)
            if not data:
                return
            for frame in decoder.feed(data):
                session.last_rx = time.monotonic()  # complete packets count as life, stray bytes do not
                if not bucket.take(session.last_rx):
                    raise RateLimited(
                        f"more than {self.config.max_frames_per_s:g} frames/s "
                        f"(burst {self.config.frame_burst}); cut off"
                    )
                await self._dispatch(session, frame)
                if not session.open:
                    return

    async def _dispatch(self, session: AgentSession, frame: Frame) -> None:
        body = frame.body
        if isinstance(body, StatusReport):
            self._exception_events(session, body)
            session.status = body
            session.status_count += 1
            for status_hook in self.on_status:
                await status_hook(session, body)
        elif isinstance(body, SyncSignal):
            if body.kind != "finished":
                raise ProtocolError("agents may only send 'finished' sync signals")
            for sync_hook in self.on_sync:
                await sync_hook(session, body)
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

    def _exception_events(self, session: AgentSession, status: StatusReport) -> None:
        """Turn exceptions that appear in a status report into events (once each)."""
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

    async def _disconnected(self, session: AgentSession) -> None:
        session.open = False
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
            for session in self.connected():
                if now - session.last_tx >= self.config.keepalive_s:
                    await session.send(keepalive, self.config.send_timeout_s, self.config.max_pending_bytes)
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
                for hook in self.on_lost:
                    await hook(identity)

    async def close_all(self, reason: CloseReason, message: str) -> None:
        for session in self.connected():
            await session.send(Close(reason=reason, message=message), 1.0)
            session.close_transport()
        if self._tasks:  # closed transports end every frame loop; give them a moment to clean up
            await asyncio.wait(list(self._tasks), timeout=2.0)


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

"""Admission: a new connection's handshake, who may join, and the end of a served session.

A connection must complete the handshake (:class:`protocol.session.ServerHandshake`, read
through the shared :class:`protocol.stream.FramedStream`: versions negotiated, refusals with
codes) within ``handshake_timeout_s`` with frames under 1 KiB, and at most ``max_handshakes``
run at once, ``max_handshakes_per_source`` from one address (gcs/link/preauth.py, which also
rate-limits enrollment); until then no other packet is accepted. Refusals that do not depend on
the key (fleet full, banned, certificate binding, enrollment closed, CID exhaustion) are decided
after the agent's proof, so the session layer proves them to the agent (``refusal_proof``). Any
protocol error closes only that connection (type 6 ``protocol_error`` first), never the daemon
or other agents. Once admitted the session is served: its frames go to the frame ingest
(gcs/link/ingest.py) and this connection's task ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import time
from collections.abc import Awaitable, Callable

from gcs.core.config import DaemonConfig
from gcs.link.connection import Connection
from gcs.link.ingest import FrameIngest
from gcs.link.keys import KeyRing
from gcs.link.outbox import Outbox
from gcs.link.preauth import PreAuthLimits
from gcs.link.rates import RateLimited
from gcs.link.session import AgentSession
from gcs.link.sessions import SessionRegistry
from gcs.link.status_tick import StatusTicker
from gcs.observe.events import EventBus
from gcs.storage.store import CidExhausted, Store
from protocol.packets import PROTOCOL_VERSION, AgentParameters, CloseReason, RequestCid
from protocol.session import Code, Refused, ServerHandshake, close_for
from protocol.stream import FramedStream
from protocol.wire import PRE_AUTH_MAX_BODY, ProtocolError

log = logging.getLogger("gcs.link.admission")


class ProbeAnswered(ConnectionError):
    """A probe (``agent doctor``) was authenticated and answered; the connection simply ends."""


class Admission:
    """Runs each connection's handshake, admits or refuses it, serves it, and ends it."""

    def __init__(
        self,
        config: DaemonConfig,
        store: Store,
        events: EventBus,
        keys: KeyRing,
        registry: SessionRegistry,
        frames: FrameIngest,
        ticker: StatusTicker,
        assign_cid: Callable[[str], Awaitable[int]] | None = None,
    ) -> None:
        self.config = config
        self._store = store
        self._events = events
        self._keys = keys
        self._registry = registry
        self._frames = frames
        self._ticker = ticker  # joins are published through it; a session's end flushes its row
        self._table = ticker.table
        self.assign_cid = assign_cid  # cluster mode (gcs/cluster): the shared CID registry
        self.pre_auth = PreAuthLimits(config)  # handshake slots and enrollments per source address
        self.accepting = True  # False: handshakes are refused with code `starting`
        self.serving = 0  # sessions whose frames are served (their end is still to come)

    async def handle_connection(self, conn: Connection) -> None:
        """The connection's one task, for its handshake only: once the session is served its frames
        are handled by the protocol (gcs/link/connection.py) and this task ends."""
        writer = conn.writer
        peer = peer_name(writer)
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
                    await self.disconnected(conn.session)
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

    async def end(self, conn: Connection, exc: BaseException | None) -> None:
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
            self.serving -= 1
            await self.disconnected(session)
            with contextlib.suppress(Exception):
                conn.writer.close()

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
            and len(self._registry.connected()) >= self.config.max_agents
            and request.identity not in self._registry.sessions
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
        self, stream: FramedStream, handshake: ServerHandshake, conn: Connection, peer: str, source: str
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
            on_cut_off=self._registry.cut_off,
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
        was_lost = request.identity in self._registry.lost
        accepted = handshake.accept(cid, self._parameters(), time.time(), lost=was_lost)
        previous = self._registry.sessions.get(request.identity)
        if previous is not None and previous.open:
            await previous.close(
                CloseReason.REPLACED, f"replaced by a new session from {peer}", code=Code.REPLACED
            )
            self._events.publish(
                "agent_replaced", f"session from {previous.peer} replaced by {peer}", agent=request.identity
            )
        self._registry.sessions[request.identity] = session
        if not await session.send(accepted, self.config.send_timeout_s):
            raise ConnectionError("agent left during the handshake")
        self._registry.lost.discard(request.identity)
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
        self._ticker.publish("join", session.identity, session, request.resume)
        return session

    def _parameters(self) -> AgentParameters:
        return self.config.agent_parameters.model_copy(
            update={"status_period_s": self.config.status_period_s}
        )

    def _serve(self, conn: Connection, stream: FramedStream) -> None:
        """Serve the session's frames from now on in the protocol's ``buffer_updated`` (gcs/link/ingest.py):
        no task and no stream objects per connection. Frames that came right behind the proof come
        first; raises what ends the session among them (protocol error, rate limit)."""
        session = conn.session
        assert session is not None and conn.reader is not None
        reader, conn.reader = conn.reader, None  # from here on the protocol ingests what arrives
        conn.decoder = stream.decoder
        session.row = self._table.attach(conn)
        session.table = self._table
        self.serving += 1
        while stream.backlog:
            frame = stream.backlog.popleft()
            self._frames.take(conn, frame, time.monotonic())
            self._frames.handle(session, frame)
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

    async def disconnected(self, session: AgentSession) -> None:
        """The session's transport is closed; its last report still goes to the hooks, its row is freed."""
        session.close_transport()
        if session.table is not None:  # its last report still goes to the hooks, then the row is free
            with contextlib.suppress(ProtocolError):
                self._ticker.flush(session)
            _ = session.status  # kept as the session's last word once its row is free
            session.table.release(session.row)
            session.table = None
        if self._registry.sessions.get(session.identity) is session:
            self._events.publish(
                "agent_disconnected", f"connection from {session.peer} ended", agent=session.identity
            )


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


def peer_name(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    if isinstance(peer, tuple) and len(peer) >= 2:
        return f"{peer[0]}:{peer[1]}"
    return str(peer)


__all__ = ["Admission", "ProbeAnswered", "certificate_identities", "source_of"]

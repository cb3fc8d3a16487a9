"""The agent's side of the daemon link: connect, authenticate, reconnect with backoff, buffer.

While the link is down, status reports go into a bounded buffer (oldest dropped first) and
control packets (sync "finished") into an unbounded one; both are delivered, in order, right
after the next successful handshake. A ``replaced`` close means another process runs with our
identity; the link then waits ``REPLACED_BACKOFF_S`` before trying again, so two agents with
one identity do not take turns kicking each other off.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import ssl
import time
from collections import deque
from collections.abc import Awaitable, Callable

from agent.config import AgentConfig
from protocol import auth
from protocol.packets import (
    PROTOCOL_VERSION,
    Body,
    Close,
    CloseReason,
    GeoPoint,
    PerformActions,
    RequestCid,
    ResponseCid,
    Resume,
    SetParameters,
    StatusReport,
    SyncSignal,
)
from protocol.wire import Frame, FrameDecoder, ProtocolError, encode

log = logging.getLogger("agent.link")

REPLACED_BACKOFF_S = 30.0
REFUSED_BACKOFF_S = 10.0


def client_tls_context(config: AgentConfig) -> ssl.SSLContext | None:
    """TLS towards the daemon when a CA is configured; with tls_cert, mutual TLS."""
    if config.tls_ca is None:
        return None
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(config.tls_ca))
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    if config.tls_cert is not None:
        context.load_cert_chain(config.tls_cert, config.tls_key)
    return context


class HandshakeFailed(Exception):
    def __init__(self, message: str, backoff_s: float | None = None) -> None:
        super().__init__(message)
        self.backoff_s = backoff_s


class DaemonLink:
    """Keeps one authenticated session to the daemon and routes what arrives to handlers."""

    def __init__(
        self,
        config: AgentConfig,
        key: bytes,
        on_actions: Callable[[PerformActions], Awaitable[None]],
        on_release: Callable[[SyncSignal], Awaitable[None]],
        on_parameters: Callable[[SetParameters], Awaitable[None]],
        home: Callable[[], GeoPoint | None],
        resume: Callable[[], Resume | None],
    ) -> None:
        self.config = config
        self._key = key
        self._on_actions = on_actions
        self._on_release = on_release
        self._on_parameters = on_parameters
        self._home = home
        self._resume = resume
        self.cid: int | None = None
        self.connected = False
        self.last_contact = time.monotonic()
        self.sessions = 0
        self.last_error: str | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._seq = 0
        self.compact_status = False  # the daemon accepted the compact binary status body
        self._status_backlog: deque[StatusReport] = deque(maxlen=config.status_buffer)
        self._control_backlog: list[Body] = []
        self._send_lock = asyncio.Lock()
        self._stopping = False

    # --- sending --------------------------------------------------------------------------------

    async def send_status(self, status: StatusReport) -> None:
        if not self.connected or not await self._send(status):
            self._status_backlog.append(status.model_copy(update={"buffered": True}))

    async def send_control(self, body: Body) -> None:
        if not self.connected or not await self._send(body):
            self._control_backlog.append(body)

    async def _send(self, body: Body) -> bool:
        writer = self._writer
        if writer is None:
            return False
        async with self._send_lock:
            self._seq += 1
            try:
                writer.write(encode(body, self._seq, compact=self.compact_status))
                async with asyncio.timeout(5.0):
                    await writer.drain()
            except (OSError, TimeoutError, ConnectionError):
                self._drop()
                return False
        return True

    def _drop(self) -> None:
        self.connected = False
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close()
        self._writer = None

    # --- session loop ---------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, serve, reconnect with jittered exponential backoff; until cancelled."""
        delay = self.config.reconnect_min_s
        while not self._stopping:
            backoff: float | None = None
            try:
                tls = client_tls_context(self.config)
                server_name = (self.config.tls_server_name or self.config.gcs_host) if tls else None
                async with asyncio.timeout(self.config.handshake_timeout_s):
                    reader, writer = await asyncio.open_connection(
                        self.config.gcs_host, self.config.gcs_port, ssl=tls, server_hostname=server_name
                    )
            except (OSError, TimeoutError) as exc:  # ssl.SSLError is an OSError
                self.last_error = (
                    f"cannot reach daemon {self.config.gcs_host}:{self.config.gcs_port}: {exc!r}"
                )
            else:
                try:
                    await self._session(reader, writer)
                    delay = self.config.reconnect_min_s
                except HandshakeFailed as exc:
                    self.last_error = str(exc)
                    backoff = exc.backoff_s
                    log.error("%s", exc)
                except (
                    ProtocolError,
                    ConnectionError,
                    OSError,
                    TimeoutError,
                    asyncio.IncompleteReadError,
                ) as exc:
                    self.last_error = f"link error: {exc}"
                    log.warning("daemon link lost: %s", exc)
                except Exception as exc:  # whatever a peer sends, the agent must live on and reconnect
                    self.last_error = f"unexpected link failure: {exc!r}"
                    log.exception("daemon link failed unexpectedly")
                finally:
                    self._drop()
            if self._stopping:
                return
            wait = backoff if backoff is not None else delay * (0.75 + 0.5 * random.random())
            await asyncio.sleep(wait)
            delay = min(self.config.reconnect_max_s, delay * 2)

    async def stop(self, reason: CloseReason = CloseReason.NORMAL) -> None:
        self._stopping = True
        if self.connected:
            await self._send(Close(reason=reason, message="agent stopping"))
        self._drop()

    async def _session(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        decoder = FrameDecoder()
        backlog: list[Frame] = []
        self._writer = writer
        self._seq = 0
        self.compact_status = False
        async with asyncio.timeout(self.config.handshake_timeout_s):
            await self._handshake(reader, decoder, backlog)
        self.connected = True
        self.sessions += 1
        self.last_contact = time.monotonic()
        log.info("connected to daemon as %s, cid %s", self.config.identity, self.cid)
        await self._flush_backlog()
        for frame in backlog:
            await self._dispatch(frame)
        while self.connected:
            try:
                async with asyncio.timeout(self.config.daemon_silence_s):
                    data = await reader.read(65_536)
            except TimeoutError:  # a silent partition: TCP open, nothing flowing (the daemon keeps alive)
                raise ConnectionError(
                    f"nothing from the daemon for {self.config.daemon_silence_s:g} s"
                ) from None
            if not data:
                raise ConnectionError("daemon closed the connection")
            self.last_contact = time.monotonic()
            for frame in decoder.feed(data):
                await self._dispatch(frame)

    async def _handshake(
        self, reader: asyncio.StreamReader, decoder: FrameDecoder, backlog: list[Frame]
    ) -> None:
        client_nonce = auth.new_nonce()
        hello = RequestCid(
            identity=self.config.identity, protocol_version=PROTOCOL_VERSION, client_nonce=client_nonce
        )
        if not await self._send(hello):
            raise ConnectionError("daemon went away during the handshake")
        challenge = await _next_frame(reader, decoder, backlog)
        if isinstance(challenge.body, Close):
            raise HandshakeFailed(f"daemon closed: {challenge.body.message}", REFUSED_BACKOFF_S)
        if not isinstance(challenge.body, ResponseCid):
            raise ProtocolError("expected a type 1 challenge")
        if challenge.body.outcome == "refused":
            raise HandshakeFailed(f"daemon refused us: {challenge.body.reason}", REFUSED_BACKOFF_S)
        server_nonce = challenge.body.server_nonce
        if challenge.body.outcome != "challenge" or server_nonce is None:
            raise ProtocolError("expected a type 1 challenge with a nonce")
        request = RequestCid(
            identity=self.config.identity,
            protocol_version=PROTOCOL_VERSION,
            client_nonce=client_nonce,
            capabilities=self.config.capabilities,
            home=self._home(),
            proof=auth.agent_proof(self._key, self.config.identity, server_nonce, client_nonce),
            resume=self._resume(),
            compact_status=True,
        )
        if not await self._send(request):
            raise ConnectionError("daemon went away during the handshake")
        answer = await _next_frame(reader, decoder, backlog)
        body = answer.body
        if isinstance(body, ResponseCid) and body.outcome == "accepted" and body.cid is not None:
            expected = auth.daemon_proof(self._key, self.config.identity, client_nonce, server_nonce)
            if body.server_proof is None or not auth.proofs_equal(body.server_proof, expected):
                raise HandshakeFailed(
                    "the daemon could not prove it holds our key; not trusting it", REFUSED_BACKOFF_S
                )
            self.cid = body.cid
            self.compact_status = bool(body.compact_status)
            if body.parameters is not None:
                await self._on_parameters(SetParameters(parameters=body.parameters))
            return
        reason = body.reason if isinstance(body, ResponseCid) else getattr(body, "message", "")
        raise HandshakeFailed(f"daemon refused {self.config.identity}: {reason}", REFUSED_BACKOFF_S)

    async def _flush_backlog(self) -> None:
        while self._status_backlog and self.connected:
            if not await self._send(self._status_backlog[0]):
                return
            self._status_backlog.popleft()
        while self._control_backlog and self.connected:
            if not await self._send(self._control_backlog[0]):
                return
            self._control_backlog.pop(0)

    async def _dispatch(self, frame: Frame) -> None:
        body = frame.body
        if isinstance(body, PerformActions):
            await self._on_actions(body)
        elif isinstance(body, SyncSignal) and body.kind == "release":
            await self._on_release(body)
        elif isinstance(body, SetParameters):
            await self._on_parameters(body)
        elif isinstance(body, Close):
            self._drop()
            if body.reason == CloseReason.REPLACED:
                raise HandshakeFailed(
                    f"replaced by another session of {self.config.identity}", REPLACED_BACKOFF_S
                )
            raise ConnectionError(f"daemon closed the session: {body.reason.value} {body.message}")
        else:
            raise ProtocolError(f"type {frame.packet_type.value} is not valid from the daemon")

    @property
    def buffered(self) -> tuple[int, int]:
        """(status reports, control packets) waiting for the link."""
        return len(self._status_backlog), len(self._control_backlog)


async def _next_frame(reader: asyncio.StreamReader, decoder: FrameDecoder, backlog: list[Frame]) -> Frame:
    while not backlog:
        data = await reader.read(65_536)
        if not data:
            raise ConnectionError("daemon closed the connection")
        backlog.extend(decoder.feed(data))
    return backlog.pop(0)

"""One agent connection from accept to close (:class:`Connection`, an asyncio ``BufferedProtocol``).

Why a module of its own: it is the only object per connection besides the session, and it knows
the rest of the link only through :class:`ConnectionHost` (the agent manager, gcs/link/agents.py):
where reads land, who runs the handshake, who takes a served connection's frames, who ends it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, Protocol

from gcs.core.config import DaemonConfig
from gcs.link.rates import TokenBucket
from gcs.link.session import AgentSession
from protocol.wire import FrameDecoder

HANDSHAKE_READ_LIMIT = 1 << 16  # a connection's StreamReader during the handshake (flow control)


class ConnectionHost(Protocol):
    """What a connection needs of the link around it."""

    config: DaemonConfig
    read_buffer: memoryview  # every served connection reads into this one buffer

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None: ...

    async def handle_connection(self, conn: Connection) -> None: ...

    def take_frames(self, conn: Connection, data: bytes | memoryview) -> bool: ...

    async def end(self, conn: Connection, exc: BaseException | None) -> None: ...


class Connection(asyncio.BufferedProtocol):
    """One agent connection from accept to close: the only object per connection besides the session.

    During the handshake the bytes feed a ``StreamReader`` that the connection's one task reads
    through :class:`~protocol.stream.FramedStream`. Once the session is served
    (gcs/link/admission.py) that task and the reader are gone: every read lands in the
    link's one shared buffer (``get_buffer``) and ``buffer_updated`` hands it to the
    frame ingest (gcs/link/ingest.py), which consumes it at once (a partial frame stays in the
    connection's decoder), so no read allocates. Writes go through a ``StreamWriter`` whose flow
    control is this object's (``pause_writing``/``resume_writing``/``_drain_helper``), which is what
    the session's outbox drains on. A session's end runs in a task started only then (:meth:`finish`).
    """

    __slots__ = (
        "_drain_waiters",
        "_host",
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

    def __init__(self, host: ConnectionHost) -> None:
        config = host.config
        self._host = host
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
        self._host.spawn(self._host.handle_connection(self))

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._host.read_buffer

    def buffer_updated(self, nbytes: int) -> None:
        data = self._host.read_buffer[:nbytes]
        if self.reader is not None:  # the handshake: its task reads the bytes (copied)
            self.reader.feed_data(data)
        else:
            self.ingest(data)

    def ingest(self, data: bytes | memoryview) -> None:
        """Handle the frames ``data`` completes, synchronously (``data`` may be the shared buffer)."""
        if self.ended:
            return
        try:
            if not self._host.take_frames(self, data):
                self.finish()
        except Exception as exc:  # ends this session only (the host's end deals with it)
            self.finish(exc)

    def finish(self, exc: BaseException | None = None) -> None:
        """The served session is over (``exc``: why); its end runs in a task of its own, once."""
        if self.ended or self.reader is not None:  # not served yet: the handshake task ends it
            return
        self.ended = True
        self._host.spawn(self._host.end(self, exc))

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


__all__ = ["Connection", "ConnectionHost"]

"""A framed stream over asyncio: read a frame, send with the next sequence number, bounded drain.

This is the only module of ``protocol/`` that uses asyncio; the codec (:mod:`protocol.wire`),
the bodies and the handshake state machines (:mod:`protocol.session`) never import it. The
daemon, the agent, ``agent doctor``, the benches and the tests all read and write frames through
:class:`FramedStream`, and run the client handshake through :func:`client_handshake`.
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl as ssl_module
from collections import deque
from collections.abc import AsyncIterator

from protocol.packets import Body, GeoPoint, Resume
from protocol.session import Accepted, ClientHandshake
from protocol.wire import DEFAULT_MAX_BODY, SEQ_MODULO, Frame, FrameDecoder, encode

READ_CHUNK = 65_536
DRAIN_TIMEOUT_S = 5.0


class FramedStream:
    """One connection's frames. ``version`` shapes what is sent (a v1 peer gets v1 bodies)."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        *,
        max_body: int = DEFAULT_MAX_BODY,
        version: int = 1,
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.decoder = FrameDecoder(max_body)
        self.version = version
        self.compact_status = False  # negotiated (v2): status reports go out in the binary body
        self.seq = 0  # of the last frame sent
        self.backlog: deque[Frame] = deque()  # decoded, not yet read

    async def _fill(self, timeout: float | None) -> None:
        async with asyncio.timeout(timeout):
            data = await self.reader.read(READ_CHUNK)
        if not data:
            raise ConnectionError("peer closed the connection")
        self.backlog.extend(self.decoder.feed(data))

    async def read_frame(self, timeout: float | None = None) -> Frame:
        """The next frame; ``timeout`` bounds each wait for bytes (TimeoutError)."""
        while not self.backlog:
            await self._fill(timeout)
        return self.backlog.popleft()

    async def frames(self, idle_timeout: float | None = None) -> AsyncIterator[Frame]:
        """Every frame until the peer closes (then ConnectionError); the frame loop, written once.

        ``idle_timeout``: TimeoutError when no bytes arrive for that long.
        """
        while True:
            while self.backlog:
                yield self.backlog.popleft()
            await self._fill(idle_timeout)

    def frame(self, body: Body) -> bytes:
        """Encode ``body`` with the next sequence number (for callers that batch writes)."""
        self.seq = (self.seq + 1) % SEQ_MODULO
        return encode(body, self.seq, self.version, compact=self.compact_status)

    def write(self, *bodies: Body) -> None:
        """Queue ``bodies`` on the transport, numbered in order; no waiting."""
        self.writer.write(b"".join(self.frame(body) for body in bodies))

    async def send(self, *bodies: Body, timeout: float = DRAIN_TIMEOUT_S) -> None:
        """Write ``bodies`` and wait (at most ``timeout``) until the transport drained them."""
        self.write(*bodies)
        async with asyncio.timeout(timeout):
            await self.writer.drain()

    async def close(self, *bodies: Body, timeout: float = 1.0) -> None:
        """Send ``bodies`` (best effort, bounded) and close the transport."""
        if bodies:
            with contextlib.suppress(Exception):
                await self.send(*bodies, timeout=timeout)
        with contextlib.suppress(Exception):
            self.writer.close()


async def client_handshake(
    stream: FramedStream,
    handshake: ClientHandshake,
    *,
    home: GeoPoint | None = None,
    resume: Resume | None = None,
    timeout: float | None = None,
) -> Accepted:
    """Run ``handshake`` over ``stream``; raises Refused / ProtocolError / ConnectionError / TimeoutError.

    On success ``stream.version`` is the negotiated version and ``stream.compact_status`` whether
    status reports are sent in the compact body.
    """
    stream.version = max(handshake.versions)  # the hello is shaped by what we offer
    async with asyncio.timeout(timeout):
        await stream.send(handshake.hello())
        challenge = await stream.read_frame()
        await stream.send(handshake.on_challenge(challenge.body, home=home, resume=resume))
        accepted = handshake.on_answer((await stream.read_frame()).body)
    stream.version = accepted.version
    stream.compact_status = accepted.compact_status
    return accepted


async def open_client(
    host: str,
    port: int,
    handshake: ClientHandshake,
    *,
    ssl: ssl_module.SSLContext | None = None,
    server_hostname: str | None = None,
    timeout: float = 5.0,
    home: GeoPoint | None = None,
    resume: Resume | None = None,
) -> tuple[FramedStream, Accepted]:
    """Connect and run the client handshake (benches, tests); the caller closes the stream."""
    async with asyncio.timeout(timeout):
        reader, writer = await asyncio.open_connection(
            host,
            port,
            ssl=ssl,
            server_hostname=server_hostname,
        )
    stream = FramedStream(reader, writer)
    try:
        accepted = await client_handshake(stream, handshake, home=home, resume=resume, timeout=timeout)
    except BaseException:
        await stream.close()
        raise
    return stream, accepted


__all__ = ["FramedStream", "client_handshake", "open_client"]

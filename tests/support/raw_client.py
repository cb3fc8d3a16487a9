"""A hand-driven protocol peer for tests that must send exactly what they need (malformed, early, late).

Shared by the backbone, link and fault tests; it speaks the real framed stream over loopback TCP.
"""

from __future__ import annotations

import asyncio
import time

from protocol.packets import PROTOCOL_VERSION, SUPPORTED_VERSIONS, Body, Position, StatusReport
from protocol.session import ClientHandshake, Refused
from protocol.stream import FramedStream
from protocol.wire import Frame


class RawClient:
    """A hand-driven protocol peer on the shared framed stream, to send exactly what a test needs."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.stream = FramedStream(reader, writer, version=PROTOCOL_VERSION)

    @classmethod
    async def connect(cls, port: int) -> RawClient:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        return cls(reader, writer)

    async def send(self, body: Body) -> None:
        await self.stream.send(body)

    async def send_raw(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def receive(self, timeout: float = 5.0) -> Frame | None:
        """Next frame, or None when the daemon closed the connection (an RST included)."""
        try:
            return await self.stream.read_frame(timeout)
        except ConnectionError:
            return None

    async def receive_all_until_closed(self, timeout: float = 5.0) -> list[Body]:
        bodies: list[Body] = []
        for _ in range(20):
            frame = await self.receive(timeout)
            if frame is None:
                return bodies
            bodies.append(frame.body)
        raise AssertionError("daemon kept talking instead of closing")

    async def handshake(
        self, identity: str, key_hex: str, version: int | None = None
    ) -> tuple[Body, str, str]:
        """The shared client handshake, step by step; returns (last answer, server nonce, client nonce)."""
        versions = [version] if version is not None else list(SUPPORTED_VERSIONS)
        session = ClientHandshake(identity, bytes.fromhex(key_hex), versions=versions)
        await self.send(session.hello())
        challenge = await self.receive()
        assert challenge is not None
        try:
            proof = session.on_challenge(challenge.body)
        except Refused:
            return challenge.body, "", session.client_nonce
        await self.send(proof)
        answer = await self.receive()
        assert answer is not None
        return answer.body, session.server_nonce or "", session.client_nonce

    def close(self) -> None:
        self.writer.close()


def build_status_report() -> StatusReport:
    """A plausible status report (landed at 47N 8E), for peers that only need to keep reporting."""
    return StatusReport(time=time.time(), position=Position(lat=47.0, lon=8.0, alt_rel=0.0, alt_amsl=400.0))

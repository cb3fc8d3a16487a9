"""Hostile WebSocket clients: unauthenticated peers that push huge messages into an endpoint.

Raw sockets (the upgrade by hand, one masked binary frame header announcing ``message_bytes``,
then its payload streamed from one reused chunk), so a test can run dozens of them without
holding their messages in its own memory. Each client reconnects after the server drops it, a
bounded number of times; blocking sockets, meant for threads.
"""

from __future__ import annotations

import base64
import os
import socket
import struct
import threading
from dataclasses import dataclass

CHUNK = b"\0" * 65_536


@dataclass
class HostileStats:
    connections: int = 0
    upgraded: int = 0
    refused: int = 0
    bytes_sent: int = 0


def _upgrade(sock: socket.socket, port: int, path: str) -> bool:
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
    )
    answer = b""
    while b"\r\n\r\n" not in answer and len(answer) < 65_536:
        data = sock.recv(4096)
        if not data:
            return False
        answer += data
    return answer.startswith(b"HTTP/1.1 101")


def push_large_messages(
    port: int,
    path: str,
    message_bytes: int,
    stop: threading.Event,
    stats: HostileStats,
    max_connections: int = 40,
) -> None:
    """Connect, upgrade and stream one ``message_bytes`` message, again and again until ``stop``."""
    header = bytes([0x82, 0xFF]) + struct.pack(">Q", message_bytes)  # FIN binary, masked, 64-bit length
    while not stop.is_set() and stats.connections < max_connections:
        stats.connections += 1
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
                if not _upgrade(sock, port, path):
                    stats.refused += 1
                else:
                    stats.upgraded += 1
                    sock.sendall(header + os.urandom(4))
                    left = message_bytes
                    while left > 0 and not stop.is_set():
                        sent = sock.send(CHUNK[: min(left, len(CHUNK))])
                        left -= sent
                        stats.bytes_sent += sent
        except OSError:
            pass  # dropped by the server (as it should be) or timed out: try again
        stop.wait(0.2)


__all__ = ["HostileStats", "push_large_messages"]

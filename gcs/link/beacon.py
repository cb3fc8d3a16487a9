"""The daemon's release-beacon sender: the UDP edge of protocol/beacon.py.

A barrier release goes out as one broadcast datagram before the TCP burst (gcs/missions/runner.py
``_release_now``), so every listening agent of the segment hears it from one ``sendto``. Sending
never blocks and never raises: a full buffer or a down interface is counted and logged, and the
TCP release that always follows carries the release anyway.
"""

from __future__ import annotations

import logging
import socket
import time

from protocol.beacon import encode_beacon, parse_beacon_address

log = logging.getLogger(__name__)
WARN_EVERY_S = 60.0
LOOPBACK_BROADCAST = "127.255.255.255"
"""The broadcast address of loopback: every socket of the host bound to it hears one datagram."""


def free_udp_port() -> int:
    """A UDP port nothing on loopback uses right now (the kernel's pick for a throwaway socket)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def loopback_beacon_address() -> str:
    """A release-beacon address of its own for one run on one host (the demo, tests, benches)."""
    return f"{LOOPBACK_BROADCAST}:{free_udp_port()}"


class BeaconSender:
    """Sends release beacons to one ``IPv4:port`` (a broadcast address); counts what it sent."""

    def __init__(self, address: str) -> None:
        self.target = parse_beacon_address(address)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        self._sock.setblocking(False)
        self.sent = 0
        self.failed = 0
        self._warned_at = -WARN_EVERY_S

    def send(self, mission_id: str, step: int, value: bytes) -> bool:
        """Announce the release of ``step``; False (counted, logged at most once a minute) if it failed."""
        try:
            self._sock.sendto(encode_beacon(mission_id, step, value), self.target)
        except OSError as exc:
            self.failed += 1
            now = time.monotonic()
            if now - self._warned_at >= WARN_EVERY_S:
                self._warned_at = now
                log.warning("release beacon to %s:%d failed (%s); the TCP release follows", *self.target, exc)
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self._sock.close()

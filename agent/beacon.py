"""The agent's side of the release beacon: a UDP listener that releases a barrier ahead of TCP.

Why: the daemon's TCP release costs it one ``send`` per member, so at 1,000 members the last
agent hears it milliseconds after the first; one broadcast datagram (protocol/beacon.py) reaches
them all at once. The TCP release still follows, and a release is idempotent, so the agent acts
on whichever comes first and a lost or refused datagram only costs the TCP burst's time.

What a datagram must pass, cheapest first, so a flood of forged ones costs no hashing beyond
the agent's real progress: it decodes as a beacon; the agent holds an anchor for its mission
(``PerformActions.release_anchor``, kept for the newest ``MAX_MISSIONS`` missions); the command
queue waits for that release (its mission; the barrier it waits at, or the step it completed
last, not released yet: at most two steps at a time); the step has not had
``MAX_REJECTS_PER_STEP`` forgeries already; and its value hashes back to the chain
(:class:`protocol.beacon.ReleaseVerifier`). Only then does it take the TCP release's path.

The socket opens with the first anchor (no anchor, e.g. a version-1 daemon or one without
beacons: no socket), with ``SO_REUSEADDR`` so every agent of one machine receives the broadcast,
and closes with the agent.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass

from agent.command_queue import CommandQueue
from protocol.beacon import BeaconError, ReleaseVerifier, decode_beacon

log = logging.getLogger("agent.beacon")

MAX_MISSIONS = 4
"""Missions whose anchors are kept: the queue acts on one; the others cover a quick switch back."""
MAX_REJECTS_PER_STEP = 4
"""Forged beacons checked per step; after that the step waits for its TCP release."""
NOTE_EVERY_S = 10.0
"""At most one log line per kind of bad datagram in this time (a flood must not flood the log)."""
_MAX_REJECT_KEYS = 16


def beacon_socket(address: tuple[str, int]) -> socket.socket:
    """A non-blocking UDP socket bound to ``address`` beside other agents' (``SO_REUSEADDR``)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setblocking(False)
        sock.bind(address)
    except BaseException:
        sock.close()
        raise
    return sock


@dataclass
class BeaconStats:
    """What the listener did with the datagrams it received (``Agent.beacon.stats``)."""

    received: int = 0
    accepted: int = 0  # verified: released a barrier before its TCP release
    late: int = 0  # for a step released already (its TCP release came first)
    rejected: int = 0  # failed the chain check: forged, or from another chain
    ignored: int = 0  # no anchor for its mission, a step the queue does not wait for, or over budget
    malformed: int = 0  # not a release beacon

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class _Endpoint(asyncio.DatagramProtocol):
    def __init__(self, listener: BeaconListener) -> None:
        self._listener = listener
        self.closed = asyncio.Event()

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self._listener.on_datagram(data)

    def error_received(self, exc: Exception) -> None:
        log.debug("release beacon socket: %s", exc)

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed.set()


class BeaconListener:
    """Receives release beacons on ``address`` and releases ``queue``'s barriers through ``release``."""

    def __init__(
        self, address: tuple[str, int], queue: CommandQueue, release: Callable[[str, int], None]
    ) -> None:
        self.address = address
        self.stats = BeaconStats()
        self.last_error: str | None = None  # why the socket could not be opened, if it could not
        self._queue = queue
        self._release = release
        self._verifiers: OrderedDict[str, tuple[bytes, ReleaseVerifier]] = OrderedDict()
        self._rejects: dict[tuple[str, int], int] = {}
        self._noted: dict[str, float] = {}
        self._transport: asyncio.DatagramTransport | None = None
        self._endpoint: _Endpoint | None = None
        self._open_lock = asyncio.Lock()

    @property
    def listening(self) -> bool:
        return self._transport is not None

    def verifier(self, mission_id: str) -> ReleaseVerifier | None:
        """The verifier held for ``mission_id``, if any."""
        held = self._verifiers.get(mission_id)
        return held[1] if held is not None else None

    async def arm(self, mission_id: str, anchor_hex: str) -> None:
        """Hold ``mission_id``'s anchor (a new verifier only for a new anchor) and listen."""
        anchor = bytes.fromhex(anchor_hex)
        held = self._verifiers.get(mission_id)
        if held is None or held[0] != anchor:
            self._verifiers[mission_id] = (anchor, ReleaseVerifier(anchor))
            log.debug("release anchor for mission %s", mission_id)
        self._verifiers.move_to_end(mission_id)
        while len(self._verifiers) > MAX_MISSIONS:
            self._verifiers.popitem(last=False)
        await self.open()

    async def open(self) -> bool:
        """Bind the socket if it is not bound; False (and ``last_error``) when the address cannot be bound."""
        async with self._open_lock:
            if self._transport is not None:
                return True
            try:
                sock = beacon_socket(self.address)
            except OSError as exc:
                why = exc.strerror or str(exc)
                self.last_error = f"cannot listen for release beacons on {self._where()}: {why}"
                self._note("bind", logging.WARNING, "%s; barriers wait for TCP releases", self.last_error)
                return False
            endpoint = _Endpoint(self)
            try:
                transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
                    lambda: endpoint, sock=sock
                )
            except BaseException:
                sock.close()
                raise
            self._transport, self._endpoint, self.last_error = transport, endpoint, None
            log.info("listening for release beacons on %s", self._where())
            return True

    async def close(self) -> None:
        """Close the socket (bounded wait for the transport to let it go)."""
        transport, endpoint = self._transport, self._endpoint
        self._transport = self._endpoint = None
        if transport is None or endpoint is None:
            return
        if self.stats.received:
            log.info("release beacons: %s", self.stats.as_dict())
        transport.close()
        try:
            async with asyncio.timeout(1.0):
                await endpoint.closed.wait()
        except TimeoutError:
            log.warning("release beacon socket did not close in time")

    def on_datagram(self, data: bytes) -> None:
        """Check one datagram, cheapest test first; release the barrier it proves. Never raises."""
        stats = self.stats
        stats.received += 1
        try:
            beacon = decode_beacon(data)
        except BeaconError as exc:
            stats.malformed += 1
            self._note("malformed", logging.DEBUG, "not a release beacon: %s", exc)
            return
        mission_id, step = beacon.mission_id, beacon.step
        held = self._verifiers.get(mission_id)
        if held is None or not self._queue.awaits_release(mission_id, step):
            if held is not None and self._queue.released(mission_id, step):
                stats.late += 1
            else:
                stats.ignored += 1
            return
        key = (mission_id, step)
        if self._rejects.get(key, 0) >= MAX_REJECTS_PER_STEP:
            stats.ignored += 1
            return
        if not held[1].accept(step, beacon.value):
            stats.rejected += 1
            if len(self._rejects) >= _MAX_REJECT_KEYS:  # budgets of steps no longer awaited are moot
                self._rejects = {k: n for k, n in self._rejects.items() if self._queue.awaits_release(*k)}
            self._rejects[key] = self._rejects.get(key, 0) + 1
            self._note("rejected", logging.WARNING, "beacon %s step %d: bad chain value", mission_id, step)
            return
        stats.accepted += 1
        if stats.accepted == 1:
            log.info("release beacon accepted: step %d of mission %s (the fast path works)", step, mission_id)
        else:
            log.debug("release beacon accepted: step %d of mission %s", step, mission_id)
        self._release(mission_id, step)

    def _where(self) -> str:
        return f"{self.address[0]}:{self.address[1]}"

    def _note(self, kind: str, level: int, message: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._noted.get(kind, -NOTE_EVERY_S) >= NOTE_EVERY_S:
            self._noted[kind] = now
            log.log(level, message + " (stats %s)", *args, self.stats.as_dict())

"""Field-quality links as a test rig: named profiles, the daemon link and the autopilot link.

Two places a real fleet's links hurt (issue 26):

* **agent <-> daemon** (Wi-Fi, LTE, a mesh radio): one :class:`~tests.faults.proxy.FaultProxy` per
  agent. TCP never loses a frame; a lost segment is retransmitted after a timeout, so "loss" is a
  delay *spike* on one frame that every later frame waits behind (``spike_rate``/``spike_s``). An
  outage is a ``stall`` partition of that agent's proxy (bytes held, delivered after healing).
* **agent <-> autopilot** (a UDP or serial radio): a :class:`MavlinkRelay` between the agent's
  MAVLink link and our simulator that drops whole MAVLink frames, both ways.

Delays and spikes are wall time and are not scaled by the rig's speed-up: at 8x they last 8x
longer in vehicle time than in the field (harsher, never kinder). Outages are given in field
seconds and divided by the rig's time scale (:meth:`LinkProfile.outage_wall_s`), so a 30 s outage
is 30 s of vehicle time.

    async with LinkRig(PROFILES["lte"]) as links, rig(tmp, 3, **links.rig_options(SPEEDUP)) as r:
        links.proxies["drone-2"].partition(links.profile.outage_wall_s(SPEEDUP))
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import struct
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from tests.faults.proxy import FaultProxy

MAX_READS = 1_000_000  # per direction and connection; a test never gets near it
READ_CHUNK = 65_536
V1, V2 = 0xFE, 0xFD
COMMAND_LONG, COMMAND_ACK = 76, 77


@dataclass(frozen=True)
class LinkProfile:
    """One field condition. ``rtl_bound_s``: how long (wall s at the rig's speed-up) an operator's
    RTL may take from the daemon's call to the first command of the return reaching the vehicle."""

    name: str
    delay_s: float = 0.0  # one-way, each direction
    jitter_s: float = 0.0  # uniform on top of delay_s
    spike_rate: float = 0.0  # TCP segment loss: fraction of frames held for a retransmission
    spike_s: float = 0.0
    outage_s: float = 0.0  # field seconds of one stall partition on one agent's link (0: none)
    mavlink_loss: float = 0.0  # fraction of MAVLink frames dropped between agent and autopilot
    rtl_bound_s: float = 1.0

    def outage_wall_s(self, time_scale: float) -> float:
        """The outage in wall seconds on a rig running ``time_scale`` x real time."""
        return self.outage_s / max(time_scale, 1.0)

    def apply(self, proxy: FaultProxy) -> None:
        """Set both directions of ``proxy`` to this profile's latency and retransmission spikes."""
        for faults in (proxy.up, proxy.down):
            faults.delay_s, faults.jitter_s = self.delay_s, self.jitter_s
            faults.spike_rate, faults.spike_s = self.spike_rate, self.spike_s


# The bounds: the worst one-way delay (+ a spike) twice over, the agent's MAVLink command
# timeout for one lost frame, and a margin for a loaded 2-core host running daemon, 3 agents and
# the simulator in one process. An outage's bound is the outage itself plus the same margin.
PROFILES: dict[str, LinkProfile] = {
    p.name: p
    for p in (
        LinkProfile("wifi", delay_s=0.02, jitter_s=0.06, spike_rate=0.01, spike_s=0.3, rtl_bound_s=1.5),
        LinkProfile("lte", delay_s=0.15, jitter_s=0.25, rtl_bound_s=2.0),
        LinkProfile("mavlink-loss", mavlink_loss=0.10, rtl_bound_s=2.5),
        LinkProfile("outage", delay_s=0.02, jitter_s=0.06, outage_s=30.0, rtl_bound_s=1.5),
    )
}


# --- the agent <-> autopilot relay -------------------------------------------------------------


def split_mavlink(buffer: bytearray) -> list[bytes]:
    """Cut whole MAVLink 1/2 frames off the front of ``buffer`` (bytes before a magic go alone)."""
    out: list[bytes] = []
    for _ in range(len(buffer) + 1):
        if not buffer:
            break
        if buffer[0] not in (V1, V2):
            start = next((i for i, b in enumerate(buffer) if b in (V1, V2)), len(buffer))
            out.append(bytes(buffer[:start]))  # not a frame: passed on as it is
            del buffer[:start]
            continue
        if len(buffer) < 3:
            break
        length = buffer[1]
        signed = buffer[0] == V2 and buffer[2] & 0x01  # a signature adds 13 bytes
        size = 8 + length if buffer[0] == V1 else 12 + length + (13 if signed else 0)
        if len(buffer) < size:
            break
        out.append(bytes(buffer[:size]))
        del buffer[:size]
    return out


def message_id(frame: bytes) -> int | None:
    if len(frame) >= 10 and frame[0] == V2:
        return int.from_bytes(frame[7:10], "little")
    if len(frame) >= 6 and frame[0] == V1:
        return frame[5]
    return None


def payload(frame: bytes) -> bytes:
    """The frame's payload, zero-padded back to full length (MAVLink 2 trims trailing zeros)."""
    start = 10 if frame[0] == V2 else 6
    return frame[start : start + frame[1]] + bytes(64)


@dataclass(frozen=True, slots=True)
class CommandSeen:
    """A COMMAND_LONG the relay forwarded to the autopilot."""

    time: float
    command: int
    confirmation: int


@dataclass
class RelayFaults:
    """What one direction of the relay does to whole MAVLink frames (mutable at any time)."""

    loss: float = 0.0
    drop_next: Counter[int] = field(default_factory=Counter)  # message id -> frames still to drop


class MavlinkRelay:
    """A TCP relay between an agent's MAVLink link and our simulator that loses whole frames.

    ``up`` is agent -> autopilot, ``down`` autopilot -> agent. Every COMMAND_LONG forwarded up is
    kept in :attr:`commands` (its confirmation field, so a test can see the retries counted).
    """

    def __init__(self, upstream: str, loss: float = 0.0, *, seed: int = 0) -> None:
        kind, host, port = upstream.split(":")
        if kind != "tcp":
            raise ValueError(f"MavlinkRelay relays TCP links only, not {upstream!r}")
        self.upstream = (host, int(port))
        self.up = RelayFaults(loss)
        self.down = RelayFaults(loss)
        self.commands: list[CommandSeen] = []
        self.stats: Counter[str] = Counter()
        self._rng = random.Random(seed)
        self._server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._writers: list[asyncio.StreamWriter] = []
        self.port = 0

    @property
    def url(self) -> str:
        return f"tcp:127.0.0.1:{self.port}"

    async def start(self) -> MavlinkRelay:
        self._server = await asyncio.start_server(self._on_client, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
        for writer in self._writers:
            writer.transport.abort()
        for task in self._tasks:
            task.cancel()
        if self._tasks:
            await asyncio.wait(self._tasks, timeout=2.0)

    async def __aenter__(self) -> MavlinkRelay:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.append(writer)
        try:
            up_reader, up_writer = await asyncio.wait_for(asyncio.open_connection(*self.upstream), 5.0)
        except (OSError, TimeoutError):
            writer.transport.abort()
            return
        self._writers.append(up_writer)
        pumps = [
            asyncio.create_task(self._pump(reader, up_writer, self.up, "up")),
            asyncio.create_task(self._pump(up_reader, writer, self.down, "down")),
        ]
        self._tasks.update(pumps)
        try:
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in pumps:
                task.cancel()
            for w in (writer, up_writer):
                w.transport.abort()
            self._tasks.difference_update(pumps)

    async def _pump(
        self, src: asyncio.StreamReader, dst: asyncio.StreamWriter, faults: RelayFaults, direction: str
    ) -> None:
        buffer = bytearray()
        with contextlib.suppress(ConnectionError, OSError):
            for _ in range(MAX_READS):
                data = await src.read(READ_CHUNK)
                if not data:
                    return
                buffer += data
                for frame in split_mavlink(buffer):
                    if self._drop(frame, faults):
                        self.stats[f"{direction}_dropped"] += 1
                        continue
                    self.stats[f"{direction}_forwarded"] += 1
                    if direction == "up" and message_id(frame) == COMMAND_LONG:
                        command, _ts, _tc, confirmation = struct.unpack_from("<HBBB", payload(frame), 28)
                        self.commands.append(CommandSeen(time.monotonic(), command, confirmation))
                    dst.write(frame)
                await asyncio.wait_for(dst.drain(), 10.0)

    def _drop(self, frame: bytes, faults: RelayFaults) -> bool:
        msgid = message_id(frame)
        if msgid is None:
            return False
        if faults.drop_next[msgid] > 0:
            faults.drop_next[msgid] -= 1
            return True
        return faults.loss > 0 and self._rng.random() < faults.loss


# --- both, per agent ---------------------------------------------------------------------------


class LinkRig:
    """Per agent: a fault proxy in front of the daemon and (with ``mavlink_loss``) a relay in front
    of its vehicle, both set to ``profile``. Pass :meth:`interpose` to
    :func:`tests.cooperation.rig.rig`; enter this before the rig so it outlives the agents."""

    def __init__(self, profile: LinkProfile, seed: int = 0) -> None:
        self.profile = profile
        self.seed = seed
        self.proxies: dict[str, FaultProxy] = {}
        self.relays: dict[str, MavlinkRelay] = {}

    async def interpose(self, name: str, daemon_port: int, endpoint: str) -> tuple[int, str]:
        """Start ``name``'s proxy (and relay); returns the daemon port and the MAVLink endpoint its
        agent must use."""
        seed = self.seed + len(self.proxies)
        proxy = await FaultProxy(daemon_port, seed=seed, max_stall_s=120.0).start()
        self.profile.apply(proxy)
        self.proxies[name] = proxy
        if self.profile.mavlink_loss <= 0:
            return proxy.port, endpoint
        relay = await MavlinkRelay(endpoint, self.profile.mavlink_loss, seed=seed).start()
        self.relays[name] = relay
        return proxy.port, relay.url

    def rig_options(self, time_scale: float) -> dict[str, Any]:
        """``rig()`` keyword arguments: these links, and the timers they meet scaled alike.

        The agent's MAVLink timers are wall time: its ACK wait is shortened to 0.5 s (at 8x that is
        4 s of vehicle time, against 1.5 s in the field, so each lost frame costs the mission
        little), and ArduCopter's auto-disarm on the ground (10 s) is stretched by ``time_scale``:
        a re-sent takeoff must come before it, as it does in the field (1.5 s against 10 s).
        """
        return {
            "interpose": self.interpose,
            "fleet_options": {"params": {"DISARM_DELAY": round(10 * min(time_scale, 12.0))}},
            "autopilot_options": {"command_timeout_s": 0.5},
        }

    async def __aenter__(self) -> LinkRig:
        return self

    async def __aexit__(self, *exc: object) -> None:
        for relay in self.relays.values():
            await relay.stop()
        for proxy in self.proxies.values():
            await proxy.stop()

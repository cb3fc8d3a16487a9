"""The release beacon: a barrier release as one UDP datagram for every agent of a network segment.

Why: over TCP a release costs the daemon one ``send`` per member; on loopback each one also runs
the receiver's side of the stack, ~6 µs, so 1,000 members take 6-9 ms however lean the Python
(bench/bench_burst_floor.py). One broadcast datagram reaches every listening agent of the segment
with one ``send`` (light-show fleets start their vehicles the same way). It is a fast path only:
the TCP release always follows it, and an agent acts on whichever arrives first (a release is
idempotent), so a lost datagram costs nothing but the time the TCP burst takes.

Authenticity without per-agent keys: a hash chain per mission. The daemon draws a random seed and
computes ``value(i) = H^(L-i)(seed)`` for the mission's sync steps ``i = 0 .. L-1`` and the
anchor ``H^(L+1)(seed)``, which it sends to each agent inside its authenticated TCP session with
the mission's actions (``PerformActions.release_anchor``). A beacon for step ``i`` reveals
``value(i)``; the agent accepts it when hashing it ``i + 1`` times gives the anchor (or ``i - j``
times gives the value of a step ``j`` it accepted before). Only the daemon knows the value of a
step not yet released, so neither a third party nor another drone of the fleet (each knows the
anchor) can forge a release; a replayed beacon names a step already released. ``H`` is SHA-256
with a domain tag, cut to 16 bytes.

Datagram layout (docs/protocol.md "Release beacon")::

    offset size type  field
    0      4    bytes magic "FGRB"
    4      1    u8    layout version (1)
    5      1    u8    mission_id length N (1..64)
    6      N    utf-8 mission_id
    6+N    4    u32   step (little-endian)
    10+N   16   bytes chain value of the step

Pure: no sockets, no asyncio.
"""

from __future__ import annotations

import hashlib
import ipaddress
import secrets
import struct
from dataclasses import dataclass

MAGIC = b"FGRB"
LAYOUT_VERSION = 1
VALUE_BYTES = 16
MAX_CHAIN_STEPS = 4096
"""Longest chain (highest sync step + 1) a mission gets beacons for; a check is at most this many hashes."""
MAX_MISSION_ID_BYTES = 64
MAX_BEACON_BYTES = 6 + MAX_MISSION_ID_BYTES + 4 + VALUE_BYTES
_DOMAIN = b"fleetgcs-release-beacon-v1|"
_STEP = struct.Struct("<I")


class BeaconError(ValueError):
    """A datagram that is not a well-formed release beacon (what is wrong is in the message)."""


def chain_hash(value: bytes) -> bytes:
    """One link of the chain: SHA-256 of the domain tag and ``value``, cut to 16 bytes."""
    return hashlib.sha256(_DOMAIN + value).digest()[:VALUE_BYTES]


@dataclass(frozen=True, slots=True)
class Beacon:
    """A decoded release beacon: the release of ``step`` of ``mission_id``, proven by ``value``."""

    mission_id: str
    step: int
    value: bytes


class ReleaseChain:
    """The daemon's chain for one mission: the anchor to hand out and each step's value to reveal."""

    def __init__(self, steps: int, seed: bytes | None = None) -> None:
        if not 1 <= steps <= MAX_CHAIN_STEPS:
            raise ValueError(f"a release chain covers 1..{MAX_CHAIN_STEPS} sync steps, not {steps}")
        link = seed if seed is not None else secrets.token_bytes(VALUE_BYTES)
        values: list[bytes] = []
        for _ in range(steps):  # values[0] = H(seed) is the last step's; reversed below
            link = chain_hash(link)
            values.append(link)
        values.reverse()
        self._values = values
        self.anchor = chain_hash(values[0])

    @property
    def steps(self) -> int:
        return len(self._values)

    def value(self, step: int) -> bytes | None:
        """The value revealing ``step``'s release; None for a step beyond the chain."""
        if 0 <= step < len(self._values):
            return self._values[step]
        return None


class ReleaseVerifier:
    """The agent's check of beacons for one mission, from the anchor its daemon sent over TCP."""

    def __init__(self, anchor: bytes) -> None:
        if len(anchor) != VALUE_BYTES:
            raise ValueError(f"a release anchor is {VALUE_BYTES} bytes, not {len(anchor)}")
        self._known_step = -1  # the anchor stands for step -1
        self._known_value = anchor

    def accept(self, step: int, value: bytes) -> bool:
        """True when ``value`` proves the release of ``step`` (newer than any accepted before)."""
        distance = step - self._known_step
        if distance <= 0 or distance > MAX_CHAIN_STEPS or len(value) != VALUE_BYTES:
            return False
        link = value
        for _ in range(distance):
            link = chain_hash(link)
        if not secrets.compare_digest(link, self._known_value):
            return False
        self._known_step, self._known_value = step, value
        return True


def encode_beacon(mission_id: str, step: int, value: bytes) -> bytes:
    """The datagram announcing the release of ``step`` of ``mission_id``."""
    name = mission_id.encode()
    if not 1 <= len(name) <= MAX_MISSION_ID_BYTES:
        raise ValueError(f"mission id of {len(name)} bytes; a beacon carries 1..{MAX_MISSION_ID_BYTES}")
    if not 0 <= step < 1 << 32:
        raise ValueError(f"step {step} does not fit a beacon's u32")
    if len(value) != VALUE_BYTES:
        raise ValueError(f"a chain value is {VALUE_BYTES} bytes, not {len(value)}")
    return MAGIC + bytes((LAYOUT_VERSION, len(name))) + name + _STEP.pack(step) + value


def parse_beacon_address(text: str) -> tuple[str, int]:
    """``"IPv4:port"`` of a beacon listener or target, as ``(host, port)``; ValueError says what is wrong.

    An IPv4 address, not a name: a beacon goes to a broadcast address (127.255.255.255 on one
    host, the LAN's x.y.z.255), and an agent binding to one receives broadcasts only.
    """
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"release beacon address {text!r}: expected IPv4:PORT, e.g. 127.255.255.255:14650")
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        raise ValueError(f"release beacon address {text!r}: {host!r} is not an IPv4 address") from None
    if not 1 <= int(port) <= 65_535:
        raise ValueError(f"release beacon address {text!r}: port {port} is not in 1..65535")
    return host, int(port)


def decode_beacon(data: bytes) -> Beacon:
    """Parse a datagram; :class:`BeaconError` says what is wrong with one that is not a beacon."""
    if len(data) < 6 or data[:4] != MAGIC:
        raise BeaconError("not a release beacon (no FGRB magic)")
    if data[4] != LAYOUT_VERSION:
        raise BeaconError(f"beacon layout {data[4]}; this code reads layout {LAYOUT_VERSION}")
    size = data[5]
    if not 1 <= size <= MAX_MISSION_ID_BYTES:
        raise BeaconError(f"mission id length {size}; 1..{MAX_MISSION_ID_BYTES} allowed")
    if len(data) != 6 + size + 4 + VALUE_BYTES:
        raise BeaconError(f"beacon of {len(data)} bytes; {6 + size + 4 + VALUE_BYTES} expected")
    try:
        mission_id = data[6 : 6 + size].decode()
    except UnicodeDecodeError as exc:
        raise BeaconError(f"mission id is not UTF-8: {exc}") from None
    (step,) = _STEP.unpack_from(data, 6 + size)
    return Beacon(mission_id, step, bytes(data[10 + size :]))

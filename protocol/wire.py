"""Frame codec: a fixed 16-byte header followed by a JSON body. Sans-I/O: no sockets here.

Header, all integers big-endian::

    offset size field
    0      2    magic        b"FG" (0x46 0x47)
    2      1    version      FRAME_VERSION (1): the frame format, the same in protocol v1 and v2
    3      1    packet type  0..6; bit 7 (0x80) set = compact binary body (only 0x82, a type-2
                             status in protocol/status_binary.py's layout, a v2 capability
                             negotiated in the handshake: ``compact_status``)
    4      4    sequence     u32, per sender, +1 per frame, wraps at 2**32
    8      4    body length  u32, bytes of body that follow
    12     4    body CRC-32  u32, zlib.crc32 of the body bytes

The length is checked against the receiver's maximum *before* any body byte is buffered, so an
oversized frame costs the receiver 16 bytes. :class:`FrameDecoder` raises only
:class:`ProtocolError`; after one, the stream is out of step and the connection must be closed.

Bodies are parsed strictly (docs/protocol.md section 3): duplicate keys, NaN/Infinity and type
coercion (``"3"`` or ``3.0`` for an int, ``"yes"`` for a bool) are errors; unknown fields are
dropped, except inside commands (:data:`~protocol.packets.MUST_UNDERSTAND`).
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass

from pydantic import ValidationError

from protocol import status_binary
from protocol.packets import (
    BODY_MODELS,
    MUST_UNDERSTAND,
    PROTOCOL_VERSION,
    Body,
    PacketType,
    StatusReport,
    packet_type_of,
)
from protocol.versions import render

MAGIC = b"FG"
HEADER = struct.Struct(">2sBBIII")
HEADER_SIZE = HEADER.size  # 16
DEFAULT_MAX_BODY = 1 << 20  # 1 MiB: a 2000-waypoint survey leg is ~150 KiB
SEQ_MODULO = 1 << 32
FRAME_VERSION = 1  # the header's version byte: the frame format, unchanged by protocol v2
PRE_AUTH_MAX_BODY = 1024  # a handshake packet is well under 1 KiB; the daemon's limit before `accepted`
COMPACT = 0x80
"""Packet-type bit: the body is the compact binary form (today only type 2: ``STATUS_COMPACT``)."""
STATUS_COMPACT = COMPACT | PacketType.STATUS
_MAX_TYPE = max(PacketType)


class ProtocolError(Exception):
    """Any violation of the wire format: bad magic/version/type, size, CRC, JSON or body schema."""

    def __init__(self, message: str, *, packet_type: int | None = None) -> None:
        super().__init__(message)
        self.packet_type = packet_type


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded packet."""

    packet_type: PacketType
    seq: int
    body: Body
    compact: bool = False  # the body came in the compact binary form (type byte 0x82)


def encode(body: Body, seq: int, version: int = PROTOCOL_VERSION, *, compact: bool = False) -> bytes:
    """Serialise ``body`` into one frame with sequence number ``seq`` (taken modulo 2**32).

    ``version`` is the session's protocol version: the body is rendered for it by
    :func:`protocol.versions.render` (a version-1 peer gets only version-1 fields, because it
    rejects unknown ones).
    ``compact`` sends a status report in the binary layout (type byte 0x82); only a version-2
    session whose ``accepted`` said ``compact_status`` may use it.
    """
    if compact and version >= 2 and isinstance(body, StatusReport):
        payload = status_binary.encode(body)
        ptype = STATUS_COMPACT
    else:
        payload = render(body, version)
        ptype = packet_type_of(body)
    return (
        HEADER.pack(MAGIC, FRAME_VERSION, ptype, seq % SEQ_MODULO, len(payload), zlib.crc32(payload))
        + payload
    )


def _no_duplicate_keys(pairs: list[tuple[str, object]]) -> dict[str, object]:
    document = dict(pairs)
    if len(document) != len(pairs):  # the common case costs one C-level dict() and a length check
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise ValueError(f"duplicate key {key!r}")
            seen.add(key)
    return document


def _no_constants(name: str) -> object:
    raise ValueError(f"{name} is not JSON")


def _drop(document: dict[str, object], loc: tuple[int | str, ...]) -> None:
    target: object = document
    for part in loc[:-1]:
        target = target[part]  # type: ignore[index]
    del target[loc[-1]]  # type: ignore[attr-defined]


def decode_body(packet_type: int, payload: bytes) -> Body:
    """Validate a body for ``packet_type``; raise :class:`ProtocolError` on any problem."""
    if packet_type == STATUS_COMPACT:
        try:
            return status_binary.decode(payload)
        except status_binary.StatusBodyError as exc:
            raise ProtocolError(str(exc), packet_type=PacketType.STATUS) from None
    try:
        ptype = PacketType(packet_type)
    except ValueError:
        raise ProtocolError(f"unknown packet type {packet_type} (expected 0..6)") from None
    try:
        text = payload.decode("utf-8")
        document = json.loads(text, object_pairs_hook=_no_duplicate_keys, parse_constant=_no_constants)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError, JSONDecodeError, int digit limit
        raise ProtocolError(f"type {ptype.value} body is not UTF-8 JSON: {exc}", packet_type=ptype) from None
    if not isinstance(document, dict):
        raise ProtocolError(f"type {ptype.value} body must be a JSON object", packet_type=ptype)
    model = BODY_MODELS[ptype]
    try:
        try:
            return model.model_validate_json(text, strict=True)  # type: ignore[return-value]
        except ValidationError as exc:
            errors = exc.errors()
            protected = MUST_UNDERSTAND.get(ptype, ())
            if not all(e["type"] == "extra_forbidden" and e["loc"][0] not in protected for e in errors):
                raise
            for error in sorted(errors, key=lambda e: len(e["loc"]), reverse=True):
                _drop(document, error["loc"])  # must-ignore: an optional addition of a newer peer
            return model.model_validate_json(json.dumps(document), strict=True)  # type: ignore[return-value]
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or "body"
        raise ProtocolError(
            f"invalid type {ptype.value} ({ptype.name}) body at {where}: {first.get('msg')}",
            packet_type=ptype,
        ) from None
    except RecursionError:
        raise ProtocolError(f"type {ptype.value} body nests too deeply", packet_type=ptype) from None


class FrameDecoder:
    """Incremental decoder: feed it received bytes, iterate the complete frames."""

    def __init__(self, max_body: int = DEFAULT_MAX_BODY) -> None:
        self.max_body = max_body
        self._buffer = bytearray()
        self._failed: ProtocolError | None = None

    @property
    def pending_bytes(self) -> int:
        """Bytes received but not yet part of a complete frame."""
        return len(self._buffer)

    def feed(self, data: bytes | bytearray | memoryview) -> Iterator[Frame]:
        """Add ``data`` and yield every frame it completes."""
        if self._failed is not None:
            raise self._failed
        self._buffer += data
        while True:
            frame = self._next()
            if frame is None:
                return
            yield frame

    def split(self, data: bytes | bytearray | memoryview) -> Iterator[tuple[int, int, bytes]]:
        """Add ``data`` and yield ``(type byte, seq, body)`` of every frame it completes, CRC checked.

        The bodies are not decoded (:func:`decode_body` does that): the daemon's ingest copies a
        compact status body into its fleet table as it is (gcs/link/agents_table.py).
        """
        if self._failed is not None:
            raise self._failed
        self._buffer += data
        while True:
            raw = self._next_raw()
            if raw is None:
                return
            yield raw

    def _fail(self, message: str, packet_type: int | None = None) -> ProtocolError:
        self._failed = ProtocolError(message, packet_type=packet_type)
        self._buffer.clear()
        return self._failed

    def _next(self) -> Frame | None:
        raw = self._next_raw()
        if raw is None:
            return None
        ptype, seq, payload = raw
        try:
            body = decode_body(ptype, payload)
        except ProtocolError as exc:
            self._failed = exc
            self._buffer.clear()
            raise
        return Frame(PacketType(ptype & ~COMPACT), seq, body, ptype == STATUS_COMPACT)

    def fail(self, exc: ProtocolError) -> ProtocolError:
        """Mark the stream out of step after a body ``exc`` found outside :meth:`feed`; returns it."""
        self._failed = exc
        self._buffer.clear()
        return exc

    def _next_raw(self) -> tuple[int, int, bytes] | None:
        buf = self._buffer
        # Check what we can of the header as soon as bytes arrive, so garbage fails fast.
        if len(buf) >= 1 and buf[:2] != MAGIC[: min(2, len(buf))]:
            raise self._fail(f"bad magic {bytes(buf[:2])!r} (expected {MAGIC!r}): not a fleetgcs stream")
        if len(buf) >= 3 and buf[2] != FRAME_VERSION:
            raise self._fail(f"unsupported frame version {buf[2]} (this side speaks {FRAME_VERSION})")
        if len(buf) >= 4 and buf[3] > _MAX_TYPE and buf[3] != STATUS_COMPACT:
            raise self._fail(f"unknown packet type {buf[3]} (expected 0..6 or 0x82)", buf[3])
        if len(buf) < HEADER_SIZE:
            return None
        _, _, ptype, seq, length, crc = HEADER.unpack_from(buf)
        if length > self.max_body:
            raise self._fail(f"frame body of {length} bytes exceeds the limit of {self.max_body}", ptype)
        if len(buf) < HEADER_SIZE + length:
            return None
        payload = bytes(buf[HEADER_SIZE : HEADER_SIZE + length])
        del buf[: HEADER_SIZE + length]
        if zlib.crc32(payload) != crc:
            raise self._fail(f"type {ptype} frame seq {seq}: body CRC mismatch", ptype)
        return ptype, seq, payload


def decode_one(data: bytes, max_body: int = DEFAULT_MAX_BODY) -> Frame:
    """Decode exactly one complete frame from ``data`` (tests, tools)."""
    decoder = FrameDecoder(max_body)
    frames = list(decoder.feed(data))
    if len(frames) != 1 or decoder.pending_bytes:
        raise ProtocolError(
            f"expected exactly one complete frame, got {len(frames)} and {decoder.pending_bytes} spare bytes"
        )
    return frames[0]

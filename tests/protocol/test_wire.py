"""The frame codec: round trips, and every kind of bad input ending in ProtocolError only."""

from __future__ import annotations

import contextlib
import json
import struct
import zlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import auth
from protocol.actions import GoBy, Goto, Hold, Land, ReturnToLaunch, SetSpeed, Takeoff, Waypoint, Waypoints
from protocol.packets import (
    PROTOCOL_VERSION,
    Battery,
    Close,
    CloseReason,
    FenceCircle,
    FenceVertex,
    Geofence,
    Gps,
    PacketType,
    PerformActions,
    Position,
    RequestCid,
    ResponseCid,
    SetParameters,
    StatusReport,
    SyncSignal,
    VelocityNed,
)
from protocol.wire import (
    FRAME_VERSION,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    FrameDecoder,
    ProtocolError,
    decode_one,
    encode,
)

finite = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6)
lat = st.floats(min_value=-90, max_value=90, allow_nan=False)
lon = st.floats(min_value=-180, max_value=180, allow_nan=False)
alt = st.floats(min_value=-1000, max_value=10_000, allow_nan=False)
speed = st.none() | st.floats(min_value=0.01, max_value=100, allow_nan=False)
step = st.integers(min_value=0, max_value=1_000_000)
mission_id = st.text(min_size=1, max_size=64)

actions = st.one_of(
    st.builds(Takeoff, step=step, sync=st.booleans(), alt=st.floats(min_value=0.1, max_value=10_000)),
    st.builds(Goto, step=step, sync=st.booleans(), lat=lat, lon=lon, alt=alt, speed=speed),
    st.builds(
        GoBy, step=step, north=st.floats(-1e5, 1e5), east=st.floats(-1e5, 1e5), up=st.floats(-1e3, 1e3)
    ),
    st.builds(Land, step=step, lat=st.none() | lat, lon=st.none() | lon),
    st.builds(ReturnToLaunch, step=step),
    st.builds(Hold, step=step, seconds=st.floats(min_value=0, max_value=86_400)),
    st.builds(SetSpeed, step=step, speed=st.floats(min_value=0.01, max_value=100)),
    st.builds(
        Waypoints,
        step=step,
        points=st.lists(st.builds(Waypoint, lat=lat, lon=lon, alt=alt), min_size=1, max_size=5),
    ),
)

status_reports = st.builds(
    StatusReport,
    time=finite,
    position=st.builds(Position, lat=lat, lon=lon, alt_rel=finite, alt_amsl=finite),
    velocity=st.builds(VelocityNed, vn=finite, ve=finite, vd=finite),
    heading_deg=st.floats(min_value=0, max_value=360),
    battery=st.builds(Battery, pct=st.none() | st.floats(0, 100), voltage_v=st.none() | st.floats(0, 1000)),
    mode=st.text(max_size=32),
    armed=st.booleans(),
    landed=st.booleans(),
    gps=st.builds(Gps, fix=st.integers(0, 8), satellites=st.integers(0, 255)),
    mission_id=st.none() | mission_id,
    step=st.integers(-1, 10**6),
    queue_depth=st.integers(0, 10**6),
    exceptions=st.lists(st.text(max_size=200), max_size=5),
)

bodies = st.one_of(
    status_reports,
    st.builds(SyncSignal, mission_id=mission_id, step=step, kind=st.sampled_from(["finished", "release"])),
    st.builds(
        PerformActions,
        mission_id=mission_id,
        mode=st.sampled_from(["append", "replace"]),
        actions=st.lists(actions, max_size=6),
    ),
    st.builds(Close, reason=st.sampled_from(list(CloseReason)), message=st.text(max_size=100)),
    st.builds(
        SetParameters,
        geofence=st.none()
        | st.builds(
            Geofence,
            circle=st.none() | st.builds(FenceCircle, lat=lat, lon=lon, radius_m=st.floats(0.1, 100_000)),
            polygon=st.none() | st.lists(st.builds(FenceVertex, lat=lat, lon=lon), min_size=3, max_size=8),
        ),
    ),
    st.builds(
        RequestCid,
        identity=st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,20}", fullmatch=True),
        protocol_version=st.just(PROTOCOL_VERSION),
        client_nonce=st.just(auth.new_nonce()),
    ),
    st.builds(ResponseCid, outcome=st.just("accepted"), cid=st.integers(1, 65_535)),
)


@settings(max_examples=300, deadline=None)
@given(body=bodies, seq=st.integers(min_value=0, max_value=2**32 - 1))
def test_every_body_round_trips(body: object, seq: int) -> None:
    frame = decode_one(encode(body, seq))  # type: ignore[arg-type]
    assert frame.body == body
    assert frame.seq == seq


@settings(max_examples=100, deadline=None)
@given(body_list=st.lists(bodies, min_size=1, max_size=5), cut=st.integers(min_value=1, max_value=50))
def test_stream_split_at_any_point_decodes_the_same(body_list: list[object], cut: int) -> None:
    stream = b"".join(encode(b, i) for i, b in enumerate(body_list))  # type: ignore[arg-type]
    decoder = FrameDecoder()
    got: list[object] = []
    for start in range(0, len(stream), cut):
        got.extend(f.body for f in decoder.feed(stream[start : start + cut]))
    assert got == body_list
    assert decoder.pending_bytes == 0


@settings(max_examples=1000, deadline=None)
@given(data=st.binary(max_size=512))
def test_random_bytes_only_ever_raise_protocol_error(data: bytes) -> None:
    decoder = FrameDecoder(max_body=4096)
    with contextlib.suppress(ProtocolError):
        list(decoder.feed(data))


@settings(max_examples=500, deadline=None)
@given(ptype=st.integers(0, 6), payload=st.binary(max_size=300))
def test_valid_header_with_random_body_only_raises_protocol_error(ptype: int, payload: bytes) -> None:
    frame = HEADER.pack(MAGIC, FRAME_VERSION, ptype, 1, len(payload), zlib.crc32(payload)) + payload
    with contextlib.suppress(ProtocolError):
        decode_one(frame)


def _frame(ptype: int, payload: bytes, version: int = FRAME_VERSION, crc: int | None = None) -> bytes:
    checksum = zlib.crc32(payload) if crc is None else crc
    return HEADER.pack(MAGIC, version, ptype, 1, len(payload), checksum) + payload


def test_header_is_sixteen_bytes_big_endian() -> None:
    frame = encode(SyncSignal(mission_id="m", step=3, kind="finished"), 0x01020304)
    assert HEADER_SIZE == 16
    assert frame[:2] == b"FG" and frame[2] == 1 and frame[3] == PacketType.SYNC
    assert frame[4:8] == b"\x01\x02\x03\x04"
    (length,) = struct.unpack(">I", frame[8:12])
    assert length == len(frame) - 16
    assert json.loads(frame[16:]) == {"mission_id": "m", "step": 3, "kind": "finished"}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"GET / HTTP/1.1\r\n", "bad magic"),
        (_frame(2, b"{}", version=9), "unsupported frame version 9"),
        (_frame(7, b"{}"), "unknown packet type 7"),
        (_frame(5, b'{"mission_id":"m","step":1,"kind":"finished"}', crc=1), "CRC mismatch"),
        (_frame(5, b"\xff\xfe"), "not UTF-8 JSON"),
        (_frame(5, b"[1, 2]"), "must be a JSON object"),
        (
            _frame(5, b'{"mission_id":"m","step":-1,"kind":"finished"}'),
            r"invalid type 5 \(SYNC\) body at step",
        ),
        (_frame(5, b'{"mission_id":"m","step":1,"kind":"finished","step":2}'), "duplicate key 'step'"),
        (
            _frame(4, b'{"mission_id":"m","actions":[{"kind":"hold","step":1,"seconds":1,"x":1}]}'),
            "at actions",
        ),
        (_frame(2, b'{"time": 1, "position": 5}'), "body at position"),  # position is optional
        (_frame(4, b'{"mission_id":"m","actions":[{"kind":"teleport","step":1}]}'), "body at actions"),
        (_frame(5, b"[" * 100_000 + b"]" * 100_000), "UTF-8 JSON|nests too deeply"),
    ],
)
def test_malformed_frames_are_named(data: bytes, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        list(FrameDecoder(max_body=1 << 20).feed(data))


def test_oversized_length_is_rejected_from_the_header_alone() -> None:
    decoder = FrameDecoder(max_body=1024)
    header = HEADER.pack(MAGIC, FRAME_VERSION, 2, 1, 10_000_000, 0)
    with pytest.raises(ProtocolError, match="exceeds the limit of 1024"):
        list(decoder.feed(header))
    assert decoder.pending_bytes == 0


def test_truncated_frame_waits_then_completes() -> None:
    frame = encode(Close(reason=CloseReason.NORMAL), 5)
    decoder = FrameDecoder()
    assert list(decoder.feed(frame[:-3])) == []
    assert decoder.pending_bytes == len(frame) - 3
    (done,) = decoder.feed(frame[-3:])
    assert done.body == Close(reason=CloseReason.NORMAL)


def test_decoder_stays_failed_after_an_error() -> None:
    decoder = FrameDecoder()
    with pytest.raises(ProtocolError):
        list(decoder.feed(b"XX"))
    with pytest.raises(ProtocolError):
        list(decoder.feed(encode(Close(reason=CloseReason.NORMAL), 1)))


def test_decode_one_rejects_trailing_bytes() -> None:
    with pytest.raises(ProtocolError, match="exactly one"):
        decode_one(encode(Close(reason=CloseReason.NORMAL), 1) + b"F")


def test_nan_and_infinity_are_rejected_in_positions() -> None:
    payload = b'{"time": 1, "position": {"lat": NaN, "lon": 0, "alt_rel": 0, "alt_amsl": 0}}'
    with pytest.raises(ProtocolError, match="NaN is not JSON"):  # refused by the parser already
        decode_one(_frame(2, payload))


def test_hmac_proofs_bind_identity_and_both_nonces() -> None:
    key = bytes(range(32))
    server, client = auth.new_nonce(), auth.new_nonce()
    proof = auth.agent_proof(key, "drone-1", server, client)
    assert auth.proofs_equal(proof, auth.agent_proof(key, "drone-1", server, client))
    assert not auth.proofs_equal(proof, auth.agent_proof(key, "drone-2", server, client))
    assert not auth.proofs_equal(proof, auth.agent_proof(key, "drone-1", auth.new_nonce(), client))
    assert proof != auth.daemon_proof(key, "drone-1", client, server)
    with pytest.raises(ValueError, match="at least 16 bytes"):
        auth.parse_key("abcd")

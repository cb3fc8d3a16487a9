"""The compact binary status body: the same report as the JSON body, and bad bytes end in one error."""

from __future__ import annotations

import json
import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from protocol import status_binary
from protocol.packets import (
    Battery,
    PacketType,
    Position,
    StatusReport,
)
from protocol.wire import STATUS_COMPACT, FrameDecoder, ProtocolError, decode_body, decode_one, encode
from tests.support.status_reports import FIELDS, RAW_BODY, reports


@settings(max_examples=400, deadline=None)
@given(reports)
def test_binary_and_json_bodies_decode_to_the_same_report(report: StatusReport) -> None:
    from_json = decode_body(PacketType.STATUS, report.model_dump_json(exclude_none=True).encode())
    from_binary = decode_body(STATUS_COMPACT, status_binary.encode(report))
    assert from_binary == from_json == report
    assert from_binary.model_dump() == from_json.model_dump()  # nested models too, field by field
    frame = decode_one(encode(report, 7, compact=True))
    assert frame.compact and frame.packet_type is PacketType.STATUS and frame.seq == 7
    assert frame.body == report
    assert not decode_one(encode(report, 8)).compact


def test_a_typical_report_is_compact_and_has_no_tail() -> None:
    report = StatusReport(
        time=1.7e9,
        position=Position(lat=47.39, lon=8.54, alt_rel=12.3, alt_amsl=500.3),
        battery=Battery(pct=87.5, voltage_v=12.1, current_a=14.2),
        mode="GUIDED",
        mission_id="m-20261130-0001",
        step=3,
    )
    body = status_binary.encode(report)
    assert not body[1] & status_binary.HAS_TAIL
    assert len(body) == status_binary.FIXED_SIZE + 2 + len("GUIDED") + len("m-20261130-0001")
    assert len(body) < len(report.model_dump_json(exclude_none=True)) / 2


# --- the hand-written range checks agree with pydantic's --------------------------------------------


@settings(max_examples=500, deadline=None)
@given(**RAW_BODY)
def test_binary_accepts_exactly_what_pydantic_accepts(
    floats: list[float], fix: int, ints: tuple[int, int, int], position: bool
) -> None:
    f = dict(zip(FIELDS, floats, strict=True))
    flags = status_binary.LANDED | status_binary.AUTOPILOT_LINK
    flags |= status_binary.HAS_POSITION if position else 0
    body = status_binary.FIXED.pack(1, flags, fix, 0, *floats, ints[0], ints[1], 0, ints[2]) + b"\x00\x00"

    def none_if_nan(x: float) -> float | None:
        return None if math.isnan(x) else x

    document = {
        "time": f["time"],
        "vehicle_time": none_if_nan(f["vehicle_time"]),
        "position": {k: f[k] for k in ("lat", "lon", "alt_rel", "alt_amsl")} if position else None,
        "velocity": {"vn": f["vn"], "ve": f["ve"], "vd": f["vd"]},
        "heading_deg": f["heading"],
        "battery": {
            "pct": none_if_nan(f["pct"]),
            "voltage_v": none_if_nan(f["volts"]),
            "current_a": none_if_nan(f["amps"]),
        },
        "mode": "",
        "landed": True,
        "gps": {"fix": fix},
        "step": ints[0],
        "completed_step": ints[1],
        "waiting_sync": None if ints[2] == -1 else ints[2],
    }
    try:
        expected: StatusReport | None = StatusReport.model_validate(document)
    except ValidationError:
        expected = None
    if expected is None:
        with pytest.raises(status_binary.StatusBodyError, match=r"^compact status body"):
            status_binary.decode(body)
    else:
        assert status_binary.decode(body) == expected


# --- malformed bodies ---------------------------------------------------------------------------


def _good() -> bytes:
    return status_binary.encode(StatusReport(time=1.0, mode="AUTO", mission_id="m"))


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (b"", "shorter than"),
        (_good()[:-1], "truncated in mission_id"),
        (_good()[: status_binary.FIXED_SIZE + 3], "truncated in mode"),
        (b"\x02" + _good()[1:], "layout 2 not supported"),
        (bytes([1, 0x80]) + _good()[2:], "unknown flag bits"),
        (_good() + b"{}", "after mission_id, tail flag False"),
        (bytes([1, status_binary.HAS_TAIL]) + _good()[2:] + b"[1]", "tail must be an object"),
        (bytes([1, status_binary.HAS_TAIL]) + _good()[2:] + b"{nope", "not UTF-8 JSON"),
        (bytes([1, status_binary.HAS_TAIL]) + _good()[2:] + b'{"bogus":1}', "invalid bogus"),
        (_good()[: status_binary.FIXED_SIZE] + b"\x02\xff\xfe\x01m", "not UTF-8"),
    ],
)
def test_malformed_compact_bodies_are_one_line_protocol_errors(body: bytes, message: str) -> None:
    with pytest.raises(ProtocolError, match=message) as caught:
        decode_body(STATUS_COMPACT, body)
    assert "\n" not in str(caught.value)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_give_a_report_or_a_protocol_error(data: bytes) -> None:
    try:
        result = decode_body(STATUS_COMPACT, data)
    except ProtocolError:
        return
    assert isinstance(result, StatusReport)


def test_decoder_accepts_only_0x82_as_a_compact_type() -> None:
    frame = bytearray(encode(StatusReport(time=1.0), 1, compact=True))
    assert frame[3] == 0x82
    frame[3] = 0x83
    with pytest.raises(ProtocolError, match="unknown packet type 131"):
        list(FrameDecoder().feed(bytes(frame)))


def test_an_oversized_mission_id_rides_the_tail() -> None:
    report = StatusReport(time=1.0, mission_id="\U0001f681" * 64, step=1 << 40)  # 256 UTF-8 bytes
    body = status_binary.encode(report)
    assert body[1] & status_binary.HAS_TAIL
    tail = body[status_binary.FIXED_SIZE + 2 + len("UNKNOWN") :]
    assert json.loads(tail)["mission_id"] == report.mission_id
    assert status_binary.decode(body) == report
    assert struct.unpack_from("<i", body, 108)[0] == -1  # step's slot; the tail holds the value

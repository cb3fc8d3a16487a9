"""Write the decoder seed corpus (fuzz/corpus/decoder/): valid frames of every type plus classic breakage.

Run: python fuzz/make_corpus.py   (idempotent; the files are committed, so only rerun after a
protocol change). Each file is one fuzz case: a control byte (see fuzz_decoder.py), then bytes.
Inputs a fuzzer found crashing the decoder join the corpus once fixed (huge_integer_valueerror.bin).
"""

from __future__ import annotations

import zlib
from pathlib import Path

from protocol.actions import (
    Action,
    GoBy,
    Goto,
    Hold,
    Land,
    ReturnToLaunch,
    SetSpeed,
    Takeoff,
    Waypoint,
    Waypoints,
)
from protocol.packets import (
    PROTOCOL_VERSION,
    AgentParameters,
    Battery,
    Body,
    Capabilities,
    Close,
    CloseReason,
    FenceCircle,
    FenceVertex,
    Geofence,
    GeoPoint,
    Gps,
    PerformActions,
    Position,
    RequestCid,
    ResponseCid,
    Resume,
    SetParameters,
    StatusReport,
    SyncSignal,
    VelocityNed,
)
from protocol.wire import HEADER, MAGIC, encode

HERE = Path(__file__).resolve().parent
CORPUS = HERE / "corpus" / "decoder"

WHOLE = bytes([0x0F])  # one read of everything, CRCs as written
BYTEWISE = bytes([0x00])  # one byte per read
FIX_CRC = bytes([0x8F])  # CRCs recomputed before decoding


def raw_frame(ptype: int, body: bytes, *, version: int = PROTOCOL_VERSION, crc: int | None = None) -> bytes:
    return HEADER.pack(MAGIC, version, ptype, 1, len(body), zlib.crc32(body) if crc is None else crc) + body


def valid_frames() -> dict[str, bytes]:
    return {name: encode(body, 1) for name, body in valid_bodies().items()}


def valid_bodies() -> dict[str, Body]:
    nonce = "0123456789abcdef" * 2  # fixed, so regenerating gives the same files
    status = StatusReport(
        time=1_700_000_000.5,
        position=Position(lat=47.397742, lon=8.545594, alt_rel=12.5, alt_amsl=500.5),
        velocity=VelocityNed(vn=1.0, ve=-0.5, vd=0.1),
        heading_deg=270.0,
        battery=Battery(pct=80.0, voltage_v=15.9, current_a=12.0),
        mode="GUIDED",
        armed=True,
        landed=False,
        gps=Gps(fix=3, satellites=14),
        mission_id="m-1",
        step=2,
        completed_step=1,
        queue_depth=3,
        waiting_sync=1,
        exceptions=["battery_low: 24%; reaction rtl"],
        autopilot_link=True,
        buffered=True,
    )
    actions: list[Action] = [
        Takeoff(step=0, alt=10.0, sync=True),
        Goto(step=1, lat=47.3979, lon=8.5457, alt=10.0, speed=5.0, sync=True),
        GoBy(step=2, north=10.0, east=-5.0, up=2.0),
        Waypoints(step=3, points=[Waypoint(lat=47.398, lon=8.546, alt=12.0)] * 3, speed=4.0),
        Hold(step=4, seconds=5.0),
        SetSpeed(step=5, speed=3.0),
        Land(step=6, lat=47.3977, lon=8.5455),
        ReturnToLaunch(step=7),
    ]
    fence = Geofence(
        circle=FenceCircle(lat=47.3977, lon=8.5456, radius_m=200.0),
        polygon=[
            FenceVertex(lat=47.39, lon=8.54),
            FenceVertex(lat=47.40, lon=8.54),
            FenceVertex(lat=47.40, lon=8.55),
        ],
        max_alt_m=60.0,
        breach_action="land",
    )
    bodies: dict[str, Body] = {
        "t0_hello": RequestCid(identity="drone-1", protocol_version=1, client_nonce=nonce),
        "t0_proof": RequestCid(
            identity="drone-1",
            protocol_version=1,
            client_nonce=nonce,
            capabilities=Capabilities(vehicle_kind="vtol", max_speed_mps=20.0, autopilot="ArduPilot"),
            home=GeoPoint(lat=47.397742, lon=8.545594, alt_amsl=488.0),
            proof="ab" * 32,
            resume=Resume(mission_id="m-1", completed_step=1, waiting_step=1, queue_depth=3),
        ),
        "t1_challenge": ResponseCid(outcome="challenge", server_nonce=nonce),
        "t1_accepted": ResponseCid(
            outcome="accepted",
            cid=7,
            server_nonce=nonce,
            server_proof="cd" * 32,
            parameters=AgentParameters(status_period_s=0.5, lost_link_action="rtl", lost_link_timeout_s=15.0),
            server_time=1_700_000_000.0,
        ),
        "t1_refused": ResponseCid(outcome="refused", reason="unknown agent"),
        "t2_status": status,
        "t3_geofence": SetParameters(geofence=fence),
        "t3_clear": SetParameters(clear_geofence=True, parameters=AgentParameters(battery_low_pct=30.0)),
        "t4_replace_all_actions": PerformActions(mission_id="m-1", mode="replace", actions=actions),
        "t4_pause": PerformActions(mission_id="m-1", mode="pause", reason="collision avoidance"),
        "t5_finished": SyncSignal(mission_id="m-1", step=3, kind="finished"),
        "t5_release": SyncSignal(mission_id="m-1", step=3, kind="release"),
        "t6_close": Close(reason=CloseReason.PROTOCOL_ERROR, message="bad magic"),
    }
    return bodies


def seeds() -> dict[str, bytes]:
    frames = valid_frames()
    out = {f"valid_{name}.bin": WHOLE + frame for name, frame in frames.items()}
    out["valid_t2_status_bytewise.bin"] = BYTEWISE + frames["t2_status"]
    # The negotiated compact binary status body (type byte 0x82), with and without a JSON tail.
    status_body = valid_bodies()["t2_status"]
    assert isinstance(status_body, StatusReport)
    out["valid_t2_status_compact_tail.bin"] = WHOLE + encode(status_body, 1, compact=True)
    plain = status_body.model_copy(update={"exceptions": []})
    out["valid_t2_status_compact_bytewise.bin"] = BYTEWISE + encode(plain, 1, compact=True)
    out["valid_session_stream.bin"] = FIX_CRC + b"".join(
        frames[n] for n in ("t0_hello", "t1_challenge", "t0_proof", "t1_accepted", "t2_status", "t5_finished")
    )
    status = frames["t2_status"]
    out["truncated_header.bin"] = WHOLE + status[:10]
    out["truncated_body.bin"] = WHOLE + status[:-7]
    out["oversized_length.bin"] = WHOLE + HEADER.pack(MAGIC, 1, 2, 1, (1 << 20) + 1, 0)
    out["oversized_small_limit.bin"] = bytes([0x2F]) + raw_frame(
        4, b'{"mission_id":"m","actions":[]}' + b" " * 5000
    )
    out["wrong_version.bin"] = WHOLE + raw_frame(
        5, b'{"mission_id":"m","step":1,"kind":"finished"}', version=2
    )
    out["wrong_magic.bin"] = WHOLE + b"GF" + status[2:]
    out["http_request.bin"] = WHOLE + b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"
    out["unknown_type_7.bin"] = WHOLE + raw_frame(7, b"{}")
    out["bad_crc.bin"] = WHOLE + raw_frame(5, b'{"mission_id":"m","step":1,"kind":"finished"}', crc=1)
    out["not_json.bin"] = WHOLE + raw_frame(6, b"{nope}")
    out["not_utf8.bin"] = WHOLE + raw_frame(6, b'{"reason":"normal","message":"\xff\xfe"}')
    out["json_array.bin"] = WHOLE + raw_frame(2, b"[1,2,3]")
    out["json_nan.bin"] = WHOLE + raw_frame(6, b'{"reason":"normal","message":"x","n":NaN}')
    out["json_infinity_field.bin"] = WHOLE + raw_frame(
        5, b'{"mission_id":"m","step":1e999,"kind":"finished"}'
    )
    out["deep_nesting.bin"] = WHOLE + raw_frame(6, b'{"a":' * 5000 + b"1" + b"}" * 5000)
    out["unknown_field.bin"] = WHOLE + raw_frame(5, b'{"mission_id":"m","step":1,"kind":"finished","x":1}')
    out["wrong_body_for_type.bin"] = WHOLE + raw_frame(2, b'{"mission_id":"m","step":1,"kind":"finished"}')
    out["lone_surrogate.bin"] = WHOLE + raw_frame(6, b'{"reason":"normal","message":"a\\ud800b"}')
    out["empty_body.bin"] = WHOLE + raw_frame(6, b"")
    out["two_frames_then_garbage.bin"] = WHOLE + frames["t5_finished"] + frames["t6_close"] + b"\x00" * 20
    # Found by fuzzing: an integer over 4300 digits made json.loads raise a plain ValueError.
    huge = b'{"mission_id":"m","step":' + b"1" * 5000 + b',"kind":"finished"}'
    out["huge_integer_valueerror.bin"] = WHOLE + raw_frame(5, huge)
    return out


def main() -> int:
    CORPUS.mkdir(parents=True, exist_ok=True)
    files = seeds()
    for name, data in files.items():
        (CORPUS / name).write_bytes(data)
    print(f"{len(files)} files in {CORPUS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

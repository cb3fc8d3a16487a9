"""Status reports for the protocol and status-table tests: hypothesis strategies over every field, a
plausible report at a latitude, the daemon's ingest rule for a table row, and a v1/v2 agent join."""

from __future__ import annotations

import math
import time

from hypothesis import strategies as st

from protocol.packets import ActionFailure, Battery, Gps, Position, StatusReport, VelocityNed
from protocol.session import ClientHandshake
from protocol.stream import FramedStream, open_client

finite = st.floats(allow_nan=False, allow_infinity=False)
small = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6)
text = st.text(max_size=40)

positions = st.builds(
    Position,
    lat=st.floats(-90, 90),
    lon=st.floats(-180, 180),
    alt_rel=finite,
    alt_amsl=finite,
)
reports = st.builds(
    StatusReport,
    time=finite,
    vehicle_time=st.none() | st.floats(min_value=0.0, allow_infinity=False),
    position=st.none() | positions,
    velocity=st.builds(VelocityNed, vn=finite, ve=finite, vd=finite),
    heading_deg=st.floats(0.0, 360.0),
    battery=st.builds(
        Battery,
        pct=st.none() | st.floats(0.0, 100.0),
        voltage_v=st.none() | st.floats(0.0, 1000.0),
        current_a=st.none() | st.floats(-1000.0, 1000.0),
    ),
    mode=st.text(max_size=32),
    armed=st.booleans(),
    landed=st.booleans(),
    gps=st.builds(Gps, fix=st.integers(0, 8), satellites=st.integers(0, 255)),
    mission_id=st.none() | st.text(min_size=1, max_size=64),
    step=st.integers(-1, 1 << 40),
    completed_step=st.integers(-1, 1 << 33),
    queue_depth=st.integers(0, 1 << 33),
    waiting_sync=st.none() | st.integers(0, 1 << 33),
    paused=st.booleans(),
    exceptions=st.lists(st.text(max_size=50), max_size=3),
    autopilot_link=st.booleans(),
    buffered=st.booleans(),
    failure=st.none()
    | st.builds(ActionFailure, step=st.integers(0, 1000), kind=st.text(max_size=32), reason=text, time=small),
    failsafe=st.none() | st.text(max_size=50),
)


any_float = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from(
    [-90.5, 90.5, -180.5, 180.5, -0.1, 100.1, 360.1, 1000.1, -1000.1, math.nan]
)
FIELDS: tuple[str, ...] = ("time", "vehicle_time", "lat", "lon", "alt_rel", "alt_amsl", "vn", "ve", "vd")
FIELDS += ("heading", "pct", "volts", "amps")


RAW_BODY = {
    "floats": st.lists(any_float, min_size=13, max_size=13),
    "fix": st.integers(0, 255),
    "ints": st.tuples(st.integers(-3, 3), st.integers(-3, 3), st.integers(-3, 3)),
    "position": st.booleans(),
}
"""A fixed part's values, in and out of range (FIELDS order), for the acceptance tests."""


def report_at(lat: float, **fields: object) -> StatusReport:
    return StatusReport.model_validate(
        {
            "time": time.time(),  # the daemon refuses a time far from its clock
            "position": Position(lat=lat, lon=8.5, alt_rel=3.0, alt_amsl=503.0).model_dump(),
            "gps": {"fix": 3, "satellites": 12},
            "mode": "GUIDED",
            **fields,
        }
    )


async def join(port: int, key: str, identity: str, *, v1: bool) -> FramedStream:
    handshake = ClientHandshake(
        identity, bytes.fromhex(key), versions=[1] if v1 else [1, 2], compact_status=not v1
    )
    stream, accepted = await open_client("127.0.0.1", port, handshake)
    assert accepted.compact_status is (not v1) and accepted.version == (1 if v1 else 2)
    return stream

"""Pure helpers of the backends and the factory (no simulator needed)."""

from __future__ import annotations

import pytest

from agent.autopilot.base import Autopilot
from agent.autopilot.factory import create_autopilot
from agent.autopilot.mavlink_backend import MavlinkAutopilot, decode_mode
from agent.autopilot.mavlink_link import mavlink, parse_connection
from agent.autopilot.mavsdk_backend import MavsdkAutopilot, to_mavsdk_url


@pytest.mark.parametrize(
    ("connection", "expected"),
    [
        ("/dev/ttyAMA0:921600", ("/dev/ttyAMA0", 921600)),
        ("/dev/serial0,921600", ("/dev/serial0", 921600)),
        ("serial:/dev/ttyUSB0:57600", ("/dev/ttyUSB0", 57600)),
        ("/dev/ttyACM0", ("/dev/ttyACM0", 57600)),
        ("COM3:115200", ("COM3", 115200)),
        ("ttyUSB0:57600", ("/dev/ttyUSB0", 57600)),  # without /dev/: still the serial device
        ("serial0,921600", ("/dev/serial0", 921600)),
        ("ttyAMA0", ("/dev/ttyAMA0", 57600)),
        ("udpin:0.0.0.0:14550", ("udpin:0.0.0.0:14550", None)),
        ("udpout:10.0.0.2:14550", ("udpout:10.0.0.2:14550", None)),
        ("tcp:127.0.0.1:5760", ("tcp:127.0.0.1:5760", None)),
    ],
)
def test_parse_connection(connection: str, expected: tuple[str, int | None]) -> None:
    assert parse_connection(connection) == expected


@pytest.mark.parametrize(
    ("connection", "url"),
    [
        ("udp://:14540", "udpin://0.0.0.0:14540"),
        ("tcp://127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
        ("tcp:127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
        ("udpin:0.0.0.0:14540", "udpin://0.0.0.0:14540"),
        ("udpout:10.0.0.2:14540", "udpout://10.0.0.2:14540"),
        ("/dev/ttyAMA0:921600", "serial:///dev/ttyAMA0:921600"),
        ("/dev/serial0,921600", "serial:///dev/serial0:921600"),
        ("udpin://0.0.0.0:14540", "udpin://0.0.0.0:14540"),
        ("serial:///dev/ttyUSB0:57600", "serial:///dev/ttyUSB0:57600"),
    ],
)
def test_mavsdk_urls(connection: str, url: str) -> None:
    assert to_mavsdk_url(connection) == url


def test_decode_ardupilot_copter_modes() -> None:
    custom = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    quad = mavlink.MAV_TYPE_QUADROTOR
    ap = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert decode_mode(ap, quad, custom, 4) == "GUIDED"
    assert decode_mode(ap, quad, custom, 17) == "BRAKE"
    assert decode_mode(ap, quad, custom, 6) == "RTL"
    assert decode_mode(ap, quad, custom | mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 3) == "AUTO"
    assert decode_mode(ap, quad, custom, 99) == "MODE(99)"
    assert decode_mode(ap, quad, 0, 4) == "UNKNOWN"


@pytest.mark.parametrize(
    ("main", "sub", "name"),
    [
        (4, 3, "LOITER"),
        (4, 4, "AUTO"),
        (4, 5, "RTL"),
        (4, 6, "LAND"),
        (4, 2, "TAKEOFF"),
        (3, 0, "POSCTL"),
        (6, 0, "OFFBOARD"),
        (1, 0, "MANUAL"),
    ],
)
def test_decode_px4_modes(main: int, sub: int, name: str) -> None:
    custom = (main << 16) | (sub << 24)
    assert decode_mode(mavlink.MAV_AUTOPILOT_PX4, mavlink.MAV_TYPE_QUADROTOR, 1, custom) == name


def test_factory_builds_each_backend_without_io() -> None:
    ap = create_autopilot("mavlink", "tcp:127.0.0.1:5760", telemetry_hz=5.0)
    assert isinstance(ap, MavlinkAutopilot) and ap.telemetry_hz == 5.0
    assert isinstance(create_autopilot("mavsdk", "udpin://0.0.0.0:14540"), MavsdkAutopilot)
    memory = create_autopilot("memory", "")
    assert isinstance(memory, Autopilot)
    assert type(memory).__name__ == "MemoryAutopilot"
    with pytest.raises(ValueError, match="unknown autopilot backend"):
        create_autopilot("dronekit", "")


def test_constructing_a_backend_does_not_touch_the_link() -> None:
    ap = MavlinkAutopilot("/dev/does-not-exist:921600")
    tel = ap.telemetry()
    assert tel.mode == "UNKNOWN" and tel.last_heartbeat_monotonic == 0.0 and tel.status_texts == []


async def test_memory_autopilot_lands_at_a_given_position() -> None:
    """A land at a position flies there, then descends and disarms (it used to hover there for good:
    the target's altitude pulled it back up every step, so missions hit their 120 s step timeout)."""
    from agent.autopilot.memory import MemoryAutopilot
    from protocol.geo import distance_m, offset_latlon

    ap = MemoryAutopilot()  # not connected: the kinematics are stepped by hand, no wall clock
    await ap.arm()
    await ap.takeoff(10.0)
    for _ in range(100):
        ap._advance(0.1)
    assert ap.telemetry().alt_rel == pytest.approx(10.0)
    lat, lon = offset_latlon(ap.telemetry().lat, ap.telemetry().lon, 8.0, -6.0)
    await ap.land(lat, lon)
    for _ in range(200):  # 20 s of vehicle time: 2 s to the point, 4 s down
        ap._advance(0.1)
        if ap.telemetry().landed:
            break
    t = ap.telemetry()
    assert t.landed and not t.armed, f"still at {t.alt_rel:.2f} m"
    assert distance_m(t.lat, t.lon, lat, lon) < 0.1

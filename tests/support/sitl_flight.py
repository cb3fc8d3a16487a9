"""Driving our simulator by hand, shared by the sitl tests: a SimVehicle stepped directly into the air and
sent somewhere, and a PX4-personality ground station's commands (arm, take off, reposition, wait for a
mode or a STATUSTEXT), as real PX4 v1.16 answers them (../shared/notes/px4-behaviour.md)."""

from __future__ import annotations

import math
import time
from typing import Any

from sitl.dialect import mavlink as mav
from sitl.vehicle import GUIDED, SimVehicle
from tests.sitl.conftest import HOME, Gcs, mavlink, offset

DT = 0.02


def flying_vehicle(seed: int = 1, speed_cms: float = 500, **kw: object) -> SimVehicle:
    v = SimVehicle(0, HOME, seed=seed, prearm_delay_s=0.0, params={"WPNAV_SPEED": speed_cms}, **kw)  # type: ignore[arg-type]
    v.step(DT)
    assert v.set_mode(GUIDED)
    assert v.arm() == (True, "")
    v.handle(mav.MAVLink_command_long_message(1, 1, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 10), 0.0)
    for _ in range(2000):
        v.step(DT)
        if v.takeoff_alt is None:
            break
    assert not v.landed and v.state.alt_rel > 9.5
    return v


def goto(v: SimVehicle, north: float, east: float, alt: float = 10.0) -> None:
    st = v.state
    lat, lon = offset(st.home_lat, st.home_lon, north, east)
    v.handle(
        mav.MAVLink_set_position_target_global_int_message(
            0, 1, 1, 6, 0x0DF8, round(lat * 1e7), round(lon * 1e7), alt, 0, 0, 0, 0, 0, 0, 0, 0
        ),
        0.0,
    )


ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED
FAILED = mavlink.MAV_RESULT_FAILED
HOLD = (4, 3)
TAKEOFF = (4, 2)
NAN = math.nan
INT32_MAX = 0x7FFFFFFF


def px4_mode(hb: Any) -> tuple[int, int]:
    return (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF


def armed(hb: Any) -> bool:
    return bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def set_px4_mode(g: Gcs, main: int, sub: int = 0) -> int:
    return g.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)


def wait_mode(g: Gcs, mode: tuple[int, int], timeout: float = 5.0) -> Any:
    return g.heartbeat_msg(lambda m: px4_mode(m) == mode, timeout)


def arm(g: Gcs, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    for _ in range(500):
        if g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED:
            return
        assert time.monotonic() < deadline, f"could not arm; texts {g.texts[-3:]}"
        time.sleep(0.05)


def takeoff(g: Gcs, alt_rel: float, timeout: float = 15.0) -> Any:
    """Arm in Hold, NAV_TAKEOFF to home + ``alt_rel`` AMSL, wait until within 0.5 m."""
    arm(g)
    r = g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN, HOME[2] + alt_rel)
    assert r == ACCEPTED
    return g.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > (alt_rel - 0.5) * 1000, timeout)


def reposition(g: Gcs, lat: float, lon: float, alt_amsl: float, speed: float = -1.0, flags: int = 1) -> int:
    return g.command_int(
        mavlink.MAV_CMD_DO_REPOSITION,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,  # PX4 ignores the frame: z is AMSL anyway
        speed,
        flags,
        round(lat * 1e7),
        round(lon * 1e7),
        alt_amsl,
    )


def saw(g: Gcs, text: str, timeout: float = 5.0) -> None:
    """A STATUSTEXT containing ``text`` arrived (already, e.g. before an ACK, or within ``timeout``)."""
    if not any(text in t for t in g.texts):
        g.wait("STATUSTEXT", lambda m: text in m.text, timeout)


def speed(m: Any) -> float:
    return math.hypot(m.vx, m.vy) / 100.0

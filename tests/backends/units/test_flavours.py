"""The autopilot flavours (agent/autopilot/flavours): pure, no vehicle needed.

Each rule here was measured on real PX4 v1.16 SITL and ArduCopter SITL (docs/autopilot-backends.md);
the real-vehicle scenarios are in tests/px4 and tests/ardupilot.
"""

from __future__ import annotations

import math
import struct

import pytest

from agent.autopilot.base import FenceCircle, FenceSpec, Telemetry
from agent.autopilot.flavours import ARDUPILOT, PX4, ArduPilotFlavour, Px4Flavour, flavour_for
from agent.autopilot.flavours.base import RETURN_ALT_FLOOR_M, ShownMode
from agent.autopilot.flavours.px4 import PX4_SET
from agent.autopilot.mavlink_link import mavlink

QUAD = mavlink.MAV_TYPE_QUADROTOR


def _tel(**kw: float | bool | None) -> Telemetry:
    base: dict[str, float | bool | None] = dict(lat=47.3977, lon=8.5456, alt_rel=12.0, alt_amsl=501.4)
    base.update(home_alt_amsl=489.4, armed=True, landed=False)
    base.update(kw)
    return Telemetry(**base)  # type: ignore[arg-type]


def test_flavour_from_the_heartbeat_autopilot_field() -> None:
    assert isinstance(flavour_for(mavlink.MAV_AUTOPILOT_PX4), Px4Flavour)
    assert isinstance(flavour_for(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA), ArduPilotFlavour)
    # Generic MAVLink autopilots and "no heartbeat yet" follow ArduPilot's conventions.
    assert flavour_for(mavlink.MAV_AUTOPILOT_GENERIC) is ARDUPILOT
    assert flavour_for(None) is ARDUPILOT


@pytest.mark.parametrize("name", sorted(PX4_SET))
def test_px4_mode_encoding_round_trips(name: str) -> None:
    params, custom = PX4.mode_command(name, QUAD)
    assert params[0] == mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert custom == (int(params[1]) << 16) | (int(params[2]) << 24)
    decoded = PX4.decode_mode(QUAD, 1, custom)
    aliases = {"GUIDED": "LOITER", "BRAKE": "LOITER", "HOLD": "LOITER", "MISSION": "AUTO"}
    assert decoded == aliases.get(name, name)


def test_ardupilot_mode_encoding_round_trips() -> None:
    for name, number in (("GUIDED", 4), ("BRAKE", 17), ("RTL", 6), ("LAND", 9), ("LOITER", 5)):
        params, custom = ARDUPILOT.mode_command(name, QUAD)
        assert custom == number and params == (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number)
        assert ARDUPILOT.decode_mode(QUAD, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom) == name
    with pytest.raises(KeyError):
        PX4.mode_command("SMART_RTL", QUAD)


def test_takeoff_altitude_is_amsl_on_px4_and_above_home_on_ardupilot() -> None:
    tel = _tel()
    p = PX4.takeoff_params(10.0, tel)
    assert p[6] == pytest.approx(499.4)  # home 489.4 + 10: "10" alone stays near the ground
    assert (p[4], p[5]) == (tel.lat, tel.lon) and math.isnan(p[3])
    assert ARDUPILOT.takeoff_params(10.0, tel) == (0, 0, 0, 0, 0, 0, 10.0)
    # No home yet: AMSL minus height above home.
    assert PX4.takeoff_params(10.0, _tel(home_alt_amsl=None))[6] == pytest.approx(499.4)
    # On the ground PX4 is about to take its home where it stands (it does at arming): the last
    # flight's home, 0.7 m below, would leave it at 9.3 m above the new one.
    ground = _tel(alt_rel=0.7, alt_amsl=490.1, landed=True)
    assert PX4.takeoff_params(10.0, ground)[6] == pytest.approx(500.1)


def test_px4_reposition_carries_the_speed() -> None:
    p = PX4.reposition_params(47.1, 8.2, 500.0, 3.0)
    assert p[0] == 3.0  # param1: DO_CHANGE_SPEED could reach a drone still in AUTO.TAKEOFF
    assert p[1] == mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE  # 0 gives UNSUPPORTED
    assert p[4:] == (47.1, 8.2, 500.0) and math.isnan(p[3])
    assert PX4.reposition_params(47.1, 8.2, 500.0, None)[0] == -1.0  # PX4's cruise speed
    with pytest.raises(NotImplementedError):
        ARDUPILOT.reposition_params(47.1, 8.2, 500.0, 3.0)


def test_hold_is_px4s_pause_and_a_mode_on_ardupilot() -> None:
    """PX4: DO_REPOSITION with NaN position, altitude and yaw is its pause (brake, hold where it stops);
    any finite one of them would keep flying the leg's setpoint (PX4 navigator_main.cpp)."""
    pause = PX4.pause_params()
    assert pause is not None and pause[1] == mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE
    assert all(math.isnan(v) for v in pause[3:7])
    assert ARDUPILOT.pause_params() is None
    assert ARDUPILOT.hold_modes == ("BRAKE", "LOITER")
    assert PX4.guided_mode is None and ARDUPILOT.guided_mode == "GUIDED"


def test_speed_change_modes() -> None:
    assert ARDUPILOT.speed_accepted_in("GUIDED") and not ARDUPILOT.speed_accepted_in("BRAKE")
    assert PX4.speed_accepted_in("LOITER")


def test_return_altitude_parameter_and_default() -> None:
    assert (ARDUPILOT.return_alt_param, ARDUPILOT.return_alt_value(16.0)) == ("RTL_ALT", 1600.0)
    assert (PX4.return_alt_param, PX4.return_alt_value(16.0)) == ("RTL_RETURN_ALT", 16.0)
    # PX4 would climb every drone to RTL_RETURN_ALT (30 m): return at the current height instead.
    assert PX4.default_return_alt(_tel(alt_rel=18.26)) == 18.3
    assert PX4.default_return_alt(_tel(alt_rel=1.0)) == RETURN_ALT_FLOOR_M
    assert ARDUPILOT.default_return_alt(_tel()) is None  # keeps RTL_ALT


def test_fence_parameters_per_flavour() -> None:
    fence = FenceSpec(circle=FenceCircle(47.0, 8.0, 100.0), max_alt_m=40.0, breach_action="land")
    assert ARDUPILOT.fence_params(fence, True) == [
        ("FENCE_ALT_MAX", 40.0),
        ("FENCE_ACTION", 2),
        ("FENCE_TYPE", 5),
        ("FENCE_ENABLE", 1),
    ]
    assert PX4.fence_params(fence, True) == [("GF_ACTION", 5), ("GF_MAX_VER_DIST", 40.0)]
    assert PX4.fence_params(FenceSpec(breach_action="hold"), False) == [("GF_ACTION", 2)]
    with pytest.raises(ValueError, match="breach action"):
        PX4.fence_params(FenceSpec(breach_action="explode"), False)


def test_px4_integer_parameters_travel_bytewise() -> None:
    int32, real32 = mavlink.MAV_PARAM_TYPE_INT32, mavlink.MAV_PARAM_TYPE_REAL32
    wire_one = struct.unpack("<f", struct.pack("<i", 1))[0]  # MAV_SYS_ID = 1 arrives as 1.4e-45
    assert PX4.decode_param(wire_one, int32) == 1.0
    assert PX4.encode_param(3, int32) == struct.unpack("<f", struct.pack("<i", 3))[0]
    assert PX4.decode_param(PX4.encode_param(-7, int32), int32) == -7.0
    assert PX4.encode_param(42.5, real32) == 42.5 and PX4.decode_param(42.5, real32) == 42.5
    # ArduPilot casts: the float is the value.
    assert ARDUPILOT.encode_param(3, int32) == 3.0 and ARDUPILOT.decode_param(3.0, int32) == 3.0


def test_px4_mode_shown_tells_a_leg_from_a_hold() -> None:
    shown = ShownMode()
    assert shown.leg(PX4, True) is None  # no heartbeat yet
    assert shown.from_heartbeat(PX4, "TAKEOFF") == "TAKEOFF"
    assert shown.leg(PX4, True) == "TAKEOFF"
    # A heartbeat sent before the reposition took effect (no mode change) keeps the leg.
    assert shown.from_heartbeat(PX4, "TAKEOFF") == "TAKEOFF"
    assert shown.from_heartbeat(PX4, "LOITER") == "GUIDED"
    assert shown.leg(PX4, False) == "LOITER"  # held
    assert shown.leg(PX4, True) == "GUIDED"
    assert shown.from_heartbeat(PX4, "RTL") == "RTL"  # the vehicle left Hold: the leg is over
    assert shown.from_heartbeat(PX4, "LOITER") == "LOITER"
    ardu = ShownMode()
    ardu.from_heartbeat(ARDUPILOT, "LOITER")
    assert ardu.leg(ARDUPILOT, True) == "LOITER"  # ArduPilot shows the vehicle's mode as it is

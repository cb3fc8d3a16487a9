"""The PX4 personality (``FleetConfig(flavour="px4")``, ``sitl run --flavour px4``) behaves as the real PX4
v1.16 SITL does toward a pymavlink ground station (../shared/notes/px4-behaviour.md, probes on the real
binary). Whatever it lets through that real PX4 refuses is a bug: each test pins one such behaviour.
"""

from __future__ import annotations

import socket
import struct
import subprocess
import sys
from collections.abc import Callable
from typing import Any

import pytest

from sitl.fleet import SimFleet
from tests.sitl.conftest import HOME, Gcs, dist_m, mavlink, offset
from tests.support.sitl_flight import (
    ACCEPTED,
    FAILED,
    HOLD,
    NAN,
    REJECTED,
    TAKEOFF,
    UNSUPPORTED,
    arm,
    armed,
    px4_mode,
    reposition,
    saw,
    set_px4_mode,
    speed,
    takeoff,
    wait_mode,
)


def test_heartbeat_is_px4_and_boots_in_hold(px4: Any) -> None:
    _fleet, g = px4()
    hb = g.heartbeat_msg()
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert px4_mode(hb) == HOLD and hb.custom_mode == (4 << 16) | (3 << 24)
    assert not armed(hb)
    # PX4's API link streams telemetry unasked
    types = {m.get_type() for m in g.drain(0.4)}
    assert {"GLOBAL_POSITION_INT", "SYS_STATUS", "EXTENDED_SYS_STATE", "VFR_HUD"} <= types


def test_set_mode_takes_main_and_sub_and_ardupilot_numbers_mean_px4_modes(px4: Any) -> None:
    _fleet, g = px4()
    g.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK, 15)
    # disarmed, PX4 takes any mode and shows it (probed: MANUAL, Mission without a mission, Return, Land)
    assert set_px4_mode(g, 4) == ACCEPTED  # ArduCopter GUIDED (4) = main AUTO, sub 0 = Mission
    wait_mode(g, (4, 4))
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == REJECTED  # no mission to fly
    for mode in ((1, 0), (4, 5), (4, 6)):
        assert set_px4_mode(g, *mode) == ACCEPTED
        wait_mode(g, mode)
    assert g.command(mavlink.MAV_CMD_MISSION_START, 0, 0) == mavlink.MAV_RESULT_DENIED
    assert g.command(mavlink.MAV_CMD_CONDITION_YAW, 90, 10, 1) == UNSUPPORTED
    assert set_px4_mode(g, 4, 3) == ACCEPTED
    wait_mode(g, HOLD)
    # airborne: what cannot run is ACCEPTED, then refused (STATUSTEXT), and the mode stays
    takeoff(g, 3.0)
    for main, word in ((1, "Manual"), (2, "Altitude"), (3, "Position"), (7, "Stabilized"), (4, "Mission")):
        g.texts.clear()
        assert set_px4_mode(g, main) == ACCEPTED
        saw(g, f"Switching to {word} is currently not available")
        assert px4_mode(g.heartbeat_msg()) == HOLD
    assert set_px4_mode(g, 6) == ACCEPTED  # OFFBOARD without a setpoint stream
    saw(g, "Offboard is currently not available")
    assert set_px4_mode(g, 9) == ACCEPTED  # ArduCopter LAND (9): no such PX4 main mode, nothing happens
    assert px4_mode(g.heartbeat_msg()) == HOLD
    assert set_px4_mode(g, 4, 77) == REJECTED


def test_arming_refused_until_prearm_then_auto_disarm_after_preflight_timeout(px4: Any) -> None:
    _fleet, g = px4(prearm_delay_s=5.0, speedup=5.0)
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == REJECTED
    saw(g, "Arming denied")
    st = g.wait("SYS_STATUS")
    assert not st.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    g.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK, 15)
    arm(g)
    t_arm = g.wait("GLOBAL_POSITION_INT", timeout=3).time_boot_ms
    hb = g.heartbeat_msg(lambda m: not armed(m), timeout=6)
    t_dis = g.wait("GLOBAL_POSITION_INT", timeout=3).time_boot_ms
    assert hb is not None
    assert 9.0 <= (t_dis - t_arm) / 1000 <= 12.5  # COM_DISARM_PRFLT 10 s (sim time)


def test_takeoff_amsl_nan_and_relative_altitude(px4: Any) -> None:
    _fleet, g = px4()
    g.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK, 15)
    # ArduPilot-style relative "10": below the ground AMSL, "Already higher", stays on the ground in Hold
    assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN, 10.0) == ACCEPTED
    saw(g, "Already higher than takeoff altitude")
    arm(g)
    lows = [m.relative_alt for m in g.drain(0.3) if m.get_type() == "GLOBAL_POSITION_INT"]
    assert lows and max(lows) < 500
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == ACCEPTED
    # sent while disarmed: AUTO.TAKEOFF at once, arming climbs to MIS_TAKEOFF_ALT 2.5 m, then Hold
    assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN, NAN) == ACCEPTED
    wait_mode(g, TAKEOFF)
    arm(g)
    g.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 1500, 5)
    wait_mode(g, HOLD)
    top = max(m.relative_alt for m in g.drain(0.5) if m.get_type() == "GLOBAL_POSITION_INT")
    assert 2000 < top < 3000
    # an AMSL altitude climbs there (MPC_TKO_SPEED 1.5 m/s)
    assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN, HOME[2] + 8.0) == ACCEPTED
    wait_mode(g, TAKEOFF)
    climb = [-m.vz / 100 for m in g.drain(0.3) if m.get_type() == "GLOBAL_POSITION_INT"]
    assert climb and max(climb) <= 1.6
    g.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 7500, 10)


def test_disarm_refused_in_the_air_and_disarm_after_landing(px4: Any) -> None:
    _fleet, g = px4()
    takeoff(g, 5.0)
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == REJECTED
    assert g.command(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
    wait_mode(g, (4, 6))
    g.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND, 10)
    t_land = g.wait("GLOBAL_POSITION_INT").time_boot_ms
    saw(g, "Disarmed by landing", 5)
    t_dis = g.wait("GLOBAL_POSITION_INT").time_boot_ms
    assert 1.0 <= (t_dis - t_land) / 1000 <= 3.5  # COM_DISARM_LAND 2 s
    assert px4_mode(g.heartbeat_msg(lambda m: not armed(m))) == HOLD


def test_reposition_rules_speed_and_stop(px4: Any) -> None:
    fleet, g = px4()
    north = offset(HOME[0], HOME[1], 60.0, 0.0)
    # disarmed: accepted (Hold), nothing flies
    assert reposition(g, *north, HOME[2] + 10.0) == ACCEPTED
    takeoff(g, 5.0)
    # COMMAND_INT param2 = 0: UNSUPPORTED
    assert reposition(g, *north, HOME[2] + 10.0, flags=0) == UNSUPPORTED
    # z is AMSL whatever the frame; flown in Hold at MPC_XY_CRUISE 5 m/s
    assert reposition(g, *north, HOME[2] + 10.0) == ACCEPTED
    msgs = [m for m in g.drain(0.6) if m.get_type() == "GLOBAL_POSITION_INT"]
    assert max(speed(m) for m in msgs) > 4.0 and max(speed(m) for m in msgs) <= 5.3
    assert px4_mode(g.heartbeat_msg()) == HOLD
    g.wait("GLOBAL_POSITION_INT", lambda m: 9000 < m.relative_alt < 11000, 5)
    # a reposition to the current position stops the drone (PX4 hold), braking as PX4 does: from
    # 4 m/s below 0.5 m/s within 3 s, not sooner than 2 s (real PX4: 4.5 m/s, 6.9 m, about 3 s)
    assert reposition(g, *offset(HOME[0], HOME[1], 200.0, 0.0), HOME[2] + 10.0, speed=4.0) == ACCEPTED
    g.wait("GLOBAL_POSITION_INT", lambda m: speed(m) > 3.9, 5)
    here = g.wait("GLOBAL_POSITION_INT")
    assert reposition(g, here.lat / 1e7, here.lon / 1e7, here.alt / 1000) == ACCEPTED
    t0 = g.wait("GLOBAL_POSITION_INT").time_boot_ms
    slow = g.wait("GLOBAL_POSITION_INT", lambda m: speed(m) < 0.5, 5)
    assert 2.0 < (slow.time_boot_ms - t0) / 1000 < 3.0
    # param1 speed, and DO_CHANGE_SPEED kept for the repositions that give none (until a mode change)
    assert reposition(g, *north, HOME[2] + 10.0, speed=2.0) == ACCEPTED
    g.drain(0.3)
    assert max(speed(m) for m in g.drain(0.3) if m.get_type() == "GLOBAL_POSITION_INT") <= 2.1
    assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 3.0, -1) == ACCEPTED
    assert reposition(g, HOME[0], HOME[1], HOME[2] + 10.0) == ACCEPTED
    g.drain(0.4)
    top = max(speed(m) for m in g.drain(0.3) if m.get_type() == "GLOBAL_POSITION_INT")
    assert 2.5 < top <= 3.1
    assert fleet.vehicle(0).state.mode == "AUTO.LOITER"


def test_change_speed_during_takeoff_is_lost_when_hold_takes_over(px4: Any) -> None:
    """Issue 23: a DO_CHANGE_SPEED that reaches a drone still in AUTO.TAKEOFF is lost (PX4 resets the
    cruise speed on the mode change to Hold): the next reposition without a speed flies MPC_XY_CRUISE."""
    _fleet, g = px4(speedup=5.0)  # the speed must reach the drone during its 5 s (sim) climb
    arm(g)
    assert g.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, NAN, NAN, NAN, HOME[2] + 8.0) == ACCEPTED
    wait_mode(g, TAKEOFF)
    assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 2.0, -1) == ACCEPTED
    wait_mode(g, HOLD, timeout=10)
    assert reposition(g, *offset(HOME[0], HOME[1], 80.0, 0.0), HOME[2] + 8.0) == ACCEPTED
    top = max(speed(m) for m in g.drain(2.0) if m.get_type() == "GLOBAL_POSITION_INT")
    assert top > 4.5, f"flew {top:.1f} m/s: the take-off's speed survived into Hold"


def test_pause_continue_unsupported_and_change_speed_accepted_on_the_ground(px4: Any) -> None:
    _fleet, g = px4()
    assert g.command(mavlink.MAV_CMD_DO_PAUSE_CONTINUE, 0) == UNSUPPORTED
    assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 3.0, -1) == ACCEPTED
    interval = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert g.command(interval, mavlink.MAVLINK_MSG_ID_MISSION_CURRENT, 1e6) == FAILED  # PX4 refuses it
    assert g.command(interval, mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, 1e5) == ACCEPTED


def test_position_targets_only_in_offboard(px4: Any) -> None:
    _fleet, g = px4(speedup=1.0)  # COM_OF_LOSS_T is 1 s of sim time: real time lets a busy test stream
    takeoff(g, 3.0)
    target = offset(HOME[0], HOME[1], 20.0, 0.0)
    g.goto(*target, 3.0)  # in Hold: silently ignored
    assert max(speed(m) for m in g.drain(1.0) if m.get_type() == "GLOBAL_POSITION_INT") < 0.5

    def stream(seconds: float) -> list[Any]:
        out: list[Any] = []
        for _ in range(int(seconds / 0.02)):
            g.goto(*target, 3.0)
            out += g.drain(0.02)
        return out

    stream(0.1)  # setpoints first, then OFFBOARD: flown
    assert set_px4_mode(g, 6) == ACCEPTED
    msgs = stream(2.5)
    assert any(m.get_type() == "HEARTBEAT" and px4_mode(m) == (6, 0) for m in msgs)
    assert max(speed(m) for m in msgs if m.get_type() == "GLOBAL_POSITION_INT") > 1.0
    # the stream stops: COM_OF_LOSS_T 1 s, failsafe, Position mode
    saw(g, "Failsafe activated", 5)
    wait_mode(g, (3, 0))


def test_rtl_climbs_to_return_alt_returns_and_lands(px4: Any) -> None:
    fleet, g = px4(speedup=40.0)
    takeoff(g, 6.0)
    assert reposition(g, *offset(HOME[0], HOME[1], 40.0, 0.0), HOME[2] + 6.0, speed=5.0) == ACCEPTED
    g.wait("GLOBAL_POSITION_INT", lambda m: dist_m(HOME[0], HOME[1], m.lat / 1e7, m.lon / 1e7) > 39, 10)
    assert g.command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH) == ACCEPTED
    wait_mode(g, (4, 5))
    top = g.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 29_000, 10)
    assert dist_m(HOME[0], HOME[1], top.lat / 1e7, top.lon / 1e7) > 35  # climbs before returning
    g.heartbeat_msg(lambda m: not armed(m), timeout=20)
    st = fleet.vehicle(0).state
    assert dist_m(HOME[0], HOME[1], st.lat, st.lon) < 2.0 and st.landed
    assert st.mode == "AUTO.LOITER"


def test_integer_params_are_bytewise_both_ways(px4: Any) -> None:
    fleet, g = px4()
    g.m.mav.param_request_read_send(1, 1, b"MAV_SYS_ID", -1)
    pv = g.wait("PARAM_VALUE", lambda m: m.param_id == "MAV_SYS_ID")
    assert pv.param_type == mavlink.MAV_PARAM_TYPE_INT32
    assert struct.unpack("<i", struct.pack("<f", pv.param_value))[0] == 1
    assert pv.param_value < 1e-40  # 1.4e-45, not 1.0
    g.m.mav.param_request_read_send(1, 1, b"MPC_XY_CRUISE", -1)
    assert g.wait("PARAM_VALUE", lambda m: m.param_id == "MPC_XY_CRUISE").param_value == pytest.approx(5.0)
    # PARAM_SET of an INT32 takes the bytes: a cast 2.0 sets 1073741824, as on real PX4
    g.m.mav.param_set_send(1, 1, b"NAV_DLL_ACT", 2.0, mavlink.MAV_PARAM_TYPE_INT32)
    pv = g.wait("PARAM_VALUE", lambda m: m.param_id == "NAV_DLL_ACT")
    assert struct.unpack("<i", struct.pack("<f", pv.param_value))[0] == 1073741824
    wire2 = struct.unpack("<f", struct.pack("<i", 2))[0]
    g.m.mav.param_set_send(1, 1, b"NAV_DLL_ACT", wire2, mavlink.MAV_PARAM_TYPE_INT32)
    g.wait("PARAM_VALUE", lambda m: m.param_id == "NAV_DLL_ACT" and m.param_value == wire2)
    assert fleet.vehicle(0).px4_params["NAV_DLL_ACT"] == 2
    # wrong type or unknown name: no answer; ArduCopter names do not exist
    g.m.mav.param_set_send(1, 1, b"GF_ACTION", 3.0, mavlink.MAV_PARAM_TYPE_REAL32)
    g.m.mav.param_set_send(1, 1, b"RTL_ALT", 2000.0, mavlink.MAV_PARAM_TYPE_REAL32)
    assert not [m for m in g.drain(0.3) if m.get_type() == "PARAM_VALUE"]
    assert fleet.vehicle(0).px4_params["GF_ACTION"] == 2
    # PX4 parameters drive the flight: MPC_XY_CRUISE
    g.m.mav.param_set_send(1, 1, b"MPC_XY_CRUISE", 3.0, mavlink.MAV_PARAM_TYPE_REAL32)
    g.wait("PARAM_VALUE", lambda m: m.param_id == "MPC_XY_CRUISE")
    assert fleet.vehicle(0).params["WPNAV_SPEED"] == pytest.approx(300.0)


def test_mission_upload_quirks_and_repeated_item_reached(px4: Any) -> None:
    _fleet, g = px4()
    home = (round(HOME[0] * 1e7), round(HOME[1] * 1e7))

    def upload(items: list[tuple[int, int, int, int, float]]) -> list[tuple[str, int]]:
        g.m.mav.mission_count_send(1, 1, len(items), 0)
        seen: list[tuple[str, int]] = []
        for _ in range(len(items) + 1):
            r = g.wait(("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"))
            if r.get_type() == "MISSION_ACK":
                seen.append(("ACK", r.type))
                return seen
            seen.append((r.get_type(), r.seq))
            frame, cmd, lat, lon, alt = items[r.seq]
            g.m.mav.mission_item_int_send(1, 1, r.seq, frame, cmd, 0, 1, 0, 0, 0, NAN, lat, lon, alt, 0)
        return seen

    wps = [
        (6, mavlink.MAV_CMD_NAV_TAKEOFF, *home, 5.0),
        (6, mavlink.MAV_CMD_NAV_WAYPOINT, home[0] + 900, home[1], 5.0),
    ]
    # a global frame for the return item: refused; PX4 asks item 0 with MISSION_REQUEST first
    seen = upload([*wps, (0, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 0, 0.0)])
    assert seen[0] == ("MISSION_REQUEST", 0) and seen[1] == ("MISSION_REQUEST_INT", 1)
    assert seen[-1] == ("ACK", mavlink.MAV_MISSION_UNSUPPORTED)
    seen = upload([*wps, (mavlink.MAV_FRAME_MISSION, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 0, 0.0)])
    assert seen[0] == ("MISSION_REQUEST_INT", 0) and seen[-1] == ("ACK", mavlink.MAV_MISSION_ACCEPTED)
    # fly it: each reached item is repeated about once a second for about 10 s
    arm(g)
    assert set_px4_mode(g, 4, 4) == ACCEPTED
    first = g.wait("MISSION_ITEM_REACHED", timeout=10)
    again = g.wait("MISSION_ITEM_REACHED", lambda m: m.seq == first.seq, 3)
    assert again is not None


def _free_base(n: int) -> int:
    """A base port P with P..P+n-1 and P+40..P+40+n-1 free on loopback UDP (bounded tries)."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + 40 + n > 65000:
            continue
        socks = []
        try:
            for port in [*range(base, base + n), *range(base + 40, base + 40 + n)]:
                t = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(t)
                t.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for t in socks:
                t.close()
    raise AssertionError("no free UDP port range")


def test_cli_px4_links_are_laid_out_as_px4_sitl(make_gcs: Callable[..., Gcs]) -> None:
    base = _free_base(2)
    proc = subprocess.Popen(
        [sys.executable, "-m", "sitl", "run", "--flavour", "px4", "-n", "2", "--base-port", str(base),
         "--speedup", "5"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.split() == ["SITL", "READY", f"udpin:127.0.0.1:{base}", f"udpin:127.0.0.1:{base + 1}"]
        # the simulator speaks first, to BASE+i, as PX4 does: a udpin client hears it unasked
        g = make_gcs(f"udpin:127.0.0.1:{base + 1}", sysid=2)
        hb = g.heartbeat_msg()
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        # and answers commands at the sender's address
        assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 3.0, -1) == ACCEPTED
    finally:
        proc.terminate()
        assert proc.wait(10) == 0
    bad = subprocess.run(
        [sys.executable, "-m", "sitl", "run", "--flavour", "px4", "--transport", "tcp"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert bad.returncode == 2 and "UDP" in bad.stderr and not bad.stdout


def test_unknown_px4_parameter_in_config_is_a_clear_error(make_fleet: Callable[..., SimFleet]) -> None:
    with pytest.raises(ValueError, match=r"unknown PX4 parameter.*WPNAV_SPEED"):
        make_fleet(flavour="px4", params={"WPNAV_SPEED": 800})

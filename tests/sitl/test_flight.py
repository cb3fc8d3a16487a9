"""Flight behaviour seen over MAVLink: goto, speed limit, land, RTL, reposition, brake."""

from __future__ import annotations

import math

from tests.sitl.conftest import MODE, dist_m, mavlink, offset

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED


def test_goto_global_int_arrives_within_acceptance_radius(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(10)
    st = fleet.vehicle(0).state
    lat, lon = offset(st.home_lat, st.home_lon, 40.0, 30.0)  # 50 m away
    g.drain(0.02)
    g.goto(lat, lon, 15)
    # not acknowledged (like ArduCopter): no COMMAND_ACK / POSITION_TARGET ack of any kind
    msg = g.wait(
        "GLOBAL_POSITION_INT",
        lambda m: dist_m(m.lat / 1e7, m.lon / 1e7, lat, lon) < 1.0 and abs(m.relative_alt / 1000 - 15) < 0.5,
        timeout=3.0,
    )
    assert msg.time_boot_ms / 1000 > 10  # it took sim time to get there
    assert not [m for m in g.drain(0.05) if m.get_type() == "COMMAND_ACK"]
    truth = fleet.vehicle(0).state
    assert dist_m(truth.lat, truth.lon, lat, lon) < 2.0  # ground truth too (GPS error < 1 m)
    assert truth.max_path_error_m > 0.3  # the flown path is not a perfect line (eq. 9)


def test_goto_ignored_when_z_ignore_bit_set_and_outside_guided(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(5)
    st = fleet.vehicle(0).state
    lat, lon = offset(st.home_lat, st.home_lon, 30.0, 0.0)
    g.goto(lat, lon, 5, mask=0x0DF8 | 0x4)  # Z ignored -> whole position ignored
    g.drain(0.2)  # 5 s sim
    st2 = fleet.vehicle(0).state
    assert dist_m(st.lat, st.lon, st2.lat, st2.lon) < 1.5
    assert g.set_mode("LOITER") == ACCEPTED
    g.goto(lat, lon, 5)  # not in GUIDED -> ignored
    g.drain(0.2)
    st3 = fleet.vehicle(0).state
    assert dist_m(st.lat, st.lon, st3.lat, st3.lon) < 1.5


def test_speed_limit_respected_and_change_speed(make_fleet, make_gcs) -> None:
    fleet = make_fleet(params={"WPNAV_SPEED": 300})
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(10)
    g.stream(mavlink.MAVLINK_MSG_ID_VFR_HUD, 10)
    st = fleet.vehicle(0).state
    lat, lon = offset(st.home_lat, st.home_lon, 80.0, 0.0)
    g.goto(lat, lon, 10)
    speeds = [g.wait("VFR_HUD").groundspeed for _ in range(60)]
    assert max(speeds) <= 3.0 + 0.05
    assert max(speeds) > 2.8  # reaches cruise
    # DO_CHANGE_SPEED raises the limit for the current GUIDED target
    assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 6.0, -1) == ACCEPTED
    g.wait("VFR_HUD", lambda m: m.groundspeed > 4.5, timeout=3)
    speeds = [g.wait("VFR_HUD").groundspeed for _ in range(20)]
    assert max(speeds) <= 6.05


def test_land_descends_and_disarms(make_fleet, make_gcs) -> None:
    fleet = make_fleet(params={"LAND_SPEED": 150})
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(6)
    g.stream(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5)
    assert g.command(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
    g.heartbeat_msg(lambda m: m.custom_mode == MODE["LAND"])
    g.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_LANDING)
    g.heartbeat_msg(lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, timeout=5)
    st = fleet.vehicle(0).state
    assert st.landed and not st.armed and abs(st.alt_rel) < 0.05
    g.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND)


def test_rtl_returns_home_lands_and_disarms(make_fleet, make_gcs) -> None:
    fleet = make_fleet(params={"RTL_ALT": 1200, "RTL_LOIT_TIME": 1000, "LAND_SPEED": 150, "WPNAV_SPEED": 800})
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(5)
    st = fleet.vehicle(0).state
    lat, lon = offset(st.home_lat, st.home_lon, -40.0, 25.0)
    g.goto(lat, lon, 5)
    g.wait("GLOBAL_POSITION_INT", lambda m: dist_m(m.lat / 1e7, m.lon / 1e7, lat, lon) < 1.0, timeout=4)
    assert g.command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH) == ACCEPTED
    # climbs to RTL_ALT (12 m) first
    g.wait("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 11500, timeout=4)
    g.heartbeat_msg(lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, timeout=8)
    st = fleet.vehicle(0).state
    assert st.mode == "RTL" and st.landed and not st.armed
    assert dist_m(st.lat, st.lon, st.home_lat, st.home_lon) < 2.0


def test_reposition_brake_and_loiter(make_fleet, make_gcs) -> None:
    fleet = make_fleet(params={"WPNAV_SPEED": 1000})
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(8)
    st = fleet.vehicle(0).state
    lat, lon = offset(st.home_lat, st.home_lon, 0.0, 120.0)
    res = g.command_int(
        mavlink.MAV_CMD_DO_REPOSITION,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        -1,
        1,
        round(lat * 1e7),
        round(lon * 1e7),
        8,
    )
    assert res == ACCEPTED
    g.stream(mavlink.MAVLINK_MSG_ID_VFR_HUD, 10)
    g.wait("VFR_HUD", lambda m: m.groundspeed > 8.0, timeout=3)
    assert g.set_mode("BRAKE") == ACCEPTED
    g.wait("VFR_HUD", lambda m: m.groundspeed < 0.2, timeout=2)
    stopped = fleet.vehicle(0).state
    assert dist_m(stopped.lat, stopped.lon, lat, lon) > 40  # stopped short of the target
    assert g.set_mode("LOITER") == ACCEPTED
    g.drain(0.2)
    held = fleet.vehicle(0).state
    assert dist_m(stopped.lat, stopped.lon, held.lat, held.lon) < 1.5
    # DO_REPOSITION from LOITER switches back to GUIDED
    res = g.command_int(mavlink.MAV_CMD_DO_REPOSITION, 6, -1, 1, round(lat * 1e7), round(lon * 1e7), 8)
    assert res == ACCEPTED
    g.heartbeat_msg(lambda m: m.custom_mode == MODE["GUIDED"])


def test_local_ned_offset_target(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(6)
    start = fleet.vehicle(0).state
    g.m.mav.set_position_target_local_ned_send(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, 0x0DF8, 20.0, -10.0, -4.0, 0, 0, 0, 0, 0, 0, 0, 0
    )
    want_alt = start.est_alt_rel + 4.0
    g.wait(
        "GLOBAL_POSITION_INT",
        lambda m: (
            abs(m.relative_alt / 1000 - want_alt) < 0.4
            and dist_m(start.est_lat, start.est_lon, m.lat / 1e7, m.lon / 1e7) > 21.5
        ),
        timeout=4,
    )
    end = fleet.vehicle(0).state
    dn = (end.est_lat - start.est_lat) * 111318.845
    de = (end.est_lon - start.est_lon) * 111318.845 * math.cos(math.radians(start.est_lat))
    assert abs(dn - 20) < 1.5 and abs(de + 10) < 1.5


def test_multiple_vehicles_fly_independently(make_fleet, make_gcs) -> None:
    fleet = make_fleet(vehicles=3, spacing_m=5.0)
    homes = [fleet.vehicle(i).state for i in range(3)]
    assert 4.9 < dist_m(homes[0].lat, homes[0].lon, homes[1].lat, homes[1].lon) < 5.1
    g2 = make_gcs(fleet.endpoints[2], sysid=3)
    g2.takeoff(4)
    assert fleet.vehicle(2).state.armed and not fleet.vehicle(2).state.landed
    assert not fleet.vehicle(0).state.armed and fleet.vehicle(1).state.landed


def test_no_position_fix_or_home_during_the_boot_period(make_fleet, make_gcs) -> None:
    """Like ArduCopter: fix 0 and lat/lon 0,0 after boot, no home, arming refused; then a fix."""
    fleet = make_fleet(prearm_delay_s=8.0, gps_boot_s=6.0, speedup=10.0)
    g = make_gcs(fleet.endpoints[0])
    g.stream(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 5)
    g.stream(mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 5)
    gpi = g.wait("GLOBAL_POSITION_INT")
    gps = g.wait("GPS_RAW_INT")
    assert gpi.time_boot_ms < 5000
    assert (gpi.lat, gpi.lon, gps.fix_type, gps.lat) == (0, 0, 0, 0)
    g.drain(0.05)
    assert g.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION) == ACCEPTED
    assert not [m for m in g.drain(0.1) if m.get_type() == "HOME_POSITION" and m.time_usec < 5_000_000]
    assert g.set_mode("GUIDED") == ACCEPTED
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_FAILED
    fixed = g.wait("GPS_RAW_INT", lambda m: m.fix_type == 3, timeout=5.0)
    assert fixed.time_usec >= 6_000_000
    gpi = g.wait("GLOBAL_POSITION_INT")
    home = fleet.vehicle(0).state
    assert dist_m(gpi.lat / 1e7, gpi.lon / 1e7, home.home_lat, home.home_lon) < 5.0


def test_change_speed_refused_outside_auto_guided_rtl(make_fleet, make_gcs) -> None:
    """DO_CHANGE_SPEED: MAV_RESULT_FAILED in BRAKE and LOITER (ArduCopter's Mode::set_speed_xy)."""
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(8)
    for mode, expected in (
        ("BRAKE", mavlink.MAV_RESULT_FAILED),
        ("LOITER", mavlink.MAV_RESULT_FAILED),
        ("GUIDED", ACCEPTED),
        ("RTL", ACCEPTED),
    ):
        assert g.set_mode(mode) == ACCEPTED
        assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 3.0, -1) == expected, mode


def test_first_guided_target_after_takeoff_resets_the_speed(make_fleet, make_gcs) -> None:
    """A speed sent before the first target after takeoff is lost (WPNAV_SPEED); sent after, it holds."""
    fleet = make_fleet(params={"WPNAV_SPEED": 800})
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(10)
    g.stream(mavlink.MAVLINK_MSG_ID_VFR_HUD, 10)
    st = fleet.vehicle(0).state
    assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 3.0, -1) == ACCEPTED  # before the target
    lat, lon = offset(st.home_lat, st.home_lon, 120.0, 0.0)
    g.goto(lat, lon, 10)
    g.wait("VFR_HUD", lambda m: m.groundspeed > 7.0, timeout=5)  # the 3 m/s was dropped
    # after the target (waypoint controller running), the change holds
    assert g.command(mavlink.MAV_CMD_DO_CHANGE_SPEED, 1, 3.0, -1) == ACCEPTED
    g.wait("VFR_HUD", lambda m: m.groundspeed < 3.2, timeout=5)
    g.goto(lat, lon, 12)  # a further target in the same GUIDED session keeps it
    speeds = [g.wait("VFR_HUD").groundspeed for _ in range(20)]
    assert max(speeds) <= 3.1

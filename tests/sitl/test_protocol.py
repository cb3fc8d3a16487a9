"""MAVLink behaviour toward a GCS: heartbeat, modes, streams, commands, params, link handling."""

from __future__ import annotations

import itertools
import socket
import time

from pymavlink import mavutil

from tests.sitl.conftest import MODE, Gcs, mavlink

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
FAILED = mavlink.MAV_RESULT_FAILED


def test_heartbeat_identity_and_custom_modes(make_fleet, make_gcs) -> None:
    fleet = make_fleet(vehicles=3)
    assert len(fleet.endpoints) == 3
    assert all(e.startswith("tcp:127.0.0.1:") for e in fleet.endpoints)
    for i, url in enumerate(fleet.endpoints):
        g = make_gcs(url, sysid=i + 1)
        hb = g.heartbeat_msg()
        assert hb.get_srcSystem() == i + 1 and hb.get_srcComponent() == 1
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.custom_mode == MODE["STABILIZE"]
    g = make_gcs(fleet.endpoints[0])
    for name in ("GUIDED", "LOITER", "BRAKE", "RTL", "LAND", "AUTO", "STABILIZE"):
        assert g.set_mode(name) == ACCEPTED, name
        g.heartbeat_msg(lambda m, n=name: m.custom_mode == MODE[n])
    assert g.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 42) == FAILED  # no such mode
    # component 0 accepted as target, unknown command unsupported
    assert g.command(mavlink.MAV_CMD_DO_SET_MODE, 1, MODE["GUIDED"], comp=0) == ACCEPTED
    assert g.command(mavlink.MAV_CMD_DO_SET_SERVO, 5, 1500) == mavlink.MAV_RESULT_UNSUPPORTED


def test_default_streams_then_message_interval(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    g.heartbeat_msg()
    types = {m.get_type() for m in g.drain(0.3)}  # 0.3 s wall = 7.5 s sim
    assert types <= {"HEARTBEAT", "SYS_STATUS", "STATUSTEXT", "HOME_POSITION"}, types
    assert {"HEARTBEAT", "SYS_STATUS"} <= types
    g.stream(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10)
    stamps = [g.wait("GLOBAL_POSITION_INT").time_boot_ms for _ in range(12)]
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert all(80 <= d <= 120 for d in gaps), gaps  # 10 Hz in sim time
    # REQUEST_DATA_STREAM fallback (EXTRA2 -> VFR_HUD)
    g.m.mav.request_data_stream_send(1, 1, mavlink.MAV_DATA_STREAM_EXTRA2, 4, 1)
    g.wait("VFR_HUD")
    # disabling with interval -1
    gpi = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
    assert g.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, gpi, -1) == ACCEPTED
    g.drain(0.1)
    assert not [m for m in g.drain(0.3) if m.get_type() == "GLOBAL_POSITION_INT"]
    # REQUEST_MESSAGE for HOME_POSITION (ACK then the message)
    assert g.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION) == ACCEPTED
    home = g.wait("HOME_POSITION")
    st = fleet.vehicle(0).state
    assert abs(home.latitude / 1e7 - st.home_lat) < 1e-6
    assert abs(home.altitude / 1000 - st.home_alt_amsl) < 0.01
    # streams are per link: a new connection starts from the defaults again
    g.stream(mavlink.MAVLINK_MSG_ID_ATTITUDE, 10)
    g.wait("ATTITUDE")
    g.close()
    g2 = make_gcs(fleet.endpoints[0])
    g2.heartbeat_msg()
    assert "ATTITUDE" not in {m.get_type() for m in g2.drain(0.3)}


def test_all_telemetry_messages_decode(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    wanted = {
        "GLOBAL_POSITION_INT": mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        "GPS_RAW_INT": mavlink.MAVLINK_MSG_ID_GPS_RAW_INT,
        "ATTITUDE": mavlink.MAVLINK_MSG_ID_ATTITUDE,
        "VFR_HUD": mavlink.MAVLINK_MSG_ID_VFR_HUD,
        "BATTERY_STATUS": mavlink.MAVLINK_MSG_ID_BATTERY_STATUS,
        "EXTENDED_SYS_STATE": mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
        "MISSION_CURRENT": mavlink.MAVLINK_MSG_ID_MISSION_CURRENT,
        "HOME_POSITION": mavlink.MAVLINK_MSG_ID_HOME_POSITION,
    }
    for msgid in wanted.values():
        g.stream(msgid, 5)
    got = {name: g.wait(name) for name in wanted}
    got["GPS_RAW_INT"] = g.wait("GPS_RAW_INT", lambda m: m.fix_type == 3)  # after the boot period
    assert got["GPS_RAW_INT"].fix_type == 3 and got["GPS_RAW_INT"].satellites_visible >= 6
    assert got["EXTENDED_SYS_STATE"].landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
    assert 99 <= got["BATTERY_STATUS"].battery_remaining <= 100
    assert got["BATTERY_STATUS"].voltages[0] > 12000
    sys_status = g.wait("SYS_STATUS")
    assert sys_status.voltage_battery > 12000 and sys_status.battery_remaining >= 99


def test_arm_refused_during_prearm_then_accepted_and_auto_disarm(make_fleet, make_gcs) -> None:
    fleet = make_fleet(prearm_delay_s=20.0, speedup=20.0)
    g = make_gcs(fleet.endpoints[0])
    g.heartbeat_msg()
    assert g.set_mode("GUIDED") == ACCEPTED
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == FAILED
    assert any(t.startswith("PreArm: Need Position Estimate") for t in g.texts)
    assert not fleet.vehicle(0).state.armed
    g.arm(timeout=5.0)  # 20 s sim at 20x = 1 s wall
    g.heartbeat_msg(lambda m: m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
    assert fleet.sim_time >= 20.0
    # no takeoff: ArduCopter disarms itself after DISARM_DELAY (10 s)
    armed_at = fleet.sim_time
    g.heartbeat_msg(lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, timeout=3.0)
    assert 9.0 <= fleet.sim_time - armed_at <= 12.0
    # force arm skips pre-arm checks but not the mode check
    assert g.set_mode("RTL") == ACCEPTED
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196) == FAILED
    assert "Arm: Mode not armable" in g.texts


def test_takeoff_rules(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    takeoff = mavlink.MAV_CMD_NAV_TAKEOFF
    assert g.command(takeoff, 0, 0, 0, 0, 0, 0, 10) == FAILED  # disarmed
    g.arm()  # in STABILIZE
    assert g.command(takeoff, 0, 0, 0, 0, 0, 0, 10) == FAILED  # not GUIDED
    assert g.set_mode("GUIDED") == ACCEPTED
    assert g.command(takeoff, 0, 0, 0, 0, 0, 0, -1) == FAILED  # not above current altitude
    assert g.command(takeoff, 0, 0, 0, 0, 0, 0, 8) == ACCEPTED
    assert g.command(takeoff, 0, 0, 0, 0, 0, 0, 12) == FAILED  # no longer landed
    g.stream(mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 5)
    g.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF)
    g.wait("EXTENDED_SYS_STATE", lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR, timeout=5)
    st = fleet.vehicle(0).state
    assert 7.5 < st.alt_rel < 8.5 and not st.landed
    # disarm refused in the air without the force magic
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == FAILED


def test_params_read_set_list(make_fleet, make_gcs) -> None:
    fleet = make_fleet(vehicles=2)
    g = make_gcs(fleet.endpoints[1], sysid=2)
    g.m.mav.param_request_read_send(2, 1, b"SYSID_THISMAV", -1)
    pv = g.wait("PARAM_VALUE", lambda m: m.param_id == "SYSID_THISMAV")
    assert pv.param_value == 2
    g.m.mav.param_request_read_send(2, 1, b"WPNAV_SPEED", -1)
    assert g.wait("PARAM_VALUE", lambda m: m.param_id == "WPNAV_SPEED").param_value == 500
    g.m.mav.param_set_send(2, 1, b"WPNAV_SPEED", 750, mavlink.MAV_PARAM_TYPE_REAL32)
    assert g.wait("PARAM_VALUE", lambda m: m.param_id == "WPNAV_SPEED").param_value == 750
    g.m.mav.param_set_send(2, 1, b"RTL_ALT", 2000.4, mavlink.MAV_PARAM_TYPE_INT32)
    assert g.wait("PARAM_VALUE", lambda m: m.param_id == "RTL_ALT").param_value == 2000
    g.m.mav.param_request_list_send(2, 1)
    first = g.wait("PARAM_VALUE")
    names = {first.param_id}
    for _ in range(first.param_count - 1):
        names.add(g.wait("PARAM_VALUE").param_id)
    needed_names = (
        "WPNAV_SPEED",
        "WPNAV_ACCEL",
        "WPNAV_SPEED_UP",
        "WPNAV_SPEED_DN",
        "WPNAV_RADIUS",
        "RTL_ALT",
        "FENCE_ENABLE",
        "FENCE_ACTION",
        "FENCE_ALT_MAX",
        "FENCE_RADIUS",
        "BATT_LOW_VOLT",
    )
    for needed in needed_names:
        assert needed in names
    # the other vehicle is untouched
    assert fleet.vehicle(0).params["WPNAV_SPEED"] == 500


def test_link_drop_silences_and_ignores_input(make_fleet, make_gcs) -> None:
    fleet = make_fleet(speedup=10.0)
    g = make_gcs(fleet.endpoints[0])
    g.stream(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10)
    g.wait("GLOBAL_POSITION_INT")
    fleet.vehicle(0).inject_link_drop(5.0)  # 0.5 s wall
    time.sleep(0.02)
    g.drain(0.05)
    g.m.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, MODE["GUIDED"], 0, 0, 0, 0, 0)
    assert g.drain(0.3) == []
    assert fleet.vehicle(0).state.mode == "STABILIZE"  # the command was lost
    g.wait("GLOBAL_POSITION_INT", timeout=2.0)  # comes back by itself


def test_link_drop_from_cli_spec(make_fleet, make_gcs) -> None:
    fleet = make_fleet(speedup=10.0, failures=["1:link_drop@3+4"])
    g = make_gcs(fleet.endpoints[0])
    g.stream(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10)
    assert fleet.wait_sim_time(3.2, 5.0)
    g.drain(0.05)
    assert [m for m in g.drain(0.2) if m.get_type() == "GLOBAL_POSITION_INT"] == []
    msg = g.wait("GLOBAL_POSITION_INT", timeout=2.0)
    assert msg.time_boot_ms >= 7000


def test_client_reconnect_replaces_old_client(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    url = fleet.endpoints[0]
    g1 = make_gcs(url)
    g1.heartbeat_msg()
    g2 = make_gcs(url)  # the old client is dropped, the new one served
    g2.heartbeat_msg()
    assert g2.set_mode("GUIDED") == ACCEPTED
    g2.close()
    g3 = make_gcs(url)
    g3.heartbeat_msg(lambda m: m.custom_mode == MODE["GUIDED"])
    # a raw socket that connects and vanishes does not break the endpoint
    host, port = url.split(":")[1], int(url.split(":")[2])
    with socket.create_connection((host, port)):
        pass
    g4 = make_gcs(url)
    g4.heartbeat_msg()


def test_udp_transport(make_fleet) -> None:
    fleet = make_fleet(transport="udp", vehicles=2)
    assert all(e.startswith("udpout:127.0.0.1:") for e in fleet.endpoints)
    g = Gcs(fleet.endpoints[1], sysid=2)
    try:
        hb = g.heartbeat_msg()
        assert hb.get_srcSystem() == 2
        assert g.set_mode("GUIDED") == ACCEPTED
    finally:
        g.close()


def test_gps_loss_injection(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    g.stream(mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 5)
    g.wait("GPS_RAW_INT", lambda m: m.fix_type == 3)
    fleet.vehicle(0).inject_gps_loss(10.0)
    g.wait("GPS_RAW_INT", lambda m: m.fix_type == 0 and m.satellites_visible == 0)
    assert fleet.vehicle(0).state.gps_fix == 0
    assert g.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == FAILED
    g.wait("GPS_RAW_INT", lambda m: m.fix_type == 3, timeout=3.0)


def test_mavutil_dialect_is_mavlink2(make_fleet) -> None:
    fleet = make_fleet()
    m = mavutil.mavlink_connection(fleet.endpoints[0], source_system=255)
    try:
        hb = m.recv_match(type="HEARTBEAT", blocking=True, timeout=5)
        assert hb is not None and hb.get_header().mlen >= 9
        assert m.WIRE_PROTOCOL_VERSION == "2.0"
    finally:
        m.close()


def test_do_set_home_and_autopilot_version(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    st = fleet.vehicle(0).state
    new_lat, new_lon = st.home_lat + 0.0005, st.home_lon + 0.0005
    assert g.command(mavlink.MAV_CMD_DO_SET_HOME, 0, 0, 0, 0, new_lat, new_lon, 500.0) == ACCEPTED
    home = g.wait("HOME_POSITION")
    assert abs(home.latitude / 1e7 - new_lat) < 1e-6 and home.altitude == 500000
    assert abs(fleet.vehicle(0).state.alt_rel - (st.alt_amsl - 500.0)) < 0.01
    assert g.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == ACCEPTED
    ver = g.wait("AUTOPILOT_VERSION")
    assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE

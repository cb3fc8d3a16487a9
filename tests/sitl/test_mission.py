"""Mission and fence protocol (MISSION_REQUEST_INT and legacy MISSION_REQUEST), AUTO flight, fence actions."""

from __future__ import annotations

from typing import Any

import pytest

from tests.sitl.conftest import MODE, Gcs, dist_m, mavlink, offset

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
NAV_WP = mavlink.MAV_CMD_NAV_WAYPOINT
REL = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT


def item(
    seq: int,
    cmd: int,
    lat: float = 0.0,
    lon: float = 0.0,
    alt: float = 0.0,
    p1: float = 0.0,
    frame: int = REL,
    mission_type: int = 0,
) -> tuple[Any, ...]:
    return (seq, frame, cmd, 0, 1, p1, 0.0, 0.0, 0.0, round(lat * 1e7), round(lon * 1e7), alt, mission_type)


def upload(
    g: Gcs, items: list[tuple[Any, ...]], mission_type: int = 0, legacy_item: bool = False
) -> list[str]:
    """Upload ``items``; returns the request message types seen. Fails unless MISSION_ACK ACCEPTED."""
    g.m.mav.mission_count_send(g.sysid, 1, len(items), mission_type)
    seen: list[str] = []
    for _ in range(len(items) * 3 + 5):
        msg = g.wait(("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"))
        if msg.get_type() == "MISSION_ACK":
            assert msg.type == mavlink.MAV_MISSION_ACCEPTED, msg
            assert msg.mission_type == mission_type
            return seen
        seen.append(msg.get_type())
        assert msg.mission_type == mission_type
        it = items[msg.seq]
        if legacy_item:
            g.m.mav.mission_item_send(
                g.sysid,
                1,
                it[0],
                it[1] - 3 if it[1] >= 5 else it[1],
                *it[2:9],
                it[9] / 1e7,
                it[10] / 1e7,
                it[11],
                it[12],
            )
        else:
            g.m.mav.mission_item_int_send(g.sysid, 1, *it)
    raise AssertionError("upload did not finish")


def download(g: Gcs, mission_type: int = 0, legacy: bool = False) -> list[Any]:
    """Read the vehicle's items back; ``legacy`` asks with MISSION_REQUEST (answered by MISSION_ITEM)."""
    g.m.mav.mission_request_list_send(g.sysid, 1, mission_type)
    count = g.wait("MISSION_COUNT").count
    out = []
    for seq in range(count):
        if legacy:
            g.m.mav.mission_request_send(g.sysid, 1, seq, mission_type)
        else:
            g.m.mav.mission_request_int_send(g.sysid, 1, seq, mission_type)

        def is_seq(m: Any, s: int = seq) -> bool:
            return bool(m.seq == s)

        out.append(g.wait("MISSION_ITEM" if legacy else "MISSION_ITEM_INT", is_seq))
    g.m.mav.mission_ack_send(g.sysid, 1, mavlink.MAV_MISSION_ACCEPTED, mission_type)
    return out


def square_mission(lat: float, lon: float, alt: float = 8.0, side: float = 20.0) -> list[tuple[Any, ...]]:
    corners = [(side, 0.0), (side, side), (0.0, side)]
    items = [
        item(0, NAV_WP, lat, lon, 0, frame=mavlink.MAV_FRAME_GLOBAL_INT),
        item(1, mavlink.MAV_CMD_NAV_TAKEOFF, alt=alt),
    ]
    for i, (n, e) in enumerate(corners):
        la, lo = offset(lat, lon, n, e)
        items.append(item(2 + i, NAV_WP, la, lo, alt))
    items.append(item(5, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH))
    return items


@pytest.mark.parametrize("legacy", [False, True])
def test_mission_upload_then_auto_flies_it(make_fleet, make_gcs, legacy: bool) -> None:
    fleet = make_fleet(legacy_mission_request=legacy, params={"RTL_LOIT_TIME": 0, "LAND_SPEED": 200})
    g = make_gcs(fleet.endpoints[0])
    st = fleet.vehicle(0).state
    items = square_mission(st.home_lat, st.home_lon)
    seen = upload(g, items, legacy_item=legacy)
    assert set(seen) == {"MISSION_REQUEST" if legacy else "MISSION_REQUEST_INT"}
    assert len(seen) == len(items)
    got = download(g)
    assert len(got) == len(items)
    assert got[0].x == round(st.home_lat * 1e7)  # seq 0 is home
    assert [m.command for m in got[1:]] == [it[2] for it in items[1:]]
    tol = 40 if legacy else 1  # MISSION_ITEM carries float32 degrees (~4e-6 deg resolution here)
    assert abs(got[3].x - items[3][9]) <= tol and abs(got[3].y - items[3][10]) <= tol
    degrees = download(g, legacy=True)  # the legacy read-back: MISSION_ITEM in float degrees
    assert [m.command for m in degrees] == [m.command for m in got]
    assert degrees[3].x == pytest.approx(got[3].x / 1e7, abs=1e-5) and degrees[3].z == got[3].z
    # arm in GUIDED, switch to AUTO on the ground: the takeoff item starts the mission
    g.stream(mavlink.MAVLINK_MSG_ID_MISSION_CURRENT, 2)
    assert g.set_mode("GUIDED") == ACCEPTED
    g.arm()
    assert g.set_mode("AUTO") == ACCEPTED
    reached = []
    for _ in range(5):
        reached.append(g.wait("MISSION_ITEM_REACHED", timeout=6).seq)
    assert reached == [1, 2, 3, 4, 5]
    g.heartbeat_msg(lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, timeout=6)
    v = fleet.vehicle(0).state
    assert v.landed and dist_m(v.lat, v.lon, v.home_lat, v.home_lon) < 2.5
    assert v.distance_flown_m > 60 + 2 * 8
    assert any(t.startswith("Mission: 2 WP") for t in g.texts)


def test_mission_rules_clear_in_auto_and_missing_takeoff(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    st = fleet.vehicle(0).state
    la, lo = offset(st.home_lat, st.home_lon, 10, 0)
    upload(g, [item(0, NAV_WP, st.home_lat, st.home_lon), item(1, NAV_WP, la, lo, 5)])
    assert g.set_mode("GUIDED") == ACCEPTED
    g.arm()
    assert g.set_mode("AUTO") == mavlink.MAV_RESULT_FAILED  # on the ground without a takeoff item
    assert "Auto: Missing Takeoff Cmd" in g.texts
    upload(g, square_mission(st.home_lat, st.home_lon))
    assert g.set_mode("AUTO") == ACCEPTED
    g.wait("MISSION_ITEM_REACHED", timeout=5)
    g.m.mav.mission_clear_all_send(1, 1, 0)
    assert g.wait("MISSION_ACK").type == mavlink.MAV_MISSION_ERROR  # cannot clear while flying it
    assert g.set_mode("LOITER") == ACCEPTED
    g.m.mav.mission_clear_all_send(1, 1, 0)
    assert g.wait("MISSION_ACK").type == mavlink.MAV_MISSION_ACCEPTED
    assert len(download(g)) == 1  # home only


def test_out_of_sequence_item_is_nacked_but_upload_continues(make_fleet, make_gcs) -> None:
    fleet = make_fleet()
    g = make_gcs(fleet.endpoints[0])
    st = fleet.vehicle(0).state
    items = square_mission(st.home_lat, st.home_lon)
    g.m.mav.mission_count_send(1, 1, len(items), 0)
    req = g.wait("MISSION_REQUEST_INT")
    assert req.seq == 0
    g.m.mav.mission_item_int_send(1, 1, *items[2])  # wrong seq
    assert g.wait("MISSION_ACK").type == mavlink.MAV_MISSION_INVALID_SEQUENCE
    for it in items:
        g.m.mav.mission_item_int_send(1, 1, *it)
        if it[0] < len(items) - 1:
            g.wait("MISSION_REQUEST_INT", lambda m, s=it[0]: m.seq == s + 1)
    assert g.wait("MISSION_ACK").type == mavlink.MAV_MISSION_ACCEPTED


def fence_polygon(lat: float, lon: float, half: float) -> list[tuple[Any, ...]]:
    corners = [(-half, -half), (-half, half), (half, half), (half, -half)]
    out = []
    for i, (n, e) in enumerate(corners):
        la, lo = offset(lat, lon, n, e)
        out.append(
            item(
                i,
                mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                la,
                lo,
                0,
                p1=4,
                frame=mavlink.MAV_FRAME_GLOBAL_INT,
                mission_type=mavlink.MAV_MISSION_TYPE_FENCE,
            )
        )
    return out


def set_param(g: Gcs, name: str, value: float) -> None:
    g.m.mav.param_set_send(g.sysid, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32)
    g.wait("PARAM_VALUE", lambda m: m.param_id == name and abs(m.param_value - value) < 1e-3)


def test_fence_polygon_breach_triggers_rtl(make_fleet, make_gcs) -> None:
    fleet = make_fleet(params={"RTL_LOIT_TIME": 0, "LAND_SPEED": 200, "WPNAV_SPEED": 800})
    g = make_gcs(fleet.endpoints[0])
    st = fleet.vehicle(0).state
    fence = fence_polygon(st.home_lat, st.home_lon, 30.0)
    fence.append(
        item(
            4,
            mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
            st.home_lat,
            st.home_lon,
            0,
            p1=200,
            frame=mavlink.MAV_FRAME_GLOBAL_INT,
            mission_type=mavlink.MAV_MISSION_TYPE_FENCE,
        )
    )
    upload(g, fence, mission_type=mavlink.MAV_MISSION_TYPE_FENCE)
    got = download(g, mavlink.MAV_MISSION_TYPE_FENCE)
    assert [m.command for m in got] == [5001] * 4 + [5003] and got[4].param1 == 200
    set_param(g, "FENCE_ENABLE", 1)
    set_param(g, "FENCE_ACTION", 1)
    g.takeoff(6)
    target = offset(st.home_lat, st.home_lon, 60.0, 0.0)
    g.goto(*target, 6)
    g.heartbeat_msg(lambda m: m.custom_mode == MODE["RTL"], timeout=4)
    assert "Fence Breached" in g.texts
    assert g.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_FENCE_STATUS) == ACCEPTED
    fs = g.wait("FENCE_STATUS")
    assert fs.breach_count >= 1 and fs.breach_type == mavlink.FENCE_BREACH_BOUNDARY
    g.heartbeat_msg(lambda m: not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED, timeout=8)
    v = fleet.vehicle(0).state
    assert dist_m(v.lat, v.lon, v.home_lat, v.home_lon) < 2.5


@pytest.mark.parametrize(("action", "mode"), [(2, "LAND"), (4, "BRAKE"), (0, "GUIDED")])
def test_fence_alt_max_actions(make_fleet, make_gcs, action: int, mode: str) -> None:
    fleet = make_fleet(params={"FENCE_ENABLE": 1, "FENCE_ALT_MAX": 12, "FENCE_ACTION": action})
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(8)
    st = fleet.vehicle(0).state
    g.goto(st.lat, st.lon, 20)
    g.wait("STATUSTEXT", lambda m: m.text == "Fence Breached", timeout=4)
    g.heartbeat_msg(lambda m: m.custom_mode == MODE[mode], timeout=2)
    assert fleet.vehicle(0).state.fence_breached


def test_fence_home_circle_radius(make_fleet, make_gcs) -> None:
    fleet = make_fleet(
        params={"FENCE_ENABLE": 1, "FENCE_RADIUS": 25, "FENCE_TYPE": 2, "FENCE_ACTION": 2, "WPNAV_SPEED": 800}
    )
    g = make_gcs(fleet.endpoints[0])
    g.takeoff(5)
    st = fleet.vehicle(0).state
    g.goto(*offset(st.home_lat, st.home_lon, 0, 50), 5)
    g.heartbeat_msg(lambda m: m.custom_mode == MODE["LAND"], timeout=4)
    v = fleet.vehicle(0).state
    assert 24 < dist_m(v.lat, v.lon, v.home_lat, v.home_lon) < 40

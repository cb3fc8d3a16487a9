"""The tests/ardupilot missions, plus pause, fleet hold, a planned survey and a geofence, flown end to
end on real PX4 SITL through daemon and agents, on both agent backends (``rig`` is parametrized).

Flights are few and combined where the scenarios do not interfere (pause and fleet hold on one leg of
the synchronized mission): every take-off and landing costs PX4 time the CI budget does not have.
Each test leaves every vehicle landed and disarmed for the next one, and places its points from where
each vehicle stands (``rig.at``): PX4 takes its home where it arms. Times about a vehicle's motion are
PX4's own (the observer's ``time_boot_ms``), since PX4 runs faster than the wall clock.
"""

from __future__ import annotations

import time

import pytest
from pymavlink.dialects.v20 import common as mavlink

from gcs.planning.mission import mission_from_paths
from protocol.actions import GoBy, Goto, ReturnToLaunch, SetSpeed, Takeoff, Waypoint, Waypoints
from protocol.geo import distance_m
from protocol.packets import FenceCircle, Geofence
from tests.px4.checks import assert_stops_and_holds, cruising
from tests.px4.rig import HOME, PX4Rig
from tests.support.pilot import PilotStation, drain_for
from tests.support.rig import task

pytestmark = [pytest.mark.px4, pytest.mark.slow, pytest.mark.timeout(300)]

FIRST_LEG_SPEED = 3.0  # not PX4's MPC_XY_CRUISE (5 m/s): a lost speed shows
SPEED_TOLERANCE = 0.6
RTL_ALTS = (14.0, 17.0, 20.0)
PX4_RTL_DEFAULT = 30.0  # RTL_RETURN_ALT out of the box


@pytest.mark.px4_extended
def test_synchronized_mission_with_pause_fleet_hold_and_resume(rig: PX4Rig) -> None:
    """One synchronized flight right after connect: takeoff 8/10/12 m, set_speed 3 m/s, a 60 m leg
    without a speed (flies the set speed), go_by, waypoints at 5 m/s, RTL at 14/17/20 m.

    On the leg the mission is paused, then (resumed, cruising again) the operator holds the fleet: each
    time every PX4 drone is below 0.5 m/s within 3 s and holds within 3 m for 10 s (the issue's
    acceptance), and after each resume the leg goes on at its set speed. The mission completes, go_by
    and the waypoints end where planned, and each drone returns at its own layer (RTL_RETURN_ALT)."""
    plans: dict[str, list[object]] = {}
    for i, name in enumerate(rig.names):
        leg, b, c = rig.at(60.0, 0.0, i), rig.at(60.0, 15.0, i), rig.at(25.0, 15.0, i)
        plans[name] = [
            Takeoff(step=0, alt=8.0 + 2 * i, sync=True),
            SetSpeed(step=1, speed=FIRST_LEG_SPEED),
            Goto(step=2, lat=leg[0], lon=leg[1], alt=8.0 + 2 * i, sync=True),
            GoBy(step=3, north=0.0, east=-10.0, up=2.0),
            Waypoints(
                step=4,
                points=[
                    Waypoint(lat=b[0], lon=b[1], alt=10.0 + 2 * i),
                    Waypoint(lat=c[0], lon=c[1], alt=10.0 + 2 * i),
                ],
                speed=5.0,
                sync=True,
            ),
            ReturnToLaunch(step=5, alt=RTL_ALTS[i]),
        ]
    mission_id = rig.submit(task("sync-pause-hold", plans, sync_timeout_s=120))
    cruising(rig, 2, FIRST_LEG_SPEED - 0.5)
    paused_at = {n: rig.vehicle_now(n) for n in rig.names}
    rig.call(rig.d.missions.pause(mission_id, "test pause"))
    assert_stops_and_holds(rig, rig.names, paused_at, "after the mission pause")
    rig.call(rig.d.missions.resume(mission_id, "test resume"))
    cruising(rig, 2, FIRST_LEG_SPEED - 0.5)
    held_at = {n: rig.vehicle_now(n) for n in rig.names}
    held = rig.call(rig.d.operator.hold(None, "test hold"))
    assert sorted(held) == sorted(rig.names)
    assert_stops_and_holds(rig, rig.names, held_at, "after the fleet hold")
    resumed_wall = time.monotonic()
    rig.call(rig.d.operator.resume(None, "test resume"))
    progress = rig.finish(mission_id, 200.0)
    assert progress.state == "completed", progress
    assert not rig.events("action_failed"), [e.message for e in rig.events("action_failed")]
    for i, name in enumerate(rig.names):
        leg_peak = rig.peak(name, mission_id, 2)
        assert abs(leg_peak - FIRST_LEG_SPEED) <= SPEED_TOLERANCE, f"{name} leg peak {leg_peak:.1f} m/s"
        after = [s.speed for s in rig.flown(name, mission_id, 2) if s.t > resumed_wall]
        assert after and max(after) >= FIRST_LEG_SPEED - SPEED_TOLERANCE, f"{name} resumed slowly"
        by = rig.flown(name, mission_id, 3)[-1]
        assert distance_m(by.lat, by.lon, *rig.at(60.0, -10.0, i)) < 4.0, f"{name}: go_by ended elsewhere"
        wp_peak = rig.peak(name, mission_id, 4)
        assert abs(wp_peak - 5.0) <= SPEED_TOLERANCE + 0.3, f"{name}: waypoints at {wp_peak:.1f} m/s"
        t = rig.agents[name].autopilot.telemetry()
        assert distance_m(t.lat, t.lon, *rig.at(0.0, 0.0, i)) < 3.0, f"{name} did not land home"
        ret = [
            s for s in rig.flown(name, mission_id, 5) if distance_m(s.lat, s.lon, *rig.at(0.0, 0.0, i)) > 15.0
        ]
        assert ret, f"{name}: no return samples"
        top = max(s.alt for s in ret)
        assert abs(top - RTL_ALTS[i]) < 2.0, f"{name} returned at {top:.1f} m, asked {RTL_ALTS[i]} m"
        assert rig.param(name, "RTL_RETURN_ALT") == pytest.approx(RTL_ALTS[i])


@pytest.mark.px4_extended
def test_planned_survey(rig: PX4Rig) -> None:
    """A small lawnmower from the planner's task builder (transit layers, RTL ending): completes, every
    drone passes each of its waypoints and lands at home."""
    paths = []
    for i in range(len(rig.names)):
        legs = [rig.at(12.0, -3.0, i), rig.at(32.0, -3.0, i), rig.at(32.0, 3.0, i), rig.at(12.0, 3.0, i)]
        paths.append(legs)
    homes = [rig.at(0.0, 0.0, i) for i in range(len(rig.names))]
    survey = mission_from_paths(
        paths,
        alt=8.0,
        speed=4.0,
        agent_names=rig.names,
        homes_latlon=homes,
        transit_alt_step=3.0,
        name="survey",
    )
    mission_id = rig.submit(survey)
    progress = rig.finish(mission_id, 200.0)
    assert progress.state == "completed", progress
    for i, name in enumerate(rig.names):
        flown = [s for s in rig.samples[name] if s.mission_id == mission_id]
        for lat, lon in paths[i]:
            miss = min(distance_m(s.lat, s.lon, lat, lon) for s in flown)
            assert miss < 3.0, f"{name} passed {miss:.1f} m from a survey waypoint"
        t = rig.agents[name].autopilot.telemetry()
        assert distance_m(t.lat, t.lon, *homes[i]) < 3.0


def test_geofence_upload_sets_px4_gf_parameters(rig: PX4Rig) -> None:
    """A fence from the daemon reaches PX4: GF_ACTION (rtl = 3) and GF_MAX_VER_DIST read back right
    (GF_ACTION is an integer parameter, sent byte-wise by PX4)."""
    fence = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=300.0), max_alt_m=60.0)
    sent = rig.call(rig.d.set_geofence(fence, ["drone-1"]))
    assert sent == ["drone-1"]
    rig.wait(lambda: rig.agents["drone-1"].monitor.geofence is not None, 10.0, "fence at the agent")
    try:
        values: dict[str, float] = {}
        wanted = {"GF_ACTION": 3.0, "GF_MAX_VER_DIST": 60.0}
        for _ in range(60):  # the upload and its parameters settle one by one (bounded: about 30 s)
            values = {p: rig.param("drone-1", p) for p in wanted}
            if values == wanted:
                break
            time.sleep(0.3)
        assert values == wanted
    finally:
        rig.call(rig.d.set_geofence(None, ["drone-1"]))


def test_a_ground_station_through_the_agents_router_sees_px4_and_sets_its_mode(rig: PX4Rig) -> None:
    """Issue 26 on PX4: a "QGroundControl" on UDP, fed by drone-3's agent (``mavlink_out``), sees PX4's
    heartbeats but not the agent's own frames nor its ACKs, and sets modes through the agent's link:
    Mission, then Hold (ACCEPTED, its own ACKs routed back to it). Landed and disarmed, so the agent
    sees the modes and takes them for no pilot's takeover."""
    if rig.backend != "mavlink":
        pytest.skip("the router is the pymavlink backend's: MAVSDK owns its link and refuses mavlink_out")
    drone3 = rig.agents["drone-3"]
    station = PilotStation(f"udpin:127.0.0.1:{rig.router_port}")
    try:
        station.wait_heartbeat()
        kinds = {(m.get_type(), m.get_srcComponent()) for m in drain_for(station, 2.0)}
        assert ("HEARTBEAT", 1) in kinds and ("HEARTBEAT", 191) not in kinds, kinds
        assert not any(kind == "COMMAND_ACK" for kind, _ in kinds), kinds
        for (main, sub), shown in (((4, 4), "AUTO"), ((4, 3), "LOITER")):  # AUTO.MISSION, then Hold
            assert station.command(mavlink.MAV_CMD_DO_SET_MODE, 1, main, sub) == 0  # ACCEPTED
            rig.wait(lambda s=shown: drone3.autopilot.telemetry().mode == s, 10.0, f"drone-3 in {shown}")
        assert rig.d.authority.pilot("drone-3") is None  # on the ground: not a takeover
    finally:
        station.close()

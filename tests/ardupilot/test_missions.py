"""Missions flown end to end on real ArduCopter SITL and on our simulator, through daemon and agents.

The first test submits its mission right after the agents connect, while the vehicles still report
no fix. Each test leaves every vehicle landed and disarmed for the next one.
"""

from __future__ import annotations

import time

import pytest

from agent.autopilot.mavlink_backend import MavlinkAutopilot
from protocol.actions import GoBy, Goto, Hold, Land, ReturnToLaunch, SetSpeed, Takeoff, Waypoint, Waypoints
from protocol.geo import distance_m
from protocol.packets import FenceCircle, Geofence
from tests.ardupilot.rig import HOME, Rig, at, fly_north_then_wait_for
from tests.support.pilot import PilotStation
from tests.support.rig import task

pytestmark = [pytest.mark.ardupilot, pytest.mark.slow, pytest.mark.timeout(240)]

FIRST_LEG_SPEED = 3.0  # neither simulator's WPNAV_SPEED (10 m/s): a lost speed shows
SPEED_TOLERANCE = 0.6
RTL_ALTS = (16.0, 20.0, 24.0)


def peak(rig: Rig, name: str, mission_id: str, step: int) -> float:
    return rig.peak(name, mission_id, step)


def test_synchronized_mission_right_after_connect(rig: Rig) -> None:
    """Takeoff 10/12/14 m, two synced waypoints (the first leg at 3 m/s), RTL at 16/20/24 m.

    Submitted at once: the daemon waits for every fix (and says so) instead of refusing the mission
    with energy figures computed from lat/lon 0,0; the first leg flies at its planned speed; each
    drone returns at its own altitude.
    """
    plans: dict[str, list[object]] = {}
    for i, name in enumerate(rig.names):
        wp1, wp2 = at(60.0, 0.0, i), at(60.0, 20.0, i)
        plans[name] = [
            Takeoff(step=0, alt=10.0 + 2 * i, sync=True),
            Goto(step=1, lat=wp1[0], lon=wp1[1], alt=10.0 + 2 * i, speed=FIRST_LEG_SPEED, sync=True),
            Goto(step=2, lat=wp2[0], lon=wp2[1], alt=10.0 + 2 * i, speed=5.0, sync=True),
            ReturnToLaunch(step=3, alt=RTL_ALTS[i]),
        ]
    mission_id = rig.submit(task("right-after-connect", plans, sync_timeout_s=120))
    progress = rig.finish(mission_id, 200.0)
    assert progress.state == "completed", progress
    if rig.simulator == "arducopter":  # ours boots fast enough that the fix may already be there
        assert rig.events("preflight_waiting"), "the daemon did not say it waited for a fix"
    for i, name in enumerate(rig.names):
        first_leg = peak(rig, name, mission_id, 1)
        assert abs(first_leg - FIRST_LEG_SPEED) <= SPEED_TOLERANCE, (
            f"{name} first leg peak {first_leg:.1f} m/s"
        )
        home = at(0.0, 0.0, i)
        ret = [s for s in rig.flown(name, mission_id, 3) if distance_m(s.lat, s.lon, *home) > 15.0]
        assert ret, f"{name}: no return samples"
        top = max(s.alt for s in ret)
        assert abs(top - RTL_ALTS[i]) < 2.0, f"{name} returned at {top:.1f} m, asked {RTL_ALTS[i]} m"
        assert rig.param(name, "RTL_ALT") == pytest.approx(RTL_ALTS[i] * 100)


def test_pause_and_resume_in_a_speed_limited_goto(rig: Rig) -> None:
    """Pause (BRAKE) mid-leg, resume: the leg goes on at its speed (no DO_CHANGE_SPEED refusal)."""
    plans: dict[str, list[object]] = {}
    for i, name in enumerate(rig.names):
        far = at(90.0, 0.0, i)
        plans[name] = [
            Takeoff(step=0, alt=8.0 + 2 * i, sync=True),
            Goto(step=1, lat=far[0], lon=far[1], alt=8.0 + 2 * i, speed=4.0, sync=True),
            Land(step=2, lat=far[0], lon=far[1]),
        ]
    mission_id = rig.submit(task("pause-resume", plans))
    rig.wait(
        lambda: all(
            a.queue.current_step == 1 and a.autopilot.telemetry().vn > 3.0 for a in rig.agents.values()
        ),
        120.0,
        "every drone cruising on step 1",
    )
    rig.call(rig.d.missions.pause(mission_id, "test pause"))
    rig.wait(lambda: all(abs(a.autopilot.telemetry().vn) < 0.3 for a in rig.agents.values()), 30.0, "stopped")
    paused_at = {n: (a.autopilot.telemetry().lat, a.autopilot.telemetry().lon) for n, a in rig.agents.items()}
    rig.call(rig.d.missions.resume(mission_id, "test resume"))
    progress = rig.finish(mission_id, 150.0)
    assert progress.state == "completed", progress
    assert not rig.events("action_failed"), [e.message for e in rig.events("action_failed")]
    for i, name in enumerate(rig.names):
        after = [
            s
            for s in rig.flown(name, mission_id, 1)
            if distance_m(s.lat, s.lon, *paused_at[name]) > 3.0 and s.mode == "GUIDED"
        ]
        assert after and max(s.speed for s in after) <= 4.0 + SPEED_TOLERANCE
        assert max(s.speed for s in after) >= 4.0 - SPEED_TOLERANCE, f"{name} resumed slowly"
        t = rig.agents[name].autopilot.telemetry()
        assert distance_m(t.lat, t.lon, *at(90.0, 0.0, i)) < 3.0  # landed at the point


def test_set_speed_after_hold_then_go_by_and_waypoints(rig: Rig) -> None:
    """hold, set_speed (refused by ArduCopter in BRAKE: the agent defers it), goto without a
    speed at the set speed, go_by, waypoints at 5 m/s, land at a point."""
    plans: dict[str, list[object]] = {}
    for i, name in enumerate(rig.names):
        a, b, c = at(40.0, 0.0, i), at(40.0, 30.0, i), at(10.0, 30.0, i)
        plans[name] = [
            Takeoff(step=0, alt=8.0 + 2 * i, sync=True),
            Hold(step=1, seconds=1.0),
            SetSpeed(step=2, speed=3.0),
            Goto(step=3, lat=a[0], lon=a[1], alt=8.0 + 2 * i, sync=True),
            GoBy(step=4, north=0.0, east=-10.0, up=2.0),
            Waypoints(
                step=5,
                points=[
                    Waypoint(lat=b[0], lon=b[1], alt=10.0 + 2 * i),
                    Waypoint(lat=c[0], lon=c[1], alt=10.0 + 2 * i),
                ],
                speed=5.0,
                sync=True,
            ),
            Land(step=6, lat=c[0], lon=c[1]),
        ]
    mission_id = rig.submit(task("hold-set-speed", plans))
    progress = rig.finish(mission_id, 200.0)
    assert progress.state == "completed", progress
    for i, name in enumerate(rig.names):
        goto_peak = peak(rig, name, mission_id, 3)
        assert abs(goto_peak - 3.0) <= SPEED_TOLERANCE, f"{name}: goto after set_speed at {goto_peak:.1f} m/s"
        wp_peak = peak(rig, name, mission_id, 5)
        assert abs(wp_peak - 5.0) <= SPEED_TOLERANCE + 0.3, f"{name}: waypoints at {wp_peak:.1f} m/s"
        by = rig.flown(name, mission_id, 4)[-1]
        assert distance_m(by.lat, by.lon, *at(40.0, -10.0, i)) < 4.0  # go_by ended 10 m west of a
        t = rig.agents[name].autopilot.telemetry()
        assert distance_m(t.lat, t.lon, *at(10.0, 30.0, i)) < 3.0


def test_refused_action_ends_the_mission_with_the_autopilot_reason(rig: Rig) -> None:
    """drone-2's autopilot refuses to arm (BATT_ARM_VOLT above the pack voltage): the mission ends,
    naming the agent, the step and ArduCopter's words; the others return to launch."""
    rig.param("drone-2", "BATT_ARM_VOLT", 30.0)
    try:
        plans: dict[str, list[object]] = {
            name: [Takeoff(step=0, alt=6.0, sync=True), GoBy(step=1, north=20.0, east=0.0), Land(step=2)]
            for name in rig.names
        }
        # Only drone-2 gives up arming early: a loaded ArduCopter can refuse a healthy drone for a few
        # seconds ("Need Position Estimate", seen in a full suite run), which the others ride out.
        refused = rig.agents["drone-2"]
        refused.executor.config = refused.config.model_copy(update={"arm_deadline_s": 6.0})
        mission_id = rig.submit(task("refused", plans))
        progress = rig.finish(mission_id, 90.0)
    finally:
        for agent in rig.agents.values():
            agent.executor.config = agent.config
        rig.param("drone-2", "BATT_ARM_VOLT", 0.0)
    assert progress.state == "aborted", progress
    assert progress.result is not None
    assert "drone-2 step 0 (takeoff)" in progress.result, progress.result
    assert "below minimum arming voltage" in progress.result, progress.result


def test_geofence_upload_reaches_the_autopilot(rig: Rig) -> None:
    """A fence from the daemon is installed on the autopilot: FENCE_ENABLE/TYPE/ACTION/ALT_MAX."""
    fence = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=300.0), max_alt_m=60.0)
    sent = rig.call(rig.d.set_geofence(fence, ["drone-1"]))
    assert sent == ["drone-1"]
    rig.wait(lambda: rig.agents["drone-1"].monitor.geofence is not None, 10.0, "fence at the agent")
    try:
        values: dict[str, float] = {}
        wanted = {"FENCE_ENABLE": 1.0, "FENCE_TYPE": 5.0, "FENCE_ACTION": 1.0}
        for _ in range(150):  # the upload and its parameters settle one by one (bounded: 30 s)
            values = {p: rig.param("drone-1", p) for p in wanted}
            if values == wanted:
                break
            time.sleep(0.2)
        assert values == wanted
        assert rig.param("drone-1", "FENCE_ALT_MAX") == pytest.approx(60.0)
    finally:
        rig.call(rig.d.set_geofence(None, ["drone-1"]))
        rig.param("drone-1", "FENCE_ENABLE", 0.0)


def test_a_pilot_takes_one_drone_mid_leg_and_the_others_complete(rig: Rig) -> None:
    """Issue 26: a pilot's ground station on drone-2's SERIAL1 sets LOITER mid-leg. It stays in LOITER
    for 30 s of vehicle time (nothing from the agent switches it back), the daemon shows ``pilot`` and
    excludes it, the other two complete; the pilot lands it where it is. Last in the module: the
    operator's release (landed and disarmed) gives drone-2 back to its agent."""
    assert rig.fleet is not None and rig.fleet.pilot_endpoints
    station = PilotStation(rig.fleet.pilot_endpoints[1])
    try:
        station.wait_heartbeat()
        mission_id = fly_north_then_wait_for(rig, "drone-2", "pilot")
        drone2 = rig.agents["drone-2"]
        assert station.set_mode("LOITER") == 0  # MAV_RESULT_ACCEPTED
        switched = drone2.autopilot.telemetry()
        assert switched.vehicle_time_s is not None
        rig.wait(lambda: rig.d.authority.pilot("drone-2") == "LOITER", 10.0, "the daemon to see the pilot")
        modes: set[str] = set()
        for _ in range(600):  # 30 s of vehicle time (bounded: 60 s of wall time)
            t = drone2.autopilot.telemetry()
            modes.add(t.mode)
            if (t.vehicle_time_s or 0.0) >= switched.vehicle_time_s + 30.0:
                break
            time.sleep(0.1)
        else:
            raise AssertionError("30 s of vehicle time did not pass")
        assert modes == {"LOITER"}, modes
        held = drone2.autopilot.telemetry()
        assert distance_m(held.lat, held.lon, switched.lat, switched.lon) < 15.0
        progress = rig.finish_without(mission_id, "drone-2", 150.0)
        assert progress.state == "completed", progress
        assert any(e.agent == "drone-2" for e in rig.events("agent_excluded"))
        assert station.set_mode("LAND") == 0
        rig.wait(lambda: (t := drone2.autopilot.telemetry()).landed and not t.armed, 60.0, "drone-2 landed")
        down = drone2.autopilot.telemetry()
        assert distance_m(down.lat, down.lon, held.lat, held.lon) < 10.0  # where the pilot landed it
        rig.wait(lambda: rig.d.authority.pilot("drone-2") == "LAND", 10.0, "the daemon to see LAND")
    finally:
        station.close()
        rig.call(rig.d.operator.resume(["drone-2"], "test over"))
        rig.wait(lambda: rig.d.authority.pilot("drone-2") is None, 10.0, "drone-2 released")


def test_a_ground_station_through_the_agents_router_sees_the_vehicle_and_sets_its_mode(rig: Rig) -> None:
    """Issue 26: a "QGroundControl" on UDP, fed by drone-3's agent (``mavlink_out``), sees the
    autopilot's heartbeats but not the agent's frames nor its ACKs, and sets a mode through the
    agent's link (ACCEPTED, its own ACK routed back to it). Landed and disarmed, so no takeover."""
    drone3 = rig.agents["drone-3"]
    station = PilotStation(f"udpin:127.0.0.1:{rig.router_port}")
    try:
        station.wait_heartbeat()
        autopilot = drone3.autopilot
        assert isinstance(autopilot, MavlinkAutopilot) and autopilot.link.router is not None
        router = autopilot.link.router
        withheld = router.stats["withheld"]
        rig.call(autopilot.set_mode("GUIDED"))  # the agent's own command: its ACK stays here
        assert router.stats["withheld"] > withheld
        kinds: set[tuple[str, int]] = set()
        until = time.monotonic() + 2.0  # two heartbeats of vehicle time at the least
        for _ in range(20_000):
            msg = station.conn.recv_match(blocking=True, timeout=0.1)
            if msg is not None:
                kinds.add((msg.get_type(), msg.get_srcComponent()))
            if time.monotonic() > until:
                break
        assert ("HEARTBEAT", 1) in kinds and ("HEARTBEAT", 191) not in kinds, kinds
        assert not any(kind == "COMMAND_ACK" for kind, _ in kinds), kinds
        assert station.set_mode("LOITER") == 0  # MAV_RESULT_ACCEPTED
        rig.wait(lambda: drone3.autopilot.telemetry().mode == "LOITER", 10.0, "drone-3 in LOITER")
        assert rig.d.authority.pilot("drone-3") is None  # on the ground: not a takeover
        assert station.set_mode("GUIDED") == 0
        rig.wait(lambda: drone3.autopilot.telemetry().mode == "GUIDED", 10.0, "drone-3 back in GUIDED")
    finally:
        station.close()

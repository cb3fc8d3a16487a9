"""MavsdkAutopilot (mavsdk 4.x native binding) against the ArduCopter-like simulator over TCP."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest

from agent.autopilot.base import CommandRefused, FenceCircle, FenceSpec, MissionPoint, PilotInControl
from agent.autopilot.mavsdk_backend import MavsdkAutopilot, to_mavsdk_url
from protocol.geo import distance_m, offset_latlon
from tests.backends.conftest import HOME, wait_until
from tests.support.pilot import PilotStation

pytestmark = pytest.mark.slow

mavsdk = pytest.importorskip("mavsdk")


async def connected(fleet: Any, closing: Any) -> MavsdkAutopilot:
    ap = MavsdkAutopilot(fleet.endpoints[0], command_timeout_s=5.0)
    closing(ap)
    await ap.connect(timeout=10.0)
    await wait_until(ap, lambda t: t.has_position, "3D fix and home position", timeout=15.0)
    return ap


async def test_mavsdk_connects_and_reports_telemetry(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    assert to_mavsdk_url(fleet.endpoints[0]).startswith("tcpout://127.0.0.1:")
    ap = await connected(fleet, closing)
    tel = await wait_until(
        ap, lambda t: t.battery_pct is not None and t.mode != "UNKNOWN", "battery and mode"
    )
    assert distance_m(tel.lat, tel.lon, HOME[0], HOME[1]) < 20.0
    assert tel.home_alt_amsl == pytest.approx(HOME[2], abs=5.0)
    assert tel.landed and not tel.armed
    first = tel.last_heartbeat_monotonic
    assert time.monotonic() - first < 3.0
    await wait_until(ap, lambda t: t.last_heartbeat_monotonic > first, "a further heartbeat", timeout=5.0)


async def test_mavsdk_refuses_takeoff_when_disarmed(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    started = time.monotonic()
    with pytest.raises(CommandRefused):
        await ap.takeoff(10.0)
    assert time.monotonic() - started < 6.0


async def test_mavsdk_arm_takeoff_goto_land(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    await ap.arm(deadline_s=20.0)
    await wait_until(ap, lambda t: t.armed, "armed")
    await ap.takeoff(10.0)
    await wait_until(ap, lambda t: t.alt_rel >= 9.5, "takeoff to 10 m", timeout=15.0)
    lat, lon = offset_latlon(HOME[0], HOME[1], 30.0, 0.0)
    await ap.goto(lat, lon, 10.0, speed_mps=8.0)
    await wait_until(ap, lambda t: distance_m(t.lat, t.lon, lat, lon) < 2.0, "arrival", timeout=15.0)
    await ap.land()
    await wait_until(ap, lambda t: t.landed and not t.armed, "landed and disarmed", timeout=20.0)


async def test_mavsdk_fence_and_mission_upload(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    fence = FenceSpec(circle=FenceCircle(HOME[0], HOME[1], 80.0), max_alt_m=40.0, breach_action="land")
    assert await ap.upload_fence(fence) is True
    vehicle = fleet.vehicle(0)
    assert vehicle.params["FENCE_ENABLE"] == 1
    assert vehicle.params["FENCE_ACTION"] == 2
    points = [
        MissionPoint(*offset_latlon(HOME[0], HOME[1], 20.0, 0.0), 10.0),
        MissionPoint(*offset_latlon(HOME[0], HOME[1], 20.0, 20.0), 10.0),
    ]
    await ap.upload_mission(points)
    await ap.arm(deadline_s=20.0)
    await ap.takeoff(10.0)
    await wait_until(ap, lambda t: t.alt_rel >= 9.75, "takeoff to 10 m", timeout=15.0)
    await ap.start_mission()
    last = points[-1]
    await wait_until(
        ap,
        lambda t: (
            # at the last item, or already past it ("Mission complete") when polled late
            t.mode == "AUTO"
            and t.mission_current >= len(points) - 1
            and distance_m(t.lat, t.lon, last.lat, last.lon) < 3
        ),
        "the last waypoint in AUTO",
        timeout=20.0,
    )


async def test_mavsdk_a_pilots_mode_switch_stops_every_moving_command(sim_fleet: Any, closing: Any) -> None:
    """The MAVSDK backend shares the pymavlink backend's pilot gate: a mode the agent did not ask
    for (a second ground station on the vehicle's pilot link) refuses goto, hold, RTL and land."""
    fleet = sim_fleet(pilot_links=True)
    ap = await connected(fleet, closing)
    assert ap.pilot_modes() is not None
    await ap.arm(deadline_s=20.0)
    await ap.takeoff(10.0)
    await wait_until(ap, lambda t: t.alt_rel >= 9.5, "takeoff to 10 m", timeout=15.0)
    lat, lon = offset_latlon(HOME[0], HOME[1], 60.0, 0.0)
    await ap.goto(lat, lon, 10.0, speed_mps=5.0)
    await ap.hold()  # our own modes (GUIDED, BRAKE) one after the other: never the pilot's
    assert ap.telemetry().pilot_mode is None
    station = PilotStation(fleet.pilot_endpoints[0])
    try:
        await asyncio.to_thread(station.wait_heartbeat)
        assert await asyncio.to_thread(station.set_mode, "LOITER") == 0
        await wait_until(ap, lambda t: t.pilot_mode == "LOITER", "the pilot's mode seen", timeout=5.0)
        for command in (ap.goto(lat, lon, 10.0), ap.hold(), ap.return_to_launch(), ap.land()):
            with pytest.raises(PilotInControl):
                await command
        assert fleet.vehicle(0).state.mode == "LOITER"  # nothing of ours reached it
        assert await asyncio.to_thread(station.set_mode, "GUIDED") == 0  # the pilot hands back
        await wait_until(ap, lambda t: t.pilot_mode is None, "the hand-back", timeout=5.0)
        await ap.land()
        await wait_until(ap, lambda t: t.landed, "landed", timeout=30.0)
    finally:
        station.close()

"""MavlinkAutopilot against the in-repo ArduCopter-like simulator, over real loopback TCP."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from typing import Any

import pytest

from agent.autopilot.base import (
    Autopilot,
    CommandRefused,
    FenceCircle,
    FenceSpec,
    LinkLost,
    MissionPoint,
)
from agent.autopilot.mavlink_backend import MavlinkAutopilot
from protocol.geo import distance_m, offset_latlon
from tests.backends.conftest import HOME, wait_until

pytestmark = pytest.mark.slow


async def connected(
    fleet: Any, closing: Callable[[Autopilot], Autopilot], **options: Any
) -> MavlinkAutopilot:
    ap = MavlinkAutopilot(fleet.endpoints[0], **options)
    closing(ap)
    await ap.connect(timeout=10.0)
    await wait_until(ap, lambda t: t.has_position, "3D fix and home position")
    return ap


async def airborne(ap: MavlinkAutopilot, alt: float = 10.0) -> None:
    await ap.arm(deadline_s=20.0)
    await ap.takeoff(alt)
    # 95 % like the agent's executor: the next position target may arrive while the climb finishes.
    await wait_until(ap, lambda t: t.alt_rel >= alt * 0.95, f"takeoff to {alt} m")


async def test_connect_fills_telemetry(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    tel = await wait_until(
        ap,
        lambda t: t.battery_pct is not None and t.satellites > 0 and t.voltage_v is not None,
        "battery and GPS",
    )
    assert distance_m(tel.lat, tel.lon, HOME[0], HOME[1]) < 20.0
    assert tel.home_lat == pytest.approx(HOME[0], abs=1e-4)
    assert tel.home_alt_amsl == pytest.approx(HOME[2], abs=5.0)
    assert abs(tel.alt_amsl - HOME[2]) < 5.0
    assert tel.gps_fix >= 3
    assert 0.0 < tel.battery_pct <= 100.0  # type: ignore[operator]
    assert tel.mode not in ("UNKNOWN", "")
    assert tel.landed and not tel.armed
    assert tel.mission_current == -1
    first = tel.last_heartbeat_monotonic
    assert 0.0 < time.monotonic() - first < 3.0
    # Heartbeats keep arriving (1 Hz real time in the simulator, or faster).
    await wait_until(ap, lambda t: t.last_heartbeat_monotonic > first, "a further heartbeat", timeout=5.0)
    # We identify as the vehicle's companion computer.
    assert ap.link.vehicle is not None
    assert ap.link.vehicle.system == 1


async def test_arm_refused_during_prearm_then_succeeds_by_retrying(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet(prearm_delay_s=40.0)  # ~2 s of wall time at 20x
    ap = MavlinkAutopilot(fleet.endpoints[0])
    closing(ap)
    await ap.connect(timeout=10.0)
    started = time.monotonic()
    with pytest.raises(CommandRefused) as refused:
        await ap.arm(deadline_s=0.5)
    assert time.monotonic() - started < 6.0
    assert "PreArm" in refused.value.reason, refused.value.reason
    await ap.arm(deadline_s=20.0)
    await wait_until(ap, lambda t: t.armed, "armed")
    assert ap.telemetry().mode == "GUIDED"
    assert any("PreArm" in text for text in ap.telemetry().status_texts)


async def test_refused_command_raises_instead_of_hanging(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    started = time.monotonic()
    with pytest.raises(CommandRefused) as refused:
        await ap.takeoff(10.0)  # disarmed: ArduCopter refuses NAV_TAKEOFF
    assert time.monotonic() - started < 3.0
    assert "MAV_RESULT" in refused.value.reason
    with pytest.raises(CommandRefused):
        await ap.goto(HOME[0], HOME[1], 10.0)  # a position target needs an armed vehicle


async def test_takeoff_goto_go_by_hold_and_land(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    await airborne(ap, 10.0)
    assert not ap.telemetry().landed

    lat, lon = offset_latlon(HOME[0], HOME[1], 40.0, 20.0)
    await ap.goto(lat, lon, 15.0, speed_mps=8.0)
    tel = await wait_until(
        ap,
        lambda t: distance_m(t.lat, t.lon, lat, lon) <= 2.0 and abs(t.alt_rel - 15.0) < 1.0,
        "arrival at the goto target",
        timeout=15.0,
    )
    assert tel.mode == "GUIDED"

    assert ap.supports_local_offset()  # AUTOPILOT_VERSION advertises SET_POSITION_TARGET_LOCAL_NED
    start = ap.telemetry()
    await ap.go_by(-10.0, 10.0, -5.0)
    glat, glon = offset_latlon(start.lat, start.lon, -10.0, 10.0)
    await wait_until(
        ap,
        lambda t: (
            distance_m(t.lat, t.lon, glat, glon) <= 2.0 and abs(t.alt_rel - (start.alt_rel - 5.0)) < 1.0
        ),
        "arrival at the go_by offset",
        timeout=15.0,
    )

    far_lat, far_lon = offset_latlon(HOME[0], HOME[1], -100.0, 0.0)
    await ap.goto(far_lat, far_lon, 10.0, speed_mps=10.0)
    await wait_until(ap, lambda t: (t.vn**2 + t.ve**2) ** 0.5 > 3.0, "moving towards a far target")
    await ap.hold()
    await wait_until(ap, lambda t: t.mode in ("BRAKE", "LOITER"), "BRAKE mode")
    await wait_until(ap, lambda t: (t.vn**2 + t.ve**2) ** 0.5 < 0.5, "stopped")
    stopped = ap.telemetry()
    assert distance_m(stopped.lat, stopped.lon, far_lat, far_lon) > 10.0

    await ap.land()
    await wait_until(ap, lambda t: t.mode == "LAND", "LAND mode")
    tel = await wait_until(ap, lambda t: t.landed and not t.armed, "landed and disarmed", timeout=20.0)
    assert tel.alt_rel < 0.5


async def test_land_at_a_point(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    await airborne(ap, 8.0)
    lat, lon = offset_latlon(HOME[0], HOME[1], 25.0, -15.0)
    await ap.land(lat, lon)
    tel = await wait_until(ap, lambda t: t.landed and not t.armed, "landed and disarmed", timeout=20.0)
    assert distance_m(tel.lat, tel.lon, lat, lon) < 3.0


async def test_return_to_launch(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    await airborne(ap, 10.0)
    await ap.set_speed(10.0)
    lat, lon = offset_latlon(HOME[0], HOME[1], 50.0, 0.0)
    await ap.goto(lat, lon, 10.0)
    await wait_until(ap, lambda t: distance_m(t.lat, t.lon, lat, lon) < 3.0, "out at 50 m", timeout=15.0)
    await ap.return_to_launch()
    await wait_until(ap, lambda t: t.mode == "RTL", "RTL mode")
    tel = await wait_until(ap, lambda t: t.landed and not t.armed, "back home and disarmed", timeout=40.0)
    assert distance_m(tel.lat, tel.lon, HOME[0], HOME[1]) < 5.0


async def test_return_to_launch_at_a_given_altitude(sim_fleet: Any, closing: Any) -> None:
    """ReturnToLaunch.alt sets RTL_ALT (cm) first; the vehicle climbs to it and returns at it."""
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    await airborne(ap, 8.0)
    lat, lon = offset_latlon(HOME[0], HOME[1], 40.0, 0.0)
    await ap.goto(lat, lon, 8.0)
    await wait_until(ap, lambda t: distance_m(t.lat, t.lon, lat, lon) < 3.0, "out at 40 m", timeout=15.0)
    await ap.return_to_launch(alt_rel_m=23.0)
    assert await ap.get_param("RTL_ALT") == pytest.approx(2300.0)
    tel = await wait_until(ap, lambda t: t.alt_rel > 21.0, "climb to the return altitude", timeout=15.0)
    assert distance_m(tel.lat, tel.lon, HOME[0], HOME[1]) > 30.0  # climbs before it returns
    tel = await wait_until(
        ap, lambda t: distance_m(t.lat, t.lon, HOME[0], HOME[1]) < 10.0, "back over home", timeout=20.0
    )
    assert tel.alt_rel == pytest.approx(23.0, abs=1.5)


async def peak_ground_speed(ap: MavlinkAutopilot, seconds: float) -> float:
    peak = 0.0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        t = ap.telemetry()
        peak = max(peak, math.hypot(t.vn, t.ve))
        await asyncio.sleep(0.02)
    return peak


async def test_speed_goes_after_the_target_and_survives_a_hold(sim_fleet: Any, closing: Any) -> None:
    """The first leg after takeoff flies at the asked speed, not WPNAV_SPEED (8 m/s here); after a
    hold (BRAKE refuses DO_CHANGE_SPEED) set_speed is kept and goto switches to GUIDED first."""
    fleet = sim_fleet(params={"WPNAV_SPEED": 800})
    ap = await connected(fleet, closing)
    await airborne(ap, 8.0)
    lat, lon = offset_latlon(HOME[0], HOME[1], 200.0, 0.0)
    await ap.goto(lat, lon, 8.0, speed_mps=3.0)
    assert 2.5 < await peak_ground_speed(ap, 0.6) < 3.3
    await ap.hold()
    await wait_until(ap, lambda t: math.hypot(t.vn, t.ve) < 0.3, "stopped by BRAKE", timeout=5.0)
    await ap.set_speed(4.0)  # BRAKE: kept for the next target
    assert ap.telemetry().mode == "BRAKE"
    await ap.goto(lat, lon, 8.0)
    assert ap.telemetry().mode == "GUIDED"
    assert 3.5 < await peak_ground_speed(ap, 0.8) < 4.3
    await ap.hold()
    await wait_until(ap, lambda t: math.hypot(t.vn, t.ve) < 0.3, "stopped again", timeout=5.0)
    await ap.goto(lat, lon, 8.0, speed_mps=2.0)  # resume with a speed: target first, then speed
    assert 1.6 < await peak_ground_speed(ap, 0.8) < 2.3


async def test_fence_upload_and_breach_triggers_rtl(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    fence = FenceSpec(
        polygon=(
            offset_latlon(HOME[0], HOME[1], 60.0, -60.0),
            offset_latlon(HOME[0], HOME[1], 60.0, 60.0),
            offset_latlon(HOME[0], HOME[1], -60.0, 60.0),
            offset_latlon(HOME[0], HOME[1], -60.0, -60.0),
        ),
        circle=FenceCircle(HOME[0], HOME[1], 40.0),
        max_alt_m=30.0,
        breach_action="rtl",
    )
    assert await ap.upload_fence(fence) is True
    assert await ap.get_param("FENCE_ENABLE") == 1
    assert await ap.get_param("FENCE_ACTION") == 1
    assert await ap.get_param("FENCE_ALT_MAX") == pytest.approx(30.0)
    assert int(await ap.get_param("FENCE_TYPE")) & 5 == 5

    await airborne(ap, 10.0)
    lat, lon = offset_latlon(HOME[0], HOME[1], 80.0, 0.0)  # outside the 40 m circle
    await ap.goto(lat, lon, 10.0, speed_mps=8.0)
    await wait_until(ap, lambda t: t.mode == "RTL", "the fence breach switching to RTL", timeout=20.0)
    tel = ap.telemetry()
    assert distance_m(tel.lat, tel.lon, HOME[0], HOME[1]) < 60.0
    assert any("ence" in text for text in tel.status_texts)


async def test_mission_with_legacy_mission_request_flown_in_auto(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet(legacy_mission_request=True)
    ap = await connected(fleet, closing)
    points = [
        MissionPoint(*offset_latlon(HOME[0], HOME[1], 30.0, 0.0), 12.0),
        MissionPoint(*offset_latlon(HOME[0], HOME[1], 30.0, 30.0), 15.0),
        MissionPoint(*offset_latlon(HOME[0], HOME[1], 0.0, 30.0), 12.0),
    ]
    await ap.upload_mission(points)
    await airborne(ap, 10.0)
    await ap.start_mission()
    await wait_until(ap, lambda t: t.mode == "AUTO", "AUTO mode")
    seen: set[int] = set()

    def progressed(t: Any) -> bool:
        seen.add(t.mission_current)
        last = points[-1]
        # at the last item, or already past it ("Mission complete") when polled late
        return t.mission_current >= len(points) - 1 and distance_m(t.lat, t.lon, last.lat, last.lon) < 3.0

    await wait_until(ap, progressed, "the last waypoint", timeout=30.0)
    assert {0, 1, 2} <= seen


async def test_lost_heartbeat_raises_link_lost_quickly_and_recovers(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing, heartbeat_timeout_s=1.0)
    fleet.vehicle(0).inject_link_drop(60.0)  # simulated seconds: 3 s of wall time at 20x
    await wait_until(
        ap,
        lambda t: time.monotonic() - t.last_heartbeat_monotonic > 1.2,
        "the heartbeat going stale",
        timeout=5.0,
    )
    stale = ap.telemetry()
    started = time.monotonic()
    with pytest.raises(LinkLost):
        await ap.arm(deadline_s=10.0)
    with pytest.raises(LinkLost):
        await ap.return_to_launch()
    assert time.monotonic() - started < 0.5
    # Telemetry keeps the last values while the link is down.
    assert ap.telemetry().lat == stale.lat
    assert ap.telemetry().last_heartbeat_monotonic == stale.last_heartbeat_monotonic
    await wait_until(
        ap,
        lambda t: time.monotonic() - t.last_heartbeat_monotonic < 0.5,
        "the heartbeat coming back",
        timeout=10.0,
    )
    await ap.arm(deadline_s=10.0)
    await wait_until(ap, lambda t: t.armed, "armed after the link came back")


async def test_link_lost_during_a_command_wait(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing, heartbeat_timeout_s=1.0, command_timeout_s=5.0, command_retries=3)
    fleet.vehicle(0).inject_link_drop(60.0)
    started = time.monotonic()
    with pytest.raises(LinkLost):
        await ap.set_mode("LOITER")  # sent into the void: ends by LinkLost, not after 15 s of retries
    assert time.monotonic() - started < 3.0


async def test_reverted_stream_is_reasserted(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    seen = ap.link.last_seen
    # Another party (or a reboot) turns GLOBAL_POSITION_INT off on this link.
    ap.link.send_command_long(511, (33, -1))
    deadline = time.monotonic() + 5.0
    while time.monotonic() - seen.get("GLOBAL_POSITION_INT", 0.0) < 0.5:
        assert time.monotonic() < deadline, "the stream never stopped"
        await asyncio.sleep(0.02)
    stopped_at = time.monotonic()
    while time.monotonic() - seen.get("GLOBAL_POSITION_INT", 0.0) > 0.2:
        assert time.monotonic() - stopped_at < 10.0, "the stream was not re-asserted"
        await asyncio.sleep(0.02)


async def test_udp_link_bootstraps_with_our_heartbeat(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet(transport="udp")
    assert fleet.endpoints[0].startswith("udpout:")
    ap = await connected(fleet, closing)  # the vehicle only talks once it has heard us
    await ap.arm(deadline_s=20.0)
    await wait_until(ap, lambda t: t.armed, "armed over UDP")
    await ap.disarm()
    await wait_until(ap, lambda t: not t.armed, "disarmed over UDP")


async def test_rejected_fence_returns_false_and_rejected_mission_raises(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    ring = tuple(offset_latlon(HOME[0], HOME[1], 50.0, -50.0 + i * 0.1) for i in range(701))
    assert await ap.upload_fence(FenceSpec(polygon=ring)) is False  # MAV_MISSION_NO_SPACE
    assert await ap.get_param("FENCE_ENABLE") == 0
    with pytest.raises(CommandRefused, match="MAV_MISSION_NO_SPACE"):
        await ap.upload_mission([MissionPoint(HOME[0], HOME[1], 10.0)] * 700)


async def test_connect_failures_raise_link_lost(sim_fleet: Any, closing: Any) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        free_port = s.getsockname()[1]
    started = time.monotonic()
    with pytest.raises(LinkLost):
        await closing(MavlinkAutopilot(f"tcp:127.0.0.1:{free_port}")).connect(timeout=2.0)
    fleet = sim_fleet()
    with pytest.raises(LinkLost, match="no autopilot heartbeat"):
        await closing(MavlinkAutopilot(fleet.endpoints[0], target_system=7)).connect(timeout=1.0)
    assert time.monotonic() - started < 6.0


async def test_signed_link(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet()
    # The simulator does not sign, so a strict signed link hears nothing it accepts.
    strict = closing(MavlinkAutopilot(fleet.endpoints[0], signing_key="fleet passphrase"))
    with pytest.raises(LinkLost):
        await strict.connect(timeout=1.0)
    await strict.close()
    # Signing our frames while accepting the vehicle's unsigned ones works end to end.
    ap = await connected(fleet, closing, signing_key="ab" * 32, allow_unsigned=True)
    signing = ap.link._conn.mav.signing
    assert signing.sign_outgoing and signing.secret_key == bytes.fromhex("ab" * 32)
    await ap.arm(deadline_s=20.0)
    await wait_until(ap, lambda t: t.armed, "armed over a signed link")


async def test_mission_upload_survives_a_nack(sim_fleet: Any, closing: Any) -> None:
    from agent.autopilot.mavlink_link import mavlink

    fleet = sim_fleet()
    ap = await connected(fleet, closing)
    link = ap.link
    requests = link.subscribe(["MISSION_REQUEST_INT"])
    acks = link.subscribe(["MISSION_ACK"])
    points = [MissionPoint(*offset_latlon(HOME[0], HOME[1], 5.0 * i, 0.0), 10.0) for i in range(1, 31)]
    upload = asyncio.ensure_future(ap.upload_mission(points))
    assert await requests.get(5.0) is not None
    # A stray out-of-sequence item: the vehicle NACKs it (INVALID_SEQUENCE) and the upload goes on.
    stray = mavlink.MAVLink_mission_item_int_message(
        link.target_system, link.target_component, 20, 3, 16, 0, 1, 0, 0, 0, 0, 0, 0, 10.0, 0
    )
    link.send(stray)
    await asyncio.wait_for(upload, 10.0)
    results = []
    while (msg := await acks.get(0.2)) is not None:
        results.append(msg.type)
    assert mavlink.MAV_MISSION_INVALID_SEQUENCE in results
    assert results[-1] == mavlink.MAV_MISSION_ACCEPTED
    assert fleet.vehicle(0).state.mission_count == len(points) + 1
    link.unsubscribe(requests)
    link.unsubscribe(acks)

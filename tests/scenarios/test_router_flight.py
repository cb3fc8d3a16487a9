"""A second ground station through the agent's MAVLink router (issue 26): daemon + an in-process
agent + our simulator, and a pymavlink "QGroundControl" listening on UDP that the agent's router
(``mavlink_out``) sends to, as a pilot's tablet on the field network.

The ground station sees the vehicle's heartbeats but neither the agent's own frames nor the ACKs
addressed to the agent; its mode change reaches the vehicle through the agent's link, and the
agent, which did not ask for that mode, reports the pilot in control.
"""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path
from typing import Any

import pytest

from agent.autopilot.mavlink_router import RouterConfigError, parse_endpoint
from agent.config_file import AutopilotSection
from tests.cooperation.rig import rig, wait_for
from tests.scenarios.scenarios import hover_task
from tests.support.pilot import PILOT_SYSTEM, PilotStation, drain

AGENT_COMPONENT = 191  # MAV_COMP_ID_ONBOARD_COMPUTER


class Listening:
    """Reads the station's socket on a thread while the agent flies (a UDP buffer left unread
    would overflow and hide what the router sent); stop it before the station talks itself."""

    def __init__(self, station: PilotStation) -> None:
        self.station = station
        self.seen: list[Any] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for _ in range(1_000_000):
            if self._stop.is_set():
                return
            msg = self.station.conn.recv_match(blocking=True, timeout=0.1)
            if msg is not None:
                self.seen.append(msg)

    def stop(self) -> list[Any]:
        self._stop.set()
        self._thread.join(5.0)
        return self.seen


@pytest.mark.slow
async def test_a_ground_station_on_the_router_sees_the_vehicle_and_its_mode_change_is_the_pilots(
    tmp_path: Path,
) -> None:
    station = PilotStation("udpin:127.0.0.1:0")
    port = station.conn.port.getsockname()[1]
    try:
        options = {"mavlink_out": [f"udp:127.0.0.1:{port}"]}
        async with rig(tmp_path, 1, autopilot_options=options) as r:
            await asyncio.to_thread(station.wait_heartbeat)
            listening = Listening(station)
            try:
                await r.daemon.missions.submit(hover_task("drone-1"))
                await wait_for(lambda: (s := r.status("drone-1")) is not None and s.step == 1, 60, "hovering")
            finally:
                seen = await asyncio.to_thread(listening.stop)
            heartbeats = {
                (m.get_srcSystem(), m.get_srcComponent()) for m in seen if m.get_type() == "HEARTBEAT"
            }
            assert heartbeats == {(1, 1)}, heartbeats  # the vehicle's, never the agent's (1, 191)
            assert any(m.get_type() == "GLOBAL_POSITION_INT" for m in seen)
            # The agent armed, took off and set streams: none of the ACKs it got came out here.
            acks = [m for m in seen if m.get_type() == "COMMAND_ACK"]
            assert acks == [], [(a.command, a.target_system, a.target_component) for a in acks]
            router = r.agents["drone-1"].autopilot.link.router  # type: ignore[attr-defined]
            assert router.stats["withheld"] >= 3  # there were some: arm, takeoff, streams...
            # The ground station sets LOITER: ACCEPTED, and its ACK reaches it (routed by target).
            assert await asyncio.to_thread(station.set_mode, "LOITER") == 0
            assert r.fleet.vehicle(0).state.mode == "LOITER"
            await wait_for(lambda: r.daemon.authority.pilot("drone-1") == "LOITER", 10, "pilot in control")
            assert r.status("drone-1").pilot == "LOITER"
            assert r.daemon.authority.control("drone-1").level == "pilot"
            later = await asyncio.to_thread(drain, station)
            foreign = [m for m in later if m.get_type() == "COMMAND_ACK" and m.target_system != PILOT_SYSTEM]
            assert foreign == []
            assert any(m.get_type() == "HEARTBEAT" and m.custom_mode == 5 for m in later)  # LOITER
    finally:
        station.close()


def test_endpoints_are_checked_where_they_are_configured() -> None:
    assert str(parse_endpoint("udp:192.168.1.20:14550")) == "udp:192.168.1.20:14550"
    assert parse_endpoint("tcpin::5790").host == "0.0.0.0"
    for bad, why in (("192.168.1.20:14550", "SCHEME:HOST:PORT"), ("udp:host:0", "1..65535")):
        with pytest.raises(RouterConfigError, match=why):
            parse_endpoint(bad)
    section = AutopilotSection.model_validate({"mavlink_out": "udp:127.0.0.1:14550,tcpin:0.0.0.0:5790"})
    assert section.mavlink_out == ["udp:127.0.0.1:14550", "tcpin:0.0.0.0:5790"]
    with pytest.raises(ValueError, match="mavlink-out 'serial:/dev/ttyUSB0'"):
        AutopilotSection(mavlink_out=["serial:/dev/ttyUSB0"])

"""GNSS loss as units (issue 26): the agent names the vehicle's own failsafe and latches it."""

from __future__ import annotations

import time

from agent.autopilot.base import Telemetry
from agent.config import AgentSettings
from agent.monitor import ExceptionMonitor
from agent.pilot import failsafe_name
from tests.support.pilot import ArduPilotModes


class _Backend(ArduPilotModes):
    """A flying ArduCopter that switched to LAND by itself without GPS; records what is asked of it."""

    def __init__(self) -> None:
        self.t = Telemetry(armed=True, landed=False, gps_fix=0, mode="LAND", pilot_mode="LAND")
        self.t.last_heartbeat_monotonic = time.monotonic()
        self.t.status_texts = ["EKF variance", "EKF Failsafe: changed to LAND Mode"]
        self.calls: list[str] = []

    def telemetry(self) -> Telemetry:
        return self.t

    async def return_to_launch(self) -> None:
        self.calls.append("rtl")

    async def land(self) -> None:
        self.calls.append("land")

    async def hold(self) -> None:
        self.calls.append("hold")


def test_failsafe_name_puts_the_lost_position_first() -> None:
    flying = Telemetry(armed=True, landed=False)
    assert failsafe_name(flying, {"gps_lost", "battery_low"}) == "gnss"
    assert failsafe_name(Telemetry(status_texts=["EKF variance"]), set()) == "gnss"  # fix still 3D
    assert failsafe_name(flying, {"battery_critical"}) == "battery"
    usual = ["EKF3 IMU0 is using GPS", "EKF3 IMU0 MAG0 in-flight yaw alignment complete"]
    assert failsafe_name(Telemetry(status_texts=[*usual, "Battery 1 is low"]), set()) == "battery"
    assert failsafe_name(flying, {"fence_breach"}) == "fence"
    assert failsafe_name(Telemetry(status_texts=["Failsafe activated"]), set()) == "vehicle"


async def test_the_vehicles_gnss_failsafe_is_latched_and_the_agents_own_reactions_wait() -> None:
    backend = _Backend()
    interrupted: list[bool] = []
    reports: list[tuple[str, str]] = []

    async def interrupt() -> None:
        interrupted.append(True)

    async def report(name: str, detail: str) -> None:
        reports.append((name, detail))

    contact = [time.monotonic()]
    settings = AgentSettings(lost_link_timeout_s=1.0, lost_link_action="rtl")
    monitor = ExceptionMonitor(backend, settings, lambda: contact[0], interrupt, report)  # type: ignore[arg-type]
    await monitor.check()
    assert monitor.failsafe_text() == "gnss: land"
    assert interrupted and backend.adopted and not monitor.pilot.active
    assert ("vehicle_failsafe_mode", "the vehicle's own failsafe (gnss): mode LAND") in reports
    # The daemon link drops too: the agent's RTL would fight the landing (and needs a position).
    contact[0] -= 5.0
    await monitor.check()
    assert "link_lost" in monitor.active and backend.calls == []
    assert any(n == "link_lost" and "withheld" in d for n, d in reports), reports
    # Down and disarmed: the latch ends.
    backend.t.landed, backend.t.armed = True, False
    await monitor.check()
    assert monitor.failsafe is None


async def test_the_position_failsafe_during_our_own_landing_is_latched_too() -> None:
    """The daemon's emergency land came first (its GPS grace is shorter than the EKF's): the
    autopilot's "EKF variance" with the fix lost still makes it the vehicle's own failsafe."""
    backend = _Backend()
    backend.t.pilot_mode = None  # LAND is the agent's: no mode change to see
    backend.t.status_texts = ["EKF3 IMU0 is using GPS"]
    reports: list[tuple[str, str]] = []

    async def nothing() -> None:
        pass

    async def report(name: str, detail: str) -> None:
        reports.append((name, detail))

    monitor = ExceptionMonitor(backend, AgentSettings(), time.monotonic, nothing, report)  # type: ignore[arg-type]
    await monitor.check()
    assert monitor.failsafe is None  # the fix is lost, but the autopilot has not given up yet
    backend.t.status_texts.append("EKF variance")
    await monitor.check()
    assert monitor.failsafe_text() == "gnss: land" and backend.calls == []
    assert reports[-1][0] == "vehicle_failsafe_mode"


async def test_px4s_position_failsafe_is_read_from_its_heartbeat_without_status_texts() -> None:
    """PX4 sends no STATUSTEXT on its onboard (API) link: its "Failsafe activated" reaches the agent
    only as HEARTBEAT.system_status CRITICAL (measured on real PX4 v1.16 SIH). During the daemon's
    own landing and on a switch to LAND by itself, that makes the mode the vehicle's failsafe."""
    reports: list[tuple[str, str]] = []

    async def nothing() -> None:
        pass

    async def report(name: str, detail: str) -> None:
        reports.append((name, detail))

    for pilot_mode in (None, "LAND"):  # the daemon's LAND first; PX4's own switch from Hold
        backend = _Backend()
        backend.t.pilot_mode, backend.t.status_texts = pilot_mode, []
        monitor = ExceptionMonitor(backend, AgentSettings(), time.monotonic, nothing, report)  # type: ignore[arg-type]
        if pilot_mode is None:
            await monitor.check()
            assert monitor.failsafe is None  # fix lost, PX4 still dead-reckoning (no CRITICAL yet)
        backend.t.autopilot_failsafe = True
        await monitor.check()
        assert monitor.failsafe_text() == "gnss: land", pilot_mode
        assert not monitor.pilot.active and backend.calls == []

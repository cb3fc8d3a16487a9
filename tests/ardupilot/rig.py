"""Daemon + in-process agents (pymavlink backend) + a simulator fleet: ours or real ArduCopter SITL.

The same scenario runs on both simulators, so a behaviour our simulator allows and ArduCopter does
not shows up as a failing test. The daemon and agents are :class:`tests.support.rig.FleetRig`'s
(an event loop in a background thread), so one rig (and one SITL boot) serves a whole test module;
tests are plain functions that call into it. Every wait is bounded.
"""

from __future__ import annotations

from pathlib import Path

from agent.autopilot.base import Autopilot
from agent.autopilot.mavlink_backend import MavlinkAutopilot
from agent.config import AgentSettings
from gcs.cooperation.config import CollisionConfig, CooperationConfig
from protocol.geo import offset_latlon
from sitl.ardupilot import ArduPilotFleet
from sitl.fleet import FleetConfig, SimFleet
from tests.support.rig import FleetRig, Sample

__all__ = ["HOME", "Rig", "Sample", "at"]

HOME = (-35.363261, 149.165230, 584.0)  # ArduPilot's CMAC, where its SITL usually flies
SPACING_M = 10.0  # homes 5 m apart trip the collision monitor's 4 m / 2 m margins on takeoff
SPEEDUP = 5.0
VEHICLES = 3
# A battery that lasts the whole module (about 15 minutes of flight): no battery failsafe midway.
PARAMS = {"BATT_CAPACITY": 50000.0}
# Our simulator with ArduCopter's boot timing (sim seconds): no fix for 12 s, arming after 30 s.
OURS_GPS_BOOT_S = 12.0
OURS_PREARM_S = 30.0


def at(north: float, east: float, index: int = 0) -> tuple[float, float]:
    """Lat/lon ``north``/``east`` metres from vehicle ``index``'s home."""
    lat, lon = offset_latlon(HOME[0], HOME[1], 0.0, SPACING_M * index)
    return offset_latlon(lat, lon, north, east)


class Rig(FleetRig):
    """A running fleet: ``simulator`` is ``"ours"`` or ``"arducopter"``."""

    def __init__(self, simulator: str, binary: str | None, data_dir: Path) -> None:
        super().__init__(simulator, [f"drone-{i + 1}" for i in range(VEHICLES)], data_dir)
        self.simulator = simulator
        self.binary = binary
        self.fleet: SimFleet | ArduPilotFleet | None = None

    speedup = SPEEDUP  # the simulator's speed-up, also the daemon's vehicle time scale

    def boot_fleet(self) -> SimFleet | ArduPilotFleet:
        """Start the simulator fleet this rig flies (a subclass may boot another one)."""
        if self.simulator == "arducopter":
            assert self.binary is not None
            return ArduPilotFleet(
                self.binary,
                VEHICLES,
                HOME,
                SPACING_M,
                self.speedup,
                base_port=0,
                host="127.0.0.1",
                params=PARAMS,
            ).start()
        fleet = SimFleet(
            FleetConfig(
                vehicles=VEHICLES,
                home=HOME,
                base_port=0,
                speedup=self.speedup,
                seed=5,
                spacing_m=SPACING_M,
                prearm_delay_s=OURS_PREARM_S,
                gps_boot_s=OURS_GPS_BOOT_S,
                params={"WPNAV_SPEED": 1000.0, **PARAMS},  # ArduCopter's default speed
            )
        )
        fleet.start()
        return fleet

    def start(self) -> Rig:
        """Boot the simulator, the daemon and the agents; returns as soon as every agent has joined."""
        self.fleet = self.boot_fleet()
        autopilots: list[Autopilot] = [MavlinkAutopilot(e, telemetry_hz=10.0) for e in self.fleet.endpoints]
        try:
            self.start_agents(
                autopilots,
                # Collision avoidance (holds, climbs) would blur what the autopilot does by itself;
                # the energy pre-flight check and the other services stay on.
                CooperationConfig(vehicle_time_scale=self.speedup, collision=CollisionConfig(enabled=False)),
                AgentSettings(status_period_s=0.1),
                arm_deadline_s=30.0,
            )
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        self.stop_agents()
        if self.fleet is not None:
            self.fleet.stop()

    def param(self, name: str, param: str, value: float | None = None) -> float:
        """Read (or write, then read back) an autopilot parameter over the agent's own link."""
        autopilot = self.agents[name].autopilot
        assert isinstance(autopilot, MavlinkAutopilot)
        if value is None:
            return self.call(autopilot.get_param(param))
        return self.call(autopilot.set_param(param, value))

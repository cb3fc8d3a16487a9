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
from gcs.link.beacon import free_udp_port
from protocol.actions import Goto, Land, Takeoff
from protocol.geo import distance_m
from sitl.ardupilot import ArduPilotFleet
from sitl.fleet import FleetConfig, SimFleet
from tests.support.places import at_vehicle
from tests.support.rig import FleetRig, Sample, task

__all__ = ["HOME", "LatchedInternalError", "Rig", "Sample", "at"]

HOME = (-35.363261, 149.165230, 584.0)  # ArduPilot's CMAC, where its SITL usually flies
SPACING_M = 10.0  # homes 5 m apart trip the collision monitor's 4 m / 2 m margins on takeoff
SPEEDUP = 5.0
VEHICLES = 3
# A battery that lasts the whole module (about 15 minutes of flight): no battery failsafe midway.
PARAMS = {"BATT_CAPACITY": 50000.0}
# Our simulator with ArduCopter's boot timing (sim seconds): no fix for 12 s, arming after 30 s.
OURS_GPS_BOOT_S = 12.0
OURS_PREARM_S = 30.0
LATCHED_ERROR = "Internal errors"  # ArduCopter's arm refusal for a latched internal error


class LatchedInternalError(Exception):
    """A test failed on a rig whose ArduCopter latched an internal error (the only failure rerun)."""


def at(north: float, east: float, index: int = 0) -> tuple[float, float]:
    """Lat/lon ``north``/``east`` metres from vehicle ``index``'s home."""
    return at_vehicle(HOME, SPACING_M, north, east, index)


class Rig(FleetRig):
    """A running fleet: ``simulator`` is ``"ours"`` or ``"arducopter"``."""

    def __init__(self, simulator: str, binary: str | None, data_dir: Path) -> None:
        super().__init__(simulator, [f"drone-{i + 1}" for i in range(VEHICLES)], data_dir)
        self.simulator = simulator
        self.binary = binary
        self.fleet: SimFleet | ArduPilotFleet | None = None
        # The last drone's agent routes its MAVLink to a ground station on this UDP port (issue 26).
        self.router_port = 0

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
                pilot_links=True,  # SERIAL1 on loopback: a pilot's ground station (issue 26)
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
                pilot_links=True,
            )
        )
        fleet.start()
        return fleet

    def start(self) -> Rig:
        """Boot the simulator, the daemon and the agents; returns as soon as every agent has joined."""
        self.fleet = self.boot_fleet()
        self.router_port = free_udp_port()
        last = len(self.fleet.endpoints) - 1
        autopilots: list[Autopilot] = [
            MavlinkAutopilot(
                e,
                telemetry_hz=10.0,
                mavlink_out=[f"udp:127.0.0.1:{self.router_port}"] if i == last else (),
            )
            for i, e in enumerate(self.fleet.endpoints)
        ]
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

    def reboot(self) -> None:
        """Stop the simulator fleet, the daemon and the agents, and boot them all again."""
        self.stop()
        self._fresh()
        self.start()

    def latched_internal_error(self) -> str | None:
        """An arm refused for ArduCopter's latched internal error, if any: seen on a loaded 2-core
        machine as "Internal errors 0x100000 ... flow_of_ctrl" (its scheduler overran). The vehicle then
        refuses every arm until it reboots, so the rest of a module on this rig cannot fly."""
        if self.simulator != "arducopter" or self.daemon is None or not self.thread.is_alive():
            return None
        refused = [e.message for e in self.events("action_failed") if LATCHED_ERROR in e.message]
        return refused[0] if refused else None

    def param(self, name: str, param: str, value: float | None = None) -> float:
        """Read (or write, then read back) an autopilot parameter over the agent's own link."""
        autopilot = self.agents[name].autopilot
        assert isinstance(autopilot, MavlinkAutopilot)
        if value is None:
            return self.call(autopilot.get_param(param))
        return self.call(autopilot.set_param(param, value))


def fly_north_then_wait_for(rig: Rig, name: str, label: str, out_m: float = 30.0) -> str:
    """Every drone takes off (8/11/14 m) and flies 90 m north at 5 m/s, then lands; returns the mission
    id once ``name`` is ``out_m`` metres into that leg (where the pilot or GNSS scenarios strike)."""
    plans: dict[str, list[object]] = {}
    for i, n in enumerate(rig.names):
        lat, lon = at(90.0, 0.0, i)
        plans[n] = [
            Takeoff(step=0, alt=8.0 + 3 * i, sync=True),
            Goto(step=1, lat=lat, lon=lon, alt=8.0 + 3 * i, speed=5.0, sync=True),
            Land(step=2),
        ]
    mission_id = rig.submit(task(label, plans))
    agent, home = rig.agents[name], at(0.0, 0.0, rig.names.index(name))

    def out() -> bool:
        t = agent.autopilot.telemetry()
        return agent.queue.current_step == 1 and distance_m(t.lat, t.lon, *home) > out_m

    rig.wait(out, 90.0, f"{name} {out_m:.0f} m into its leg")
    return mission_id

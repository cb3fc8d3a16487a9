"""Daemon + in-process agents (pymavlink backend) + a simulator fleet: ours or real ArduCopter SITL.

The same scenario runs on both simulators, so a behaviour our simulator allows and ArduCopter does
not shows up as a failing test. The daemon and agents live on an event loop in a background thread
so that one rig (and one SITL boot) serves a whole test module; tests are plain functions that call
into it. Every wait is bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import secrets
import threading
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from agent.autopilot.mavlink_backend import MavlinkAutopilot
from agent.config import AgentConfig, AgentSettings
from agent.runtime import Agent
from gcs.config import DaemonConfig
from gcs.cooperation.config import CollisionConfig, CooperationConfig
from gcs.daemon import Daemon
from gcs.missions import MissionProgress
from protocol.geo import offset_latlon
from protocol.taskfile import TaskFile
from sitl.ardupilot import ArduPilotFleet
from sitl.fleet import FleetConfig, SimFleet

T = TypeVar("T")

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


@dataclass
class Sample:
    """One telemetry sample of one agent's autopilot (wall time, step being flown)."""

    t: float
    step: int
    mission_id: str | None
    speed: float
    alt: float
    lat: float
    lon: float
    mode: str


class Rig:
    """A running fleet: ``simulator`` is ``"ours"`` or ``"arducopter"``."""

    def __init__(self, simulator: str, binary: str | None, data_dir: Path) -> None:
        self.simulator = simulator
        self.binary = binary
        self.data_dir = data_dir
        self.names = [f"drone-{i + 1}" for i in range(VEHICLES)]
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name=f"rig-{simulator}", daemon=True)
        self.fleet: SimFleet | ArduPilotFleet | None = None
        self.daemon: Daemon | None = None
        self.agents: dict[str, Agent] = {}
        self.samples: dict[str, list[Sample]] = {n: [] for n in self.names}
        self._tasks: list[asyncio.Task[Any]] = []
        self.connected_at = 0.0

    # --- lifecycle --------------------------------------------------------------------------------

    def start(self) -> Rig:
        """Boot the simulator, the daemon and the agents; returns as soon as every agent has joined."""
        if self.simulator == "arducopter":
            assert self.binary is not None
            self.fleet = ArduPilotFleet(
                self.binary, VEHICLES, HOME, SPACING_M, SPEEDUP, base_port=0, host="127.0.0.1", params=PARAMS
            ).start()
        else:
            self.fleet = SimFleet(
                FleetConfig(
                    vehicles=VEHICLES,
                    home=HOME,
                    base_port=0,
                    speedup=SPEEDUP,
                    seed=5,
                    spacing_m=SPACING_M,
                    prearm_delay_s=OURS_PREARM_S,
                    gps_boot_s=OURS_GPS_BOOT_S,
                    params={"WPNAV_SPEED": 1000.0, **PARAMS},  # ArduCopter's default speed
                )
            )
            self.fleet.start()
        self.thread.start()
        try:
            self.call(self._start(), timeout=60.0)
        except BaseException:
            self.stop()
            raise
        return self

    async def _start(self) -> None:
        assert self.fleet is not None
        key = secrets.token_hex(32)
        self.daemon = Daemon(
            DaemonConfig(
                listen_port=0,
                http_host=None,
                data_dir=self.data_dir,
                fleet_key_hex=key,
                status_period_s=0.1,
                lost_after_periods=50.0,
                # Collision avoidance (holds, climbs) would blur what the autopilot does by itself;
                # the energy pre-flight check and the other services stay on.
                cooperation=CooperationConfig(
                    vehicle_time_scale=SPEEDUP, collision=CollisionConfig(enabled=False)
                ),
            )
        )
        await self.daemon.start()
        for name, endpoint in zip(self.names, self.fleet.endpoints, strict=True):
            agent = Agent(
                AgentConfig(
                    identity=name,
                    gcs_port=self.daemon.listen_port,
                    key_hex=key,
                    settings=AgentSettings(status_period_s=0.1),
                    reconnect_min_s=0.05,
                    reconnect_max_s=0.5,
                    resend_target_s=1.0,
                    monitor_period_s=0.1,
                    arm_deadline_s=30.0,
                ),
                MavlinkAutopilot(endpoint, telemetry_hz=10.0),
            )
            self.agents[name] = agent
            self._tasks.append(asyncio.create_task(agent.run(), name=f"agent-{name}"))
        deadline = time.monotonic() + 40.0
        while not all(self.daemon.agents.session(n) is not None for n in self.names):
            if time.monotonic() > deadline:
                raise AssertionError("agents did not join within 40 s")
            await asyncio.sleep(0.05)
        self.connected_at = time.monotonic()
        self._tasks.append(asyncio.create_task(self._sample(), name="sampler"))

    async def _sample(self) -> None:
        while True:
            now = time.monotonic()
            for name, agent in self.agents.items():
                t = agent.autopilot.telemetry()
                if t.position_known:
                    self.samples[name].append(
                        Sample(
                            now,
                            agent.queue.current_step,
                            agent.queue.mission_id,
                            math.hypot(t.vn, t.ve),
                            t.alt_rel,
                            t.lat,
                            t.lon,
                            t.mode,
                        )
                    )
            await asyncio.sleep(0.05)

    def stop(self) -> None:
        if self.thread.is_alive():
            with contextlib.suppress(Exception):
                self.call(self._stop(), timeout=30.0)
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10.0)
        if self.fleet is not None:
            self.fleet.stop()

    async def _stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self.daemon is not None:
            await self.daemon.stop()

    # --- calls into the loop ----------------------------------------------------------------------

    def call(self, coro: Coroutine[Any, Any, T], timeout: float = 30.0) -> T:
        """Run ``coro`` on the rig's loop and return its result (bounded)."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def run(self, fn: Callable[[], T]) -> T:
        """Evaluate ``fn`` on the loop thread (reads of daemon state without races)."""

        async def wrapper() -> T:
            return fn()

        return self.call(wrapper(), timeout=10.0)

    def wait(self, predicate: Callable[[], object], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.run(predicate):
                return
            time.sleep(0.1)
        raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")

    # --- daemon helpers ---------------------------------------------------------------------------

    @property
    def d(self) -> Daemon:
        assert self.daemon is not None
        return self.daemon

    def submit(self, task: TaskFile) -> str:
        return self.call(self.d.missions.submit(task), timeout=task.fix_wait_s + 30.0)

    def finish(self, mission_id: str, timeout: float) -> MissionProgress:
        """Wait for the mission to end, then for every vehicle to be landed and disarmed."""
        self.wait(lambda: mission_id not in self.d.missions.active, timeout, f"mission {mission_id} to end")
        self.wait(self.all_landed, 90.0, "every vehicle landed and disarmed")
        progress = self.run(lambda: self.d.missions.progress(mission_id))
        assert progress is not None
        return progress

    def all_landed(self) -> bool:
        return all((t := a.autopilot.telemetry()).landed and not t.armed for a in self.agents.values())

    def events(self, kind: str, agent: str | None = None) -> list[Any]:
        return self.run(lambda: self.d.events.history(kind=kind, agent=agent))

    def param(self, name: str, param: str, value: float | None = None) -> float:
        """Read (or write, then read back) an autopilot parameter over the agent's own link."""
        autopilot = self.agents[name].autopilot
        assert isinstance(autopilot, MavlinkAutopilot)
        if value is None:
            return self.call(autopilot.get_param(param))
        return self.call(autopilot.set_param(param, value))

    def flown(self, name: str, mission_id: str, step: int) -> list[Sample]:
        return [s for s in self.samples[name] if s.mission_id == mission_id and s.step == step]

"""A real simulator fleet, in-process agents on the MAVLink backend, and a daemon, all on loopback.

Every wait is bounded. The simulator runs at SPEEDUP x; agent timers that are in wall time
(target re-send, status period) are shortened to match.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import secrets
import threading
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.autopilot.mavlink_backend import MavlinkAutopilot
from agent.config import AgentConfig, AgentSettings
from agent.runtime import Agent
from gcs.config import DaemonConfig
from gcs.cooperation.config import CooperationConfig
from gcs.cooperation.service import CooperationService
from gcs.daemon import Daemon
from protocol.geo import ned_offset_m, offset_latlon
from sitl.fleet import FleetConfig, SimFleet

HOME = (47.397742, 8.545594, 488.0)
SPEEDUP = 8.0
SPACING_M = 6.0


def at(north: float, east: float) -> tuple[float, float]:
    """Lat/lon ``north``/``east`` metres from the first home."""
    return offset_latlon(HOME[0], HOME[1], north, east)


async def wait_for(predicate: Callable[[], object], timeout: float, what: str, poll: float = 0.05) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        await asyncio.sleep(poll)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


@dataclass
class Rig:
    daemon: Daemon
    fleet: SimFleet
    agents: dict[str, Agent]
    names: list[str]
    truth: list[list[tuple[float, ...]]] = field(default_factory=list)  # per sample: per vehicle
    make_agent: Callable[[str, int], Agent] | None = None
    tasks: dict[str, asyncio.Task[None]] = field(default_factory=dict)

    async def restart_agent(self, name: str) -> None:
        """Kill the agent process stand-in (its queue is lost) and start a fresh one on the same vehicle."""
        assert self.make_agent is not None
        task = self.tasks[name]
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
        agent = self.make_agent(name, self.daemon.listen_port)
        self.agents[name] = agent
        self.tasks[name] = asyncio.create_task(agent.run(), name=f"agent-{name}")

    async def restart_daemon(self) -> None:
        """Stop the daemon and start a new one on the same port and data directory."""
        port, config = self.daemon.listen_port, self.daemon.config
        await self.daemon.stop()
        self.daemon = Daemon(config.model_copy(update={"listen_port": port}))
        await self.daemon.start()

    @property
    def coop(self) -> CooperationService:
        return next(s for s in self.daemon.services if isinstance(s, CooperationService))

    def events(self, kind: str, agent: str | None = None) -> list[Any]:
        return self.daemon.events.history(kind=kind, agent=agent)

    def status(self, name: str) -> Any:
        session = self.daemon.agents.session(name)
        return session.status if session else None

    def landed(self, name: str) -> bool:
        s = self.status(name)
        return bool(s and s.landed and not s.armed)


def assert_pair_separated(truth: list[list[tuple[float, ...]]]) -> float:
    """Ground truth of two vehicles: never inside a 2 m x 1 m bubble of each other while both are
    in the air; returns their closest 3-D distance then."""
    closest = math.inf
    for row in truth:
        (n1, e1, u1, air1), (n2, e2, u2, air2) = row
        if air1 and air2:
            h, v = math.hypot(n1 - n2, e1 - e2), abs(u1 - u2)
            assert not (h < 2.0 and v < 1.0), f"drones within {h:.1f} m / {v:.1f} m"
            closest = min(closest, math.hypot(h, v))
    return closest


def mavlink_agent(
    name: str,
    port: int,
    key: str,
    endpoint: str,
    settings: AgentSettings | None = None,
    options: dict[str, Any] | None = None,
) -> Agent:
    """An in-process agent on the MAVLink backend, its timers shortened for SPEEDUP (``options``:
    more AgentConfig fields)."""
    return Agent(
        AgentConfig(
            identity=name,
            gcs_port=port,
            key_hex=key,
            settings=(settings or AgentSettings(status_period_s=0.05)).model_copy(),
            reconnect_min_s=0.05,
            reconnect_max_s=0.5,
            resend_target_s=0.4,
            monitor_period_s=0.05,
            **(options or {}),
        ),
        MavlinkAutopilot(endpoint, telemetry_hz=20.0),
    )


def start_sim_fleet(vehicles: int, spacing_m: float = SPACING_M, **options: Any) -> SimFleet:
    """Our simulator at SPEEDUP x around HOME (seeded), started; the caller stops it."""
    fleet = SimFleet(
        FleetConfig(
            vehicles=vehicles,
            home=HOME,
            base_port=0,
            speedup=SPEEDUP,
            seed=3,
            spacing_m=spacing_m,
            prearm_delay_s=1.0,
            **options,
        )
    )
    fleet.start()
    return fleet


def _sample_truth(fleet: SimFleet, out: list[list[tuple[float, ...]]], stop: threading.Event) -> None:
    """Ground truth positions (north, east, up) from the simulator, for separation checks."""
    while not stop.is_set():
        row = []
        for v in fleet.vehicles:
            s = v.state
            n, e = ned_offset_m(HOME[0], HOME[1], s.lat, s.lon)
            row.append((n, e, s.alt_amsl, 0.0 if s.landed else 1.0))
        out.append(tuple(row))  # type: ignore[arg-type]
        stop.wait(0.02)


@contextlib.asynccontextmanager
async def rig(
    tmp_path: Path,
    vehicles: int,
    cooperation: CooperationConfig | None = None,
    settings: AgentSettings | None = None,
    fleet_options: dict[str, Any] | None = None,
    spacing_m: float = SPACING_M,
    agent_options: dict[str, Any] | None = None,
    **daemon_options: Any,
) -> AsyncIterator[Rig]:
    key = secrets.token_hex(32)
    coop = cooperation or CooperationConfig(vehicle_time_scale=SPEEDUP)
    config = DaemonConfig(
        listen_port=0,
        http_host=None,
        data_dir=tmp_path,
        fleet_key_hex=key,
        status_period_s=0.05,
        lost_after_periods=40.0,
        cooperation=coop,
        **daemon_options,
    )
    fleet = start_sim_fleet(vehicles, spacing_m, **(fleet_options or {}))
    daemon = Daemon(config)
    await daemon.start()
    names = [f"drone-{i + 1}" for i in range(vehicles)]
    endpoints = dict(zip(names, fleet.endpoints, strict=True))
    agents: dict[str, Agent] = {}
    stop = threading.Event()
    truth: list[list[tuple[float, ...]]] = []
    sampler = threading.Thread(target=_sample_truth, args=(fleet, truth, stop), daemon=True)

    def make_agent(name: str, port: int) -> Agent:
        return mavlink_agent(name, port, key, endpoints[name], settings, agent_options)

    the_rig = Rig(daemon, fleet, agents, names, truth, make_agent)
    tasks = the_rig.tasks
    try:
        for name in names:
            agent = make_agent(name, daemon.listen_port)
            agents[name] = agent
            tasks[name] = asyncio.create_task(agent.run(), name=f"agent-{name}")
            # One at a time, so CIDs follow the names.
            await wait_for(lambda n=name: daemon.agents.session(n) is not None, 20, f"{name} joins")  # type: ignore[misc]
        await wait_for(
            lambda: all(
                (s := daemon.agents.session(n)) and s.status and s.status.gps.fix >= 3 for n in names
            ),
            20,
            "GPS fix everywhere",
        )
        sampler.start()
        yield the_rig
    finally:
        stop.set()
        for task in tasks.values():
            task.cancel()
        for task in tasks.values():
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        await the_rig.daemon.stop()
        fleet.stop()

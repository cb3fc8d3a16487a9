"""A real simulator fleet, in-process agents on the MAVLink backend, and a daemon, all on loopback.

Every wait is bounded. The simulator runs at SPEEDUP x; agent timers that are in wall time
(target re-send, status period) are shortened to match.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import secrets
import threading
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.autopilot.mavlink_backend import MavlinkAutopilot
from agent.config import AgentConfig, AgentSettings
from agent.runtime import Agent
from gcs.cooperation.config import CooperationConfig
from gcs.cooperation.service import CooperationService
from gcs.core.config import DaemonConfig
from gcs.core.daemon import Daemon
from protocol.actions import Goto, Land, Takeoff
from protocol.geo import ned_offset_m
from protocol.taskfile import AgentPlan, TaskFile
from sitl.fleet import FleetConfig, SimFleet
from tests.support import polling
from tests.support.places import HOME, at

SPEEDUP = 8.0
SPACING_M = 6.0

wait_for = functools.partial(polling.wait_for, poll=0.05)
"""The one bounded poll at 20 Hz: flight tests' predicates record what they see (modes, tracks) at the rate
they were written for; a faster poll sees a vehicle's transients they never meant to judge."""


Interpose = Callable[[str, int, str], Awaitable[tuple[int, str]]]
"""(agent name, daemon port, vehicle endpoint) -> the daemon port and endpoint the agent uses
instead: a link in between (tests/faults/links.py)."""


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
    autopilot: dict[str, Any] | None = None,
) -> Agent:
    """An in-process agent on the MAVLink backend, its timers shortened for SPEEDUP (``options``:
    more AgentConfig fields, ``autopilot``: MavlinkAutopilot options)."""
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
        MavlinkAutopilot(endpoint, **{"telemetry_hz": 20.0, **(autopilot or {})}),
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
    interpose: Interpose | None = None,
    autopilot_options: dict[str, Any] | None = None,
    **daemon_options: Any,
) -> AsyncIterator[Rig]:
    """``interpose``: put links between each agent and the daemon / its vehicle (started once per
    agent; a restarted agent uses the same ones)."""
    key = secrets.token_hex(32)
    coop = cooperation or CooperationConfig(vehicle_time_scale=SPEEDUP)
    config = DaemonConfig(
        listen_port=0,
        http_host=daemon_options.pop("http_host", None),  # no HTTP API unless a test asks for it
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

    routes: dict[str, tuple[int, str]] = {}

    def make_agent(name: str, port: int) -> Agent:
        port, endpoint = routes.get(name, (port, endpoints[name]))
        return mavlink_agent(name, port, key, endpoint, settings, agent_options, autopilot_options)

    the_rig = Rig(daemon, fleet, agents, names, truth, make_agent)
    tasks = the_rig.tasks
    try:
        for name in names:
            if interpose is not None:
                routes[name] = await interpose(name, daemon.listen_port, endpoints[name])
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


HEAD_ON_ALT_M = 10.0
"""Both drones of the head-on course fly at this height (no vertical separation to lean on)."""


def head_on_task() -> TaskFile:
    """Step 1 lines both up on the same north-south line; step 2 swaps them, head-on, same altitude."""
    east = SPACING_M / 2
    south, north = at(-25.0, east), at(25.0, east)
    plans = [
        AgentPlan(
            agent="drone-1",
            actions=[
                Takeoff(step=0, alt=HEAD_ON_ALT_M, sync=True),
                Goto(step=1, lat=south[0], lon=south[1], alt=HEAD_ON_ALT_M, speed=5.0, sync=True),
                Goto(step=2, lat=north[0], lon=north[1], alt=HEAD_ON_ALT_M, speed=5.0, sync=True),
                Land(step=3),
            ],
        ),
        AgentPlan(
            agent="drone-2",
            actions=[
                Takeoff(step=0, alt=HEAD_ON_ALT_M, sync=True),
                Goto(step=1, lat=north[0], lon=north[1], alt=HEAD_ON_ALT_M, speed=5.0, sync=True),
                Goto(step=2, lat=south[0], lon=south[1], alt=HEAD_ON_ALT_M, speed=5.0, sync=True),
                Land(step=3),
            ],
        ),
    ]
    return TaskFile(name="head-on", plans=plans)

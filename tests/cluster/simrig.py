"""Two clustered daemons (and a fleet of our simulator's vehicles, each agent linked to one daemon).

The agents fly the MAVLink backend against :class:`sitl.fleet.SimFleet` (as tests/cooperation/rig.py
does for one daemon); the simulator's ground truth is sampled for separation checks. Every wait is
bounded and everything started is stopped.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.runtime import Agent
from gcs.cooperation.config import CooperationConfig
from gcs.core.daemon import Daemon
from sitl.fleet import SimFleet
from tests.backbone.helpers import daemon_config, new_key
from tests.cooperation.rig import SPEEDUP, _sample_truth, mavlink_agent, start_sim_fleet, wait_for


@contextlib.asynccontextmanager
async def two_daemons(
    tmp_path: Path, servers: str, key: str, **overrides: object
) -> AsyncIterator[tuple[Daemon, Daemon]]:
    """Daemons gcs-a then gcs-b on one NATS (a starts first, so it holds the airspace lease)."""
    async with cluster_daemons(tmp_path, servers, key, ("a", "b"), **overrides) as (a, b):
        yield a, b


@contextlib.asynccontextmanager
async def cluster_daemons(
    tmp_path: Path, servers: str, key: str, names: tuple[str, ...], **overrides: object
) -> AsyncIterator[list[Daemon]]:
    """Daemons gcs-<name> started in order on one NATS, HTTP on a free port (token "t")."""
    daemons = []
    try:
        for name in names:
            config = daemon_config(
                tmp_path / name,
                key,
                cluster=servers,
                daemon_id=f"gcs-{name}",
                http_host="127.0.0.1",
                http_port=0,
                api_token="t",
                **overrides,
            )
            daemon = Daemon(config)
            await daemon.start()
            daemons.append(daemon)
        yield daemons
    finally:
        for daemon in reversed(daemons):
            await daemon.stop()


@dataclass
class SpreadRig:
    a: Daemon
    b: Daemon
    fleet: SimFleet
    agents: dict[str, Agent]
    links: dict[str, str]  # agent -> "a" or "b"
    truth: list[list[tuple[float, ...]]] = field(default_factory=list)

    def holder(self, name: str) -> Daemon:
        return self.a if self.links[name] == "a" else self.b

    def status(self, name: str) -> Any:
        session = self.holder(name).agents.session(name)
        return session.status if session else None

    def landed(self, name: str) -> bool:
        s = self.status(name)
        return bool(s and s.landed and not s.armed)


@contextlib.asynccontextmanager
async def spread_rig(
    tmp_path: Path, nats_url: str, links: dict[str, str], cooperation: CooperationConfig | None = None
) -> AsyncIterator[SpreadRig]:
    """``links``: agent name -> the daemon ("a" or "b") it connects to, in CID order."""
    key = new_key()
    names = list(links)
    fleet = start_sim_fleet(len(names))
    stop = threading.Event()
    tasks: list[asyncio.Task[None]] = []
    try:
        async with two_daemons(
            tmp_path,
            nats_url,
            key,
            status_period_s=0.05,
            lost_after_periods=40.0,
            cooperation=cooperation or CooperationConfig(vehicle_time_scale=SPEEDUP),
        ) as (a, b):
            rig = SpreadRig(a, b, fleet, {}, links)
            for name, endpoint in zip(names, fleet.endpoints, strict=True):
                port = (a if links[name] == "a" else b).listen_port
                agent = mavlink_agent(name, port, key, endpoint)
                rig.agents[name] = agent
                tasks.append(asyncio.create_task(agent.run(), name=f"agent-{name}"))
                # One at a time, so CIDs follow the names.
                joined = rig.holder(name).agents
                await wait_for(lambda n=name, j=joined: j.session(n) is not None, 20, f"{name} joins")  # type: ignore[misc]
            await wait_for(
                lambda: all(
                    (s := d.agents.session(n)) and s.status and s.status.gps.fix >= 3
                    for n in names
                    for d in (a, b)
                ),
                30,
                "every vehicle with a fix, seen from both daemons",
            )
            sampler = threading.Thread(target=_sample_truth, args=(fleet, rig.truth, stop), daemon=True)
            sampler.start()
            try:
                yield rig
            finally:
                stop.set()
                for task in tasks:
                    task.cancel()
                for task in tasks:
                    with contextlib.suppress(asyncio.CancelledError, Exception):
                        await task
    finally:
        stop.set()
        fleet.stop()

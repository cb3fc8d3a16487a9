"""What the real-autopilot rigs share (tests/ardupilot, tests/px4): an in-process daemon and agents on an
event loop in a background thread, fed by an autopilot per vehicle, so one simulator boot serves a whole
test module and tests are plain functions that call into the loop. Every wait is bounded.

A subclass boots its simulator, then calls :meth:`FleetRig.start` with the agents' autopilots.
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

from agent.autopilot.base import Autopilot
from agent.config import AgentConfig, AgentSettings
from agent.runtime import Agent
from gcs.cooperation.config import CooperationConfig
from gcs.core.config import DaemonConfig
from gcs.core.daemon import Daemon
from gcs.missions.runner import MissionProgress
from protocol.taskfile import AgentPlan, TaskFile
from tests.faults.proxy import FaultProxy

T = TypeVar("T")


def task(name: str, plans: dict[str, list[object]], **options: object) -> TaskFile:
    """A task file from ``{agent: [actions]}`` plus top-level options."""
    return TaskFile.model_validate(
        {"name": name, "plans": [AgentPlan(agent=a, actions=acts).model_dump() for a, acts in plans.items()]}  # type: ignore[arg-type]
        | options
    )


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


class FleetRig:
    """Daemon + agents for ``names``; ``proxy=True`` puts a :class:`FaultProxy` between them (lost links)."""

    def __init__(self, label: str, names: list[str], data_dir: Path, *, proxy: bool = False) -> None:
        self.names = names
        self.data_dir = data_dir
        self._label = label
        self._use_proxy = proxy
        self._fresh()

    def _fresh(self) -> None:
        """A new loop and empty state: what :meth:`start_agents` needs, also after :meth:`stop_agents`."""
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name=f"rig-{self._label}", daemon=True)
        self.daemon: Daemon | None = None
        self.proxy: FaultProxy | None = None
        self.agents: dict[str, Agent] = {}
        self.samples: dict[str, list[Sample]] = {n: [] for n in self.names}
        self._tasks: list[asyncio.Task[Any]] = []
        self.connected_at = 0.0

    # --- lifecycle --------------------------------------------------------------------------------

    def start_agents(
        self,
        autopilots: list[Autopilot],
        cooperation: CooperationConfig,
        settings: AgentSettings,
        join_timeout: float = 40.0,
        **agent_options: Any,
    ) -> None:
        """Start the loop, the daemon and one agent per autopilot; returns once every agent has joined."""
        self.thread.start()
        starting = self._start(autopilots, cooperation, settings, join_timeout, agent_options)
        self.call(starting, join_timeout + 20)

    async def _start(
        self,
        autopilots: list[Autopilot],
        cooperation: CooperationConfig,
        settings: AgentSettings,
        join_timeout: float,
        agent_options: dict[str, Any],
    ) -> None:
        key = secrets.token_hex(32)
        self.daemon = Daemon(
            DaemonConfig(
                listen_port=0,
                http_host=None,
                data_dir=self.data_dir,
                fleet_key_hex=key,
                status_period_s=0.1,
                lost_after_periods=50.0,
                cooperation=cooperation,
            )
        )
        await self.daemon.start()
        port = self.daemon.listen_port
        if self._use_proxy:
            self.proxy = await FaultProxy(port).start()
            port = self.proxy.port
        for name, autopilot in zip(self.names, autopilots, strict=True):
            agent = Agent(
                AgentConfig(
                    identity=name,
                    gcs_port=port,
                    key_hex=key,
                    settings=settings.model_copy(),
                    reconnect_min_s=0.05,
                    reconnect_max_s=0.5,
                    resend_target_s=1.0,
                    monitor_period_s=0.1,
                    **agent_options,
                ),
                autopilot,
            )
            self.agents[name] = agent
            self._tasks.append(asyncio.create_task(agent.run(), name=f"agent-{name}"))
        deadline = time.monotonic() + join_timeout
        while not all(self.daemon.agents.session(n) is not None for n in self.names):
            if time.monotonic() > deadline:
                raise AssertionError(f"agents did not join within {join_timeout:.0f} s")
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

    def stop_agents(self) -> None:
        """Stop agents, proxy, daemon and the loop thread (bounded; never raises)."""
        if self.thread.is_alive():
            with contextlib.suppress(Exception):
                self.call(self._stop(), timeout=30.0)
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10.0)

    async def _stop(self) -> None:
        for task_ in self._tasks:
            task_.cancel()
        for task_ in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task_
        if self.proxy is not None:
            await self.proxy.stop()
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

    def submit(self, task_file: TaskFile) -> str:
        return self.call(self.d.missions.submit(task_file), timeout=task_file.fix_wait_s + 30.0)

    def finish(self, mission_id: str, timeout: float, landed_timeout: float = 90.0) -> MissionProgress:
        """Wait for the mission to end, then for every vehicle to be landed and disarmed."""
        self.wait(lambda: mission_id not in self.d.missions.active, timeout, f"mission {mission_id} to end")
        self.wait(self.all_landed, landed_timeout, "every vehicle landed and disarmed")
        progress = self.run(lambda: self.d.missions.progress(mission_id))
        assert progress is not None
        return progress

    def finish_without(self, mission_id: str, left: str, timeout: float) -> MissionProgress:
        """Wait for the mission to end, then for every vehicle but ``left`` to be landed and disarmed."""
        self.wait(lambda: mission_id not in self.d.missions.active, timeout, f"mission {mission_id} to end")
        others = [a for n, a in self.agents.items() if n != left]
        down = lambda: all((t := a.autopilot.telemetry()).landed and not t.armed for a in others)  # noqa: E731
        self.wait(down, 90.0, f"every vehicle but {left} landed and disarmed")
        progress = self.run(lambda: self.d.missions.progress(mission_id))
        assert progress is not None
        return progress

    def all_landed(self) -> bool:
        return all((t := a.autopilot.telemetry()).landed and not t.armed for a in self.agents.values())

    def events(self, kind: str, agent: str | None = None) -> list[Any]:
        return self.run(lambda: self.d.events.history(kind=kind, agent=agent))

    def flown(self, name: str, mission_id: str, step: int) -> list[Sample]:
        return [s for s in self.samples[name] if s.mission_id == mission_id and s.step == step]

    def peak(self, name: str, mission_id: str, step: int) -> float:
        flown = self.flown(name, mission_id, step)
        assert flown, f"{name} has no samples of step {step}"
        return max(s.speed for s in flown)

"""Barrier timers: a sync step some members reached but not all, and one nobody is working towards.

Why apart: the two timers decide *when* the lost-agent policy applies, not what it does (that is
gcs/missions/policies.py, handed in as ``lost_policy``); timers that fire after a pause or a
takeover check the lease first and decide nothing for a forgotten mission.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import Protocol

from gcs.missions.core import MissionCore, MissionPart
from gcs.missions.model import ActiveMission


class LostPolicy(Protocol):
    """The task's lost-agent policy for members that did not reach barrier ``step``."""

    def __call__(
        self,
        mission: ActiveMission,
        step: int,
        missing: list[str],
        what: str,
        abort_result: str,
        exclude_why: str,
    ) -> Awaitable[None]: ...


class BarrierWatchdog(MissionPart):
    """The first-arrival sync timeout and the next barrier's watchdog of every running mission."""

    def __init__(self, core: MissionCore, lost_policy: LostPolicy) -> None:
        super().__init__(core)
        self._lost_policy = lost_policy

    async def barrier_timeout(self, mission: ActiveMission, step: int) -> None:
        if mission.state != "running" or step in mission.barriers.released:
            return
        if not await self._core.leading(mission):  # a timer that fired after a pause: lease first
            return
        missing = sorted(mission.barriers.missing(step))
        await self._lost_policy(
            mission,
            step,
            missing,
            f"step {step}: still waiting for {missing} after {mission.task.sync_timeout_s:.0f} s",
            abort_result=f"sync step {step} timed out waiting for {missing}",
            exclude_why=f"did not reach sync step {step} in time",
        )

    def _next_barrier(self, mission: ActiveMission) -> int | None:
        pending = [s for s in mission.barriers.sync_steps if s not in mission.barriers.released]
        return pending[0] if pending else None

    def arm(self, mission: ActiveMission) -> None:
        """Time the next barrier from now (mission start or the previous release).

        The usual sync timeout starts at a barrier's first arrival; this one catches a barrier
        no agent ever reaches (every agent failed, stuck idle or gone).
        """
        self._core.disarm_watchdog(mission.id)
        step = self._next_barrier(mission)
        if step is None or mission.state != "running":
            return
        self._core.watchdogs[mission.id] = asyncio.get_running_loop().call_later(
            mission.task.sync_timeout_s, lambda: asyncio.ensure_future(self._fired(mission, step))
        )

    def _working_on(self, mission: ActiveMission, identity: str) -> bool:
        """True while the agent's reports show it flying an action, waiting at a barrier, or held
        by a pause (collision avoidance holds one agent at a time)."""
        session = self._agents.session(identity)
        status = session.status if session else None
        if status is None or status.mission_id != mission.id:
            return False
        return status.step >= 0 or status.waiting_sync is not None or status.paused

    async def _fired(self, mission: ActiveMission, step: int) -> None:
        self._core.watchdogs.pop(mission.id, None)
        if mission.state != "running" or step in mission.barriers.released:
            return
        if not await self._core.leading(mission):
            return
        if mission.barriers.arrivals.get(step) and step in mission.timers:
            return  # someone arrived: the first-arrival sync timeout is running
        idle = sorted(a for a in mission.barriers.missing(step) if not self._working_on(mission, a))
        if not idle or mission.id in self._core.paused:
            self.arm(mission)  # long legs: look again one timeout later
            return
        await self._lost_policy(
            mission,
            step,
            idle,
            f"step {step}: {idle} not working towards it {mission.task.sync_timeout_s:.0f} s after "
            "the mission start or the previous release",
            abort_result=f"sync step {step}: {idle} never arrived",
            exclude_why=f"never reached sync step {step}",
        )
        if mission.state == "running":
            self.arm(mission)

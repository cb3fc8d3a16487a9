"""What the parts of the mission runner share: a running mission, its progress, the ports it needs.

Data and contracts only (no behaviour besides small pure helpers), so every part of the runner
(gcs/missions/runner.py and the modules it composes) and its callers import from here.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, Protocol

from pydantic import BaseModel

from gcs.control.authority import Owner
from gcs.link.agents import AgentSession, FinishedHook, JoinHook, LostHook, StatusHook, SyncHook
from gcs.missions.sync import BarrierSet
from protocol.actions import Action
from protocol.beacon import ReleaseChain
from protocol.taskfile import TaskFile

if TYPE_CHECKING:
    from gcs.link.dispatch import HookList


PreflightCheck = Callable[[TaskFile, dict[str, list[Action]]], Awaitable[None]]
"""Runs before a mission is accepted; raises MissionRejected (with the numbers) to refuse it."""


class MissionAgents(Protocol):
    """What the runner reads of the agent manager and hooks into: no send side (releases and
    orders go through the command port)."""

    on_join: HookList[JoinHook]
    on_status_changes: HookList[StatusHook]
    on_sync: HookList[SyncHook]
    on_lost: HookList[LostHook]
    on_finished: FinishedHook | None

    @property
    def sessions(self) -> Mapping[str, AgentSession]: ...

    def session(self, identity: str) -> AgentSession | None: ...


class MissionCluster(Protocol):
    """What the runner asks of the cluster (gcs/cluster/node.py); absent when it runs alone."""

    async def claim_release(self, mission_id: str, step: int) -> bool: ...

    def led_elsewhere(self, mission_id: str) -> bool: ...

    async def withdraw_elsewhere(self, identity: str, reason: str) -> None: ...

    def remote_blocker(self, identity: str) -> str | None: ...

    async def may_decide(self, mission_id: str) -> bool: ...


ReturnHome = Callable[[list[str], Literal["rtl", "land"], Owner, str], list[str]]
"""Starts a deconflicted return (``gcs.cooperation.return_coordinator``); returns who got it."""


MissionState = Literal["running", "completed", "aborted"]


def stored_task(task_json: str) -> TaskFile | None:
    """A stored mission's task, or None when it no longer validates (stored by another version)."""
    try:
        return TaskFile.model_validate_json(task_json)
    except ValueError:
        return None


class MissionRejected(ValueError):
    """A mission that cannot start; the message says why."""


class AgentProgress(BaseModel):
    agent: str
    cid: int | None
    connected: bool
    excluded: bool
    step: int
    completed_step: int
    last_step: int
    waiting_sync: int | None
    done: bool
    why: str | None = None  # why it was excluded (None: not excluded, or excluded before a restart)


class MissionProgress(BaseModel):
    id: str
    name: str
    state: str
    result: str | None
    sync_steps: list[int]
    released_steps: list[int]
    agents: list[AgentProgress]


@dataclass(eq=False)
class ActiveMission:
    id: str
    task: TaskFile
    plans: dict[str, list[Action]]  # identity -> actions
    barriers: BarrierSet
    completed: dict[str, int]
    excluded: set[str] = field(default_factory=set)
    left_why: dict[str, str] = field(default_factory=dict)  # excluded agent -> why (this daemon's run)
    state: MissionState = "running"
    timers: dict[int, asyncio.TimerHandle] = field(default_factory=dict)
    failures: dict[str, tuple[int, float]] = field(default_factory=dict)  # agent -> last (step, time) seen
    retries: dict[tuple[str, int], int] = field(default_factory=dict)  # (agent, step) -> retries sent
    chain: ReleaseChain | None = None  # release-beacon chain (protocol/beacon.py); None: TCP releases only

    def last_step(self, agent: str) -> int:
        return self.plans[agent][-1].step


def every_agent_left(mission: ActiveMission) -> str:
    """The result of a mission no agent flies any more, saying why each left.

    A battery emergency's withdrawal or a vehicle's own failsafe is not a lost link: the text
    names each agent with its reason ("drone-1: withdrawn: energy: ...; drone-2: vehicle
    failsafe battery_low"). Agents excluded before a daemon restart have no reason kept.
    """
    whys = [f"{a}: {mission.left_why.get(a, 'excluded')}" for a in sorted(mission.plans)]
    if all(mission.left_why.get(a, "").startswith("lost") for a in mission.plans):
        return "every agent was lost"
    return "no agent left flying (" + "; ".join(whys) + ")"

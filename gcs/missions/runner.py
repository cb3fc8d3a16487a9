"""Mission runner: validates a task, sends each agent its actions, runs the sync barriers.

Each agent gets its whole action list in one type-4 ``replace`` packet at start, so it keeps
flying its plan through a daemon restart or a short link loss; the daemon's part is the
barriers (release step k to everyone once everyone finished k), progress, and the lost-agent
policy. Accepted missions, completed steps and released barriers are in the store, so a
restarted daemon picks the mission up where it was.

``MissionRunner`` is the composition and the one surface its callers see (the API's mission
routes, the operator, bring-down, the cluster node, re-tasking); each job is a part of its own
over one shared ``MissionCore`` (gcs/missions/core.py): ``MissionAdmission`` (admission.py:
validation and start), ``BarrierReleases`` (releases.py: arrivals and the one release path),
``BarrierWatchdog`` (watchdog.py: the barrier timers), ``MissionPolicies`` (policies.py: the
lost-agent and failed-action policies, exclusion, completion, abort, withdrawal), ``Rejoins``
(rejoin.py), ``MissionRecords`` (records.py: restore, progress, plans). The agent hooks stay
bound methods of the runner, so the hook dispatcher serves them in one consumer, in order.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

from gcs.control.authority import Owner
from gcs.link.agents import AgentSession
from gcs.link.beacon import BeaconSender
from gcs.missions.admission import MissionAdmission
from gcs.missions.core import MissionCore
from gcs.missions.model import (
    ActiveMission,
    AgentProgress,
    MissionAgents,
    MissionCluster,
    MissionProgress,
    MissionRejected,
    MissionState,
    PreflightCheck,
    ReturnHome,
    every_agent_left,
    stored_task,
)
from gcs.missions.policies import MissionPolicies
from gcs.missions.records import MissionRecords
from gcs.missions.rejoin import Rejoins
from gcs.missions.releases import BarrierReleases
from gcs.missions.watchdog import BarrierWatchdog
from gcs.observe.events import EventBus
from gcs.storage.store import Store
from protocol.actions import Action
from protocol.packets import Resume, StatusReport, SyncSignal
from protocol.taskfile import TaskFile

if TYPE_CHECKING:
    from gcs.control.command_port import CommandPort

__all__ = [
    "ActiveMission",
    "AgentProgress",
    "MissionAgents",
    "MissionCluster",
    "MissionProgress",
    "MissionRejected",
    "MissionRunner",
    "MissionState",
    "PreflightCheck",
    "ReturnHome",
    "every_agent_left",
    "stored_task",
]


class MissionRunner:
    """Runs missions over the agent manager; one mission per agent at a time."""

    def __init__(
        self,
        agents: MissionAgents,
        store: Store,
        events: EventBus,
        commands: CommandPort,
        *,
        return_home: ReturnHome | None = None,
        beacon: BeaconSender | None = None,
        cluster: MissionCluster | None = None,
    ) -> None:
        core = MissionCore(
            agents, store, events, commands, return_home=return_home, beacon=beacon, cluster=cluster
        )
        self._core = core
        self._watchdog = BarrierWatchdog(core, self._lost_policy)
        self._releases = BarrierReleases(core, self._watchdog)
        self._policies = MissionPolicies(core, self._releases)
        self._admission = MissionAdmission(core, self._watchdog)
        self._rejoins = Rejoins(core, self._releases)
        self._records = MissionRecords(core, self._admission, self._watchdog)
        self.active: dict[str, ActiveMission] = core.active
        self.paused: set[str] = core.paused  # changed in place only
        self.preflight_checks: list[PreflightCheck] = self._admission.preflight_checks
        # The hooks are this object's bound methods: the dispatcher serves one owner's hooks in
        # one consumer, so one agent's join, status, sync and lost reach the parts in order.
        agents.on_join.append(self._on_join)
        agents.on_status_changes.append(self._on_status)  # completed step, failsafe, failure: state changes
        agents.on_sync.append(self._on_sync)
        agents.on_finished = self._arrive_now  # the direct path: the last arrival releases at once
        agents.on_lost.append(self._on_lost)

    # --- what the callers read of the core -------------------------------------------------------

    @property
    def return_home(self) -> ReturnHome | None:
        """The daemon's return coordinator (deconflicted returns)."""
        return self._core.return_home

    @property
    def beacon(self) -> BeaconSender | None:
        """The release beacon's sender, when release_beacon is configured."""
        return self._core.beacon

    @beacon.setter
    def beacon(self, sender: BeaconSender | None) -> None:
        """Switched off and on between barriers by bench/bench_load.py (paired beacon/TCP trials)."""
        self._core.beacon = sender

    @property
    def led_elsewhere(self) -> Callable[[str], bool]:
        """True for a running mission another daemon of the cluster leads (never without one)."""
        return self._core.led_elsewhere

    # --- lifecycle ------------------------------------------------------------------------------

    def restore(self) -> None:
        """Reload the missions that were running when the daemon stopped."""
        self._records.restore()

    def restore_one(self, mission_id: str) -> ActiveMission | None:
        """Take over one stored running mission (restart, or a cluster standby taking the lead)."""
        return self._records.restore_one(mission_id)

    def forget(self, mission_id: str) -> None:
        """Stop running a mission here without ending it (another daemon of the cluster leads it)."""
        self._core.forget(mission_id)

    async def submit(self, task: TaskFile) -> str:
        """Validate against the live fleet, persist, and send every agent its actions."""
        return await self._admission.submit(task)

    async def abort(
        self,
        mission_id: str,
        reason: str,
        owner: Owner = "mission",
        then: Literal["rtl", "land", "hold"] = "rtl",
    ) -> list[str]:
        """Stop a mission: every agent still in it returns (deconflicted), lands, or holds."""
        return await self._policies.abort(mission_id, reason, owner, then)

    async def withdraw(self, identity: str, reason: str) -> bool:
        """Take one agent out of its mission (emergency): the others go on without it."""
        return await self._policies.withdraw(identity, reason)

    def members(self, mission: ActiveMission) -> list[str]:
        """The agents of ``mission`` still flying it (not excluded)."""
        return self._core.members(mission)

    async def pause(self, mission_id: str, reason: str = "paused by the operator") -> None:
        """Every agent of the mission stops where it is and keeps its queue (an operator hold).

        The pause is stored: agents that rejoin, and a restarted daemon, keep it.
        """
        mission = await self._core.require_led(mission_id)
        for identity in self.members(mission):
            self._core.authority.hold(identity, "operator", reason, mission_id)
        self.paused.add(mission_id)
        self._core.store.set_paused(mission_id, True)
        self._core.events.publish("mission_paused", reason, mission_id=mission_id)

    async def resume(self, mission_id: str, reason: str = "resumed by the operator") -> None:
        mission = await self._core.require_led(mission_id)
        for identity in self.members(mission):
            self._core.authority.release(identity, "operator", reason, mission_id)
        self.paused.discard(mission_id)
        self._core.store.set_paused(mission_id, False)
        self._core.events.publish("mission_resumed", reason, mission_id=mission_id)

    # --- what a cluster node feeds in (gcs/cluster: agents linked to other daemons) ---------------

    async def agent_joined(self, session: AgentSession, resume: Resume | None) -> None:
        """An agent joined (here or, in a cluster, another daemon): resume or re-send its plan."""
        await self._on_join(session, resume)

    async def agent_status(self, session: AgentSession, status: StatusReport) -> None:
        """A status report (progress, failsafes, failed actions) from an agent wherever it is linked."""
        await self._on_status(session, status)

    async def agent_finished(self, session: AgentSession, signal: SyncSignal) -> None:
        """An agent finished a barrier step (its 'finished' sync signal, or one inferred from status)."""
        await self._on_sync(session, signal)

    async def agent_lost(self, identity: str) -> None:
        """An agent is gone (its daemon died or dropped it): the mission's lost-agent policy applies."""
        await self._on_lost(identity)

    def count_arrivals(self, mission_id: str, arrivals: dict[int, set[str]]) -> None:
        """Arrivals recorded elsewhere (shared state, a takeover): counted at their barriers."""
        self._releases.count_arrivals(mission_id, arrivals)

    async def release_ready(self, mission_id: str) -> list[int]:
        """Release every barrier of the mission that all its members reached; returns the steps."""
        return await self._releases.release_ready(mission_id)

    def mission_of(self, identity: str) -> ActiveMission | None:
        """The mission run here that ``identity`` flies (excluded or not), or None."""
        return self._core.mission_of(identity)

    def plan_of(self, mission_id: str, identity: str) -> list[Action] | None:
        """``identity``'s actions in a running mission here or (cluster) led by another daemon."""
        return self._records.plan_of(mission_id, identity)

    def progress(self, mission_id: str) -> MissionProgress | None:
        """A mission's progress per agent, running or finished (None: no such mission)."""
        return self._records.progress(mission_id)

    # --- agent hooks (one owner: this runner) ---------------------------------------------------

    async def _on_join(self, session: AgentSession, resume: Resume | None) -> None:
        await self._rejoins.on_join(session, resume)

    async def _on_status(self, session: AgentSession, status: StatusReport) -> None:
        await self._policies.on_status(session, status)

    async def _on_sync(self, session: AgentSession, signal: SyncSignal) -> None:
        await self._releases.on_sync(session, signal)

    def _arrive_now(self, session: AgentSession, signal: SyncSignal) -> bool:
        return self._releases.arrive_now(session, signal)

    async def _on_lost(self, identity: str) -> None:
        await self._policies.on_lost(identity)

    async def _lost_policy(
        self,
        mission: ActiveMission,
        step: int,
        missing: list[str],
        what: str,
        abort_result: str,
        exclude_why: str,
    ) -> None:
        """The barrier watchdog's way to the lost-agent policy (parts built in order, no cycle)."""
        await self._policies.lost_policy(mission, step, missing, what, abort_result, exclude_why)

"""What happens when a mission cannot go on as planned: the task's policies and the end of a mission.

Why apart: every way a member leaves (lost, withdrawn, a pilot, a vehicle failsafe, a barrier it
never reached, a failed action) ends in one ``exclude`` with the reason kept (``left_why``), and
every end (completed, aborted, no agent left) in one ``finish``; the operator's abort takes the
same path with its own priority.
"""

from __future__ import annotations

from typing import Literal

from gcs.control.authority import Owner
from gcs.link.agents import AgentSession
from gcs.missions.core import MissionCore, MissionPart
from gcs.missions.model import ActiveMission, every_agent_left
from gcs.missions.releases import BarrierReleases
from protocol.packets import ActionFailure, StatusReport


class MissionPolicies(MissionPart):
    """Lost-agent and failed-action policies, exclusions, completion, abort and withdrawal."""

    def __init__(self, core: MissionCore, releases: BarrierReleases) -> None:
        super().__init__(core)
        self._releases = releases

    async def abort(
        self,
        mission_id: str,
        reason: str,
        owner: Owner = "mission",
        then: Literal["rtl", "land", "hold"] = "rtl",
    ) -> list[str]:
        """Stop a mission: every agent still in it returns (deconflicted), lands, or holds.

        ``owner`` is who asked (``operator`` from the API): the returns run at that priority.
        Returns the agents that were given the new orders.
        """
        mission = await self._core.require_led(mission_id)
        members = self._core.members(mission)
        self._core.finish(mission, "aborted", reason)
        if then == "hold":
            return [m for m in members if self._authority.hold(m, owner, f"abort: {reason}", mission_id)[0]]
        if self._core.return_home is None:
            return []
        return self._core.return_home(members, then, owner, f"abort: {reason}")

    async def withdraw(self, identity: str, reason: str) -> bool:
        """Take one agent out of its mission (emergency): the others go on without it.

        Barriers it blocked are released; what it does next is for the caller to order through
        the authority. False if it flies no active mission here (in a cluster the daemon leading
        its mission is told through ``withdraw_elsewhere``).
        """
        mission = self._core.mission_of(identity)
        if mission is not None and not await self._core.leading(mission):
            mission = None  # we stepped down: whoever leads it now hears of it like any other
        if mission is None and self._core.withdraw_elsewhere is not None:
            await self._core.withdraw_elsewhere(identity, reason)
        if mission is None or identity in mission.excluded:
            return False
        await self.exclude(mission, identity, f"withdrawn: {reason}")
        return True

    async def on_status(self, session: AgentSession, status: StatusReport) -> None:
        if status.mission_id is None:
            return
        mission = self._core.mission_of(session.identity, status.mission_id)
        if mission is None or not await self._core.leading(mission):
            return
        if status.pilot is not None and session.identity not in mission.excluded:
            # A pilot took it (RC, another ground station): never commanded again by this mission.
            await self.exclude(mission, session.identity, f"pilot in control ({status.pilot})")
            return
        if status.failsafe is not None and session.identity not in mission.excluded:
            # The vehicle flies its own failsafe now (RTL, land, hold): the others go on without it.
            await self.exclude(mission, session.identity, f"vehicle failsafe {status.failsafe}")
            return
        previous = mission.completed.get(session.identity, -1)
        if status.completed_step > previous:
            mission.completed[session.identity] = status.completed_step
            self._store.set_completed_step(mission.id, session.identity, status.completed_step)
        if status.failure is not None:
            await self._on_action_failed(mission, session.identity, status.failure)
        if mission.state == "running":
            self.check_complete(mission)

    def check_complete(self, mission: ActiveMission) -> None:
        flying = [a for a in mission.plans if a not in mission.excluded]
        if not flying:
            self._core.finish(mission, "aborted", every_agent_left(mission))
            return
        if all(mission.completed[a] >= mission.last_step(a) for a in flying):
            note = f" ({len(mission.excluded)} agents excluded)" if mission.excluded else ""
            self._core.finish(mission, "completed", f"all {len(flying)} agents finished{note}")

    async def lost_policy(
        self,
        mission: ActiveMission,
        step: int,
        missing: list[str],
        what: str,
        abort_result: str,
        exclude_why: str,
    ) -> None:
        """The task's lost-agent policy for agents that did not reach barrier ``step``."""
        policy = mission.task.lost_agent_policy
        self._events.publish(
            "sync_timeout",
            f"{what}; policy {policy}",
            severity="error",
            mission_id=mission.id,
            data={"step": step, "missing": missing},
        )
        if policy == "abort":
            await self.abort(mission.id, abort_result)
            return
        for identity in missing:
            await self.exclude(mission, identity, exclude_why)

    async def exclude(self, mission: ActiveMission, identity: str, why: str) -> None:
        mission.excluded.add(identity)
        mission.left_why[identity] = why
        self._store.exclude_agent(mission.id, identity)
        self._events.publish("agent_excluded", why, severity="warning", agent=identity, mission_id=mission.id)
        for step in mission.barriers.exclude(identity):
            await self._releases.release(mission, step)
        if mission.state == "running":
            self.check_complete(mission)

    async def on_lost(self, identity: str) -> None:
        if self._agents.session(identity) is not None:
            return  # back already (here, or linked to another daemon of the cluster)
        mission = self._core.mission_of(identity)
        if mission is None or identity in mission.excluded or not await self._core.leading(mission):
            return
        if mission.completed.get(identity, -1) >= mission.last_step(identity):
            return  # it had finished its part
        if mission.task.lost_agent_policy == "continue":
            await self.exclude(mission, identity, "lost during the mission; continuing without it")

    async def _on_action_failed(self, mission: ActiveMission, identity: str, failure: ActionFailure) -> None:
        """Apply the task's ``on_action_failed`` policy once per failure an agent reports.

        The agent has emptied its queue and holds; it keeps reporting the failure until it
        starts another action, so each (step, time) is acted on once.
        """
        key = (failure.step, failure.time)
        if (
            mission.state != "running"
            or identity in mission.excluded
            or mission.failures.get(identity) == key
        ):
            return
        mission.failures[identity] = key
        what = f"{identity} step {failure.step} ({failure.kind}): {failure.reason}"
        policy = mission.task.on_action_failed
        self._events.publish(
            "action_failed",
            f"{what}; policy {policy}",
            severity="error",
            agent=identity,
            mission_id=mission.id,
            data={"step": failure.step, "kind": failure.kind, "reason": failure.reason},
        )
        plan = mission.plans[identity]
        if policy == "retry":
            tried = mission.retries.get((identity, failure.step), 0)
            if tried < mission.task.action_retries:
                mission.retries[(identity, failure.step)] = tried + 1
                again = [a for a in plan if a.step >= failure.step]
                self._events.publish(
                    "action_retry",
                    f"{identity}: retry {tried + 1}/{mission.task.action_retries} of step {failure.step}",
                    agent=identity,
                    mission_id=mission.id,
                )
                self._core.send_plan(mission, identity, again, f"retry step {failure.step}")
                return
        elif policy == "skip":
            await self._skip_step(mission, identity, failure)
            return
        await self.abort(mission.id, f"action failed: {what}")

    async def _skip_step(self, mission: ActiveMission, identity: str, failure: ActionFailure) -> None:
        """Count the failed step as done (a barrier at it counts the agent as arrived), fly on."""
        plan = mission.plans[identity]
        rest = [a for a in plan if a.step > failure.step]
        self._events.publish(
            "action_skipped",
            f"{identity}: step {failure.step} skipped, {len(rest)} actions left",
            severity="warning",
            agent=identity,
            mission_id=mission.id,
        )
        if mission.completed.get(identity, -1) < failure.step:
            mission.completed[identity] = failure.step
            self._store.set_completed_step(mission.id, identity, failure.step)
        if rest:
            self._core.send_plan(mission, identity, rest, f"step {failure.step} skipped")
        barriers = mission.barriers
        if (
            failure.step in barriers.sync_steps
            and failure.step not in barriers.released
            and barriers.arrive(identity, failure.step)
        ):
            await self._releases.release(mission, failure.step)

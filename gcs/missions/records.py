"""A mission's record: restored from the store after a restart or a takeover, its progress, its plans.

Why apart: the store is the mission's memory across daemon processes (accepted missions, completed
steps, released barriers, pauses); this part reads it back (``restore``), answers what the API
shows (``progress``), and what another daemon's mission plans for a drone (``plan_of``).
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from gcs.missions.core import MissionCore, MissionPart
from gcs.missions.model import ActiveMission, AgentProgress, MissionProgress, stored_task
from gcs.missions.watchdog import BarrierWatchdog
from protocol.actions import Action
from protocol.taskfile import TaskFile

if TYPE_CHECKING:
    from gcs.missions.admission import MissionAdmission

log = logging.getLogger("gcs.missions.runner")

STORED_PLAN_RECHECK_S = 1.0


class MissionRecords(MissionPart):
    """Restores running missions, reports progress, looks up plans (cached for missions led elsewhere)."""

    def __init__(self, core: MissionCore, admission: MissionAdmission, watchdog: BarrierWatchdog) -> None:
        super().__init__(core)
        self._admission = admission
        self._watchdog = watchdog
        # mission id -> (checked at, plans) of running missions led by another daemon
        self._stored_plans: dict[str, tuple[float, dict[str, list[Action]] | None]] = {}

    def restore(self) -> None:
        """Reload the missions that were running when the daemon stopped."""
        for stored in self._store.missions("running"):
            try:
                self.restore_one(stored.id)
            except ValueError as exc:  # pydantic's ValidationError and MissionRejected are ValueErrors
                self._unrestorable(stored.id, stored.name, exc)
        paused = self._store.paused_missions() & set(self.active)
        self._core.paused.clear()  # in place: every part holds this set
        self._core.paused.update(paused)

    def _unrestorable(self, mission_id: str, name: str, exc: ValueError) -> None:
        """A stored running mission this version cannot rebuild (its task no longer validates, an
        agent's CID is gone): end it as aborted, say why, and start the daemon for the rest of the
        fleet. Its drones get no further order from it; their agents keep their own failsafes."""
        why = " ".join(str(exc).split())[:300]
        self._store.finish_mission(mission_id, "aborted", f"not restored after restart: {why}")
        self._events.publish(
            "mission_restore_failed",
            f"mission {name} could not be restored after restart and was aborted: {why}",
            severity="error",
            mission_id=mission_id,
        )
        log.error("mission %s (%s) not restored: %s", mission_id, name, why)

    def restore_one(self, mission_id: str) -> ActiveMission | None:
        """Take over one stored running mission (restart, or a cluster standby taking the lead)."""
        stored = self._store.mission(mission_id)
        if stored is None or stored.state != "running" or mission_id in self.active:
            return self.active.get(mission_id)
        task = TaskFile.model_validate_json(stored.task_json)
        progress = self._store.mission_agents(stored.id)
        mission = self._admission.build(stored.id, task, self._admission.resolve(task))
        mission.barriers.released |= self._store.released_steps(stored.id)
        for agent, (completed, excluded) in progress.items():
            mission.completed[agent] = completed
            if excluded:
                mission.excluded.add(agent)
                mission.barriers.members.discard(agent)
        self.active[stored.id] = mission
        self._watchdog.arm(mission)
        self._events.publish(
            "mission_restored", f"mission {task.name} resumed after restart", mission_id=stored.id
        )
        if mission_id in self._store.paused_missions():
            self._core.paused.add(mission_id)
        return mission

    def plan_of(self, mission_id: str, identity: str) -> list[Action] | None:
        """``identity``'s actions in a running mission: run here, or (cluster) led by another daemon,
        from the stored task; None if it has no plan there. The stored state is looked at again
        at most every ``STORED_PLAN_RECHECK_S``."""
        mission = self.active.get(mission_id)
        if mission is not None:
            return mission.plans.get(identity)
        now = time.monotonic()
        cached = self._stored_plans.get(mission_id)
        if cached is None or now - cached[0] > STORED_PLAN_RECHECK_S:
            plans = None
            stored = self._store.mission(mission_id) if self._core.led_elsewhere(mission_id) else None
            if stored is not None and stored.state == "running":
                plans = cached[1] if cached is not None and cached[1] is not None else {}
                if not plans:
                    try:
                        plans = self._admission.resolve(TaskFile.model_validate_json(stored.task_json))
                    except ValueError:  # MissionRejected included: a CID no longer known
                        plans = {}
            if len(self._stored_plans) > 64:  # bounded: finished missions are not asked for again
                self._stored_plans.clear()
            cached = self._stored_plans[mission_id] = (now, plans)
        return None if cached[1] is None else cached[1].get(identity)

    def progress(self, mission_id: str) -> MissionProgress | None:
        stored = self._store.mission(mission_id)
        if stored is None:
            return None
        mission = self.active.get(mission_id)
        task = mission.task if mission else stored_task(stored.task_json)
        if task is None:  # stored by a version whose task this one cannot read: state and result only
            return MissionProgress(
                id=stored.id,
                name=stored.name,
                state=stored.state,
                result=stored.result,
                sync_steps=[],
                released_steps=sorted(self._store.released_steps(mission_id)),
                agents=[],
            )
        plans = mission.plans if mission else self._admission.resolve_stored(task)
        agents_state = self._store.mission_agents(mission_id)
        released = self._store.released_steps(mission_id)
        rows = []
        for identity, actions in plans.items():
            session = self._agents.sessions.get(identity)
            status = session.status if session else None
            completed = max(
                agents_state.get(identity, (-1, False))[0], mission.completed[identity] if mission else -1
            )
            rows.append(
                AgentProgress(
                    agent=identity,
                    cid=session.cid if session else None,
                    connected=bool(session and session.open),
                    excluded=agents_state.get(identity, (-1, False))[1],
                    why=mission.left_why.get(identity) if mission else None,
                    step=status.step if status and status.mission_id == mission_id else -1,
                    completed_step=completed,
                    last_step=actions[-1].step,
                    waiting_sync=status.waiting_sync if status and status.mission_id == mission_id else None,
                    done=completed >= actions[-1].step,
                )
            )
        return MissionProgress(
            id=stored.id,
            name=stored.name,
            state=stored.state,
            result=stored.result,
            sync_steps=task.plans[0].sync_steps(),
            released_steps=sorted(released),
            agents=rows,
        )

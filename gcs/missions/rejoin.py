"""An agent that joins again during its mission: resumed where it says it is, or its plan re-sent.

Why apart: a rejoin is where a daemon restart and a lost link meet the barriers (a 'finished'
that died with the previous process is counted again from what the agent reports).
"""

from __future__ import annotations

from gcs.link.agents import AgentSession
from gcs.missions.core import MissionCore, MissionPart
from gcs.missions.releases import BarrierReleases
from protocol.packets import Resume, SyncSignal


class Rejoins(MissionPart):
    """The ``on_join`` of the runner: resume (arrivals it reports) or re-send the rest of its plan."""

    def __init__(self, core: MissionCore, releases: BarrierReleases) -> None:
        super().__init__(core)
        self._releases = releases

    async def on_join(self, session: AgentSession, resume: Resume | None) -> None:
        identity = session.identity
        mission = self._core.mission_of(identity)
        if mission is not None and not await self._core.leading(mission):
            mission = None
        if mission is None or identity in mission.excluded:
            self._authority.reassert(identity)
            return
        if resume is not None and resume.mission_id == mission.id:
            # It still holds its queue. A sync wait it reports counts as a (repeated) arrival:
            # the 'finished' it sent before may have died with the previous daemon process.
            self._authority.reassert(identity)
            # Barriers it passed by its own account are arrivals too: a release it heard may be
            # missing here (journaled, then the daemon died before its row; the store recovers
            # it only when the database agrees, gcs/storage/store.py), and a member still waiting there
            # is released once every member says it got that far.
            passed = [s for s in mission.barriers.sync_steps if s <= resume.completed_step]
            for step in passed:
                if step != resume.waiting_step and step not in mission.barriers.released:
                    await self._releases.on_sync(
                        session, SyncSignal(mission_id=mission.id, step=step, kind="finished")
                    )
            if resume.waiting_step is not None:
                await self._releases.on_sync(
                    session, SyncSignal(mission_id=mission.id, step=resume.waiting_step, kind="finished")
                )
            return
        completed = max(mission.completed.get(identity, -1), resume.completed_step if resume else -1)
        actions = mission.plans[identity]
        remaining = [a for a in actions if a.step > completed]
        # Finished a barrier step that is not released yet: it must wait there again, not run on.
        barrier = next((a.step for a in actions if a.sync and a.step == completed), None)
        wait = barrier if barrier is not None and barrier not in mission.barriers.released else None
        self._events.publish(
            "mission_resent",
            f"agent lost its queue; re-sending {len(remaining)} actions after step {completed}"
            + (f", waiting at barrier {wait} first" if wait is not None else "")
            + (" (mission paused)" if mission.id in self._core.paused else ""),
            agent=identity,
            mission_id=mission.id,
        )
        if remaining or wait is not None:
            self._core.send_plan(
                mission, identity, remaining, "re-sent after rejoin", await_release=wait, keep_holds=True
            )

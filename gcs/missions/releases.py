"""Barrier arrivals and releases: counted, made durable, announced, then burst to the members.

Why apart: the release is the runner's one hot path (the last arrival persists and sends the
release in the same callback, ``arrive_now``) and its one way to tell agents to go on; the
bookkeeping itself is pure (gcs/missions/sync.py), this part adds the store, the beacon, the
command port and, in a cluster, the claim in shared state.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc

from gcs.cooperation.returns import RETURN_PREFIX
from gcs.link.agents import AgentSession
from gcs.missions.core import MissionCore, MissionPart
from gcs.missions.model import ActiveMission
from gcs.missions.watchdog import BarrierWatchdog
from protocol.packets import SyncSignal


class BarrierReleases(MissionPart):
    """Arrivals at the sync barriers and their releases (one release path for every caller)."""

    def __init__(self, core: MissionCore, watchdog: BarrierWatchdog) -> None:
        super().__init__(core)
        self._watchdog = watchdog
        self._taken: dict[int, SyncSignal] = {}  # id -> signal the direct path took (its hook skips it)

    def count_arrivals(self, mission_id: str, arrivals: dict[int, set[str]]) -> None:
        """Arrivals recorded elsewhere (shared state, a takeover): counted at their barriers."""
        mission = self.active.get(mission_id)
        if mission is None:
            return
        for step, agents in arrivals.items():
            for agent in agents:
                if step in mission.barriers.sync_steps and agent in mission.barriers.members:
                    with contextlib.suppress(ValueError):
                        mission.barriers.arrive(agent, step)

    async def release_ready(self, mission_id: str) -> list[int]:
        """Release every barrier of the mission that all its members reached; returns the steps."""
        mission = self.active.get(mission_id)
        if mission is None or not await self._core.leading(mission):
            return []
        ready = [
            step
            for step in mission.barriers.sync_steps
            if step not in mission.barriers.released and not mission.barriers.missing(step)
        ]
        for step in ready:
            await self.release(mission, step)
        return ready

    async def on_sync(self, session: AgentSession, signal: SyncSignal) -> None:
        if self._taken.pop(id(signal), None) is signal:
            return  # the direct path (arrive_now) counted it already
        if signal.mission_id.startswith(RETURN_PREFIX):
            return  # a return's wait point: the return coordinator releases it
        mission = self._core.mission_of(session.identity, signal.mission_id)
        if mission is not None and not await self._core.leading(mission):
            return  # we stepped down: the leader counts it (its daemon shared it)
        if mission is None and self._core.led_elsewhere(signal.mission_id):
            return
        if mission is None:
            self._events.publish(
                "sync_ignored",
                f"finished step {signal.step} for unknown mission {signal.mission_id}",
                severity="warning",
                agent=session.identity,
            )
            return
        if self._record_arrival(mission, session, signal):
            await self.release(mission, signal.step)

    def arrive_now(self, session: AgentSession, signal: SyncSignal) -> bool:
        """A 'finished' straight from the agent's frame (``AgentManager.on_finished``); True if taken.

        Called only while this runner's hook consumer holds no join or lost of the agent. A
        barrier this completes is released in the same call (persisted, then one burst): no hook
        queue, no task switch. Left to the ``on_sync`` hook, in order: an agent whose newest
        report carries a failsafe or a failure (the hook may exclude it first), a cluster (the
        release is claimed in shared state first, which is awaited), returns' wait points, and
        missions not run here.
        """
        if self._core.claim_release is not None or signal.mission_id.startswith(RETURN_PREFIX):
            return False
        mission = self._core.mission_of(session.identity, signal.mission_id)
        if mission is None:
            return False
        status = session.status
        if status is not None and (
            status.failsafe is not None or status.failure is not None or status.pilot is not None
        ):
            return False
        if len(self._taken) >= 4096:  # hooks closed at shutdown never pop theirs: bounded
            self._taken.clear()
        self._taken[id(signal)] = signal
        if self._record_arrival(mission, session, signal):
            self.release_now(mission, signal.step)
        return True

    def _record_arrival(self, mission: ActiveMission, session: AgentSession, signal: SyncSignal) -> bool:
        """Count an arrival at a barrier; True when it completes the barrier (now to be released).

        A repeated arrival at a released step is answered with the release at once; the first
        arrival at a barrier starts its sync timeout.
        """
        try:
            complete = mission.barriers.arrive(session.identity, signal.step)
        except ValueError as exc:
            self._events.publish("sync_ignored", str(exc), severity="warning", agent=session.identity)
            return False
        if signal.step in mission.barriers.released:
            self._commands.release_barrier([session.identity], mission.id, signal.step)
            return False
        if not complete and signal.step not in mission.timers:
            timeout = mission.task.sync_timeout_s
            mission.timers[signal.step] = asyncio.get_running_loop().call_later(
                timeout, lambda: asyncio.ensure_future(self._watchdog.barrier_timeout(mission, signal.step))
            )
        return complete

    async def release(self, mission: ActiveMission, step: int) -> None:
        if self._core.claim_release is not None and not await self._core.claim_release(mission.id, step):
            mission.barriers.mark_released(step)  # another daemon released it; it told the agents
            return
        self.release_now(mission, step)

    def release_now(self, mission: ActiveMission, step: int) -> None:
        """Make the release of ``step`` durable, announce it, write it to every member's socket in
        one pass, then record it in the database.

        Durable first: one append to the release journal (``Store.journal_release``; no lock, no
        transaction), so an agent never hears of a release a restarted daemon would not know.
        Then the beacon (one datagram for every listening member) and the TCP burst. The release
        row and its event follow as one transaction (a kill -9 between the two lost the event once;
        between the journal and this transaction the store recovers both when it opens).
        ``write_wanted`` is set through the burst: the telemetry writer ends its chunk at the next
        row and waits, instead of competing with this thread for the GIL while the sockets are
        written (each ``send`` lets another thread run, which may then keep the GIL for up to the
        switch interval). The garbage collector is off for the same span.
        """
        mission.barriers.mark_released(step)
        store = self._store
        collecting = gc.isenabled()
        gc.disable()
        store.write_wanted.set()
        try:
            at = store.journal_release(mission.id, step)
            self._announce(mission, step)  # one datagram for every listening member first
            # One burst: encoded once, written to every member's socket in this pass.
            members = sorted(mission.barriers.members)
            self._commands.release_barrier(members, mission.id, step)
            with store.atomic():
                store.record_release(mission.id, step, at)
                self._events.publish(
                    "sync_released",
                    f"step {step} released to {len(members)} agents",
                    mission_id=mission.id,
                    data={"step": step, "agents": members},
                )
            store.release_recorded()
        finally:
            store.write_wanted.clear()
            if collecting:
                gc.enable()
        timer = mission.timers.pop(step, None)
        if timer is not None:
            timer.cancel()
        self._watchdog.arm(mission)

    def _announce(self, mission: ActiveMission, step: int) -> None:
        """The release beacon of ``step`` (protocol/beacon.py), when the mission has a chain."""
        if self._core.beacon is None or mission.chain is None:
            return
        value = mission.chain.value(step)
        if value is not None:
            self._core.beacon.send(mission.id, step, value)

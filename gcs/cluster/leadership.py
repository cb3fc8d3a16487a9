"""Lease rounds: which missions this daemon leads, whether it decides the airspace, takeovers.

Every ``cluster_lease_ttl_s / 3`` one round renews what this daemon holds and takes what nobody
holds (gcs/cluster/fencing.py has the leases themselves). The rounds ride through a NATS node
failing (docs/cluster.md, "Losing a NATS node"):

* each lease call is short (``Leases.op_timeout``) and one lease's call that got no answer does
  not hold up the others; the next round retries;
* no answer is no verdict: a mission whose lease ran out by our clock while NATS was silent is
  *suspended* (nothing decided, nothing given up) and resumes once the lease is renewed by
  compare-and-set on our own last write (nobody led it meanwhile); it is given up only when NATS
  says another daemon holds the lease or that it lapsed;
* a takeover (stamp, reload the shared records, rebuild the mission) runs beside the rounds, so
  the lease it took keeps being renewed however long NATS takes to answer.

The airspace decider is the holder of the ``airspace`` lease while the lease is good by its own
clock; a daemon cut off from NATS decides for its own drones only after ``local_after_s`` (by
then no other decider still counts them). Every decision is recorded with its lease term
(gcs/cluster/decisions.py): the evidence that two daemons never decide at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import TYPE_CHECKING

from gcs.cluster.decisions import FILE_NAME, DecisionLog
from gcs.cluster.fencing import LEASE_ERRORS, LeaseUncertain
from gcs.cluster.forwarding import AIRSPACE_LEASE
from gcs.cooperation.airspace import Airspace
from protocol.taskfile import TaskFile

if TYPE_CHECKING:
    from gcs.cluster.node import ClusterNode

log = logging.getLogger("gcs.cluster")

STALL_S = 0.5  # the lease loop woke this much later than asked: we were stalled (paused, starved)
ROUND_S = 1.0  # lease rounds at least this often: a lease's age when NATS stops answering is small
RIDE_THROUGH_TTL_S = 8.0  # a lease this long outlives a stream leader election (5-6.5 s, nats-server 2.9)


def settings_warnings(servers: int, replicas: int, lease_ttl_s: float) -> list[str]:
    """What a daemon says at start about cluster settings that work but do not survive what a
    cluster is for (docs/cluster.md, "In production"): several NATS servers with unreplicated
    buckets, a lease shorter than a JetStream leader election on replicated ones."""
    warnings = []
    if servers > 1 and replicas == 1:
        warnings.append(
            f"{servers} NATS servers listed but cluster_replicas is 1: each shared bucket lives on one "
            "server and is lost with it; set cluster_replicas = 3 on a three-node NATS cluster "
            "(docs/cluster.md, 'In production')"
        )
    if replicas > 1 and lease_ttl_s < RIDE_THROUGH_TTL_S:
        warnings.append(
            f"cluster_lease_ttl_s {lease_ttl_s:g} s is shorter than a JetStream leader election can take: "
            "losing a NATS node may leave missions without a deciding leader for seconds "
            f"({RIDE_THROUGH_TTL_S:g} s rides through; docs/cluster.md, 'Losing a NATS node')"
        )
    return warnings


class Leadership:
    """One daemon's lease rounds (``ClusterNode.leadership``)."""

    def __init__(self, node: ClusterNode) -> None:
        self.node = node
        self.state = node.state
        self.airspace_held = False  # the last lease round renewed (or took) the airspace lease
        self.local_after_s = node.config.cluster_lease_ttl_s  # cut off this long: decide locally
        self.held: set[str] = set()  # missions led here (their lease dropped when they finish)
        self.taking: dict[str, asyncio.Task[None]] = {}  # takeovers under way
        self.suspended: set[str] = set()  # led here, lease out by our clock, NATS silent
        self.takeovers: list[tuple[str, float]] = []  # (mission id, wall time) missions taken over
        self.step_downs = 0  # missions given up: their lease ran out or another daemon holds it
        self.last_term: dict[str, int] = {}  # mission -> token we last led it under
        self.decisions = DecisionLog(node.config.data_dir / FILE_NAME, node.daemon_id)
        config = node.config
        for warning in settings_warnings(
            len(config.cluster), config.cluster_replicas, config.cluster_lease_ttl_s
        ):
            log.warning("%s", warning)

    async def loop(self) -> None:
        period = min(ROUND_S, self.node.config.cluster_lease_ttl_s / 3)
        while True:
            asked = time.monotonic() + period
            await asyncio.sleep(period)
            late = time.monotonic() - asked
            if late > self.state.leases.margin:  # long enough to matter for a lease: say so
                log.warning("stalled for %.1f s; leases are judged by our clock before any decision", late)
            try:
                await self.tick(stalled=late > STALL_S)
            except Exception:  # a bug, or NATS gone in a way the calls below do not expect
                log.warning("lease round failed", exc_info=True)

    async def stop(self) -> None:
        for task in list(self.taking.values()):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self.decisions.close()

    async def tick(self, stalled: bool = False) -> None:
        """One lease round. After a stall of ours (``stalled``) the remote agents' silence is not
        judged: their reports waited unread in our NATS connection, they come in first."""
        missions = self.node.daemon.missions
        leases = self.state.leases
        for mission_id in list(missions.active):  # by our clock first: a stale leader steps down
            if not leases.valid(mission_id) and mission_id not in leases.pending:
                await self.may_decide(mission_id)
        if not stalled:
            await self.node.sweep_remote()
        await self._renew_airspace()
        for mission_id in list(missions.active) + list(self.taking):
            if mission_id not in leases.pending:  # submitted here, its take still queued
                await self._renew(mission_id)
        finished = {m.id for m in self.node.store.missions() if m.state != "running"}
        for mission_id in finished & self.held:
            await self.state.drop_lease(mission_id)
            self.held.discard(mission_id)
        for stored in self.node.store.missions("running"):
            if stored.id in missions.active or stored.id in self.taking:
                self.held.add(stored.id)
                continue
            with contextlib.suppress(*LEASE_ERRORS):  # no answer: the next round asks again
                holder, _ = await self.state.lease_holder(stored.id)
                if holder is None and await self.state.take_lease(stored.id):
                    self._start_takeover(stored.id)
                elif holder == self.node.daemon_id and await self.state.leases.renew(stored.id, False):
                    self._start_takeover(stored.id)  # we stepped down by our clock, yet still hold it

    async def _renew_airspace(self) -> None:
        was = self.airspace_held
        try:
            holder, _ = await self.state.lease_holder(AIRSPACE_LEASE)
            self.airspace_held = holder in (None, self.node.daemon_id) and await self.state.renew_lease(
                AIRSPACE_LEASE
            )
        except LEASE_ERRORS as exc:  # no answer: our clock says how long we still decide
            log.debug("airspace lease round: %r", exc)
        if self.airspace_held != was:
            log.info("%s the airspace lease", "took" if self.airspace_held else "lost")

    async def _renew(self, mission_id: str) -> None:
        """Renew a mission's lease; let go only when NATS says it is not ours any more."""
        token = self.state.leases.token(mission_id)
        try:
            renewed = await self.state.leases.renew(mission_id, take_if_free=False)
        except LEASE_ERRORS as exc:
            log.debug("lease of %s not renewed this round: %r", mission_id, exc)
            return
        if not renewed:
            with contextlib.suppress(*LEASE_ERRORS):
                holder, _ = await self.state.lease_holder(mission_id)
                log.warning("lost the lead of %s to %s; following", mission_id, holder)
            self._let_go(mission_id, "another daemon holds its lease, or it lapsed", token)
        elif mission_id in self.suspended:
            self.suspended.discard(mission_id)
            log.info("lease of %s renewed: deciding again", mission_id)
            if mission_id in self.node.daemon.missions.active:
                with contextlib.suppress(LeaseUncertain):  # NATS slow again: an agent's report retries
                    await self.node.daemon.missions.release_ready(mission_id)  # arrivals meanwhile

    async def may_decide(self, mission_id: str) -> bool:
        """The runner asks before every decision about a mission it runs: True while our lease is
        good by our own clock (renewed once if the clock ran out). If NATS does not answer the
        mission is suspended (nothing decided, kept here); if the lease is lost we step down
        first (the runner forgets the mission; a later round follows or takes it over afresh)."""
        leases = self.state.leases
        token = leases.token(mission_id)
        verdict = await leases.confirm(mission_id)
        if verdict:
            self.decisions.note(f"mission:{mission_id}", "fleet", leases.token(mission_id) or 0)
            return True
        if verdict is None and mission_id in self.node.daemon.missions.active:
            if mission_id not in self.suspended:
                self.suspended.add(mission_id)
                log.warning("lease of %s ran out by our clock, NATS silent: deciding nothing", mission_id)
            return False
        self._let_go(mission_id, "its lease ran out by this daemon's clock", token)
        return False

    def _let_go(self, mission_id: str, why: str, token: int | None) -> None:
        """Stop leading ``mission_id`` (led under ``token``, remembered: a takeover of a mission we
        led last needs no reload)."""
        self.suspended.discard(mission_id)
        if token is not None and mission_id in self.node.daemon.missions.active:
            self.last_term[mission_id] = token
        self.state.leases.step_down(mission_id)
        taking = self.taking.pop(mission_id, None)
        if taking is not None:
            taking.cancel()
        missions = self.node.daemon.missions
        if mission_id not in missions.active:
            return
        log.warning("no longer leading %s (%s): stepping down before any decision", mission_id, why)
        self.step_downs += 1
        missions.forget(mission_id)
        self.node.daemon.events.publish(
            "mission_step_down",
            f"{self.node.daemon_id} no longer leads it ({why})",
            severity="warning",
            mission_id=mission_id,
        )

    def _start_takeover(self, mission_id: str) -> None:
        if mission_id in self.taking:
            return
        task = asyncio.create_task(self._take_over(mission_id), name=f"cluster-takeover-{mission_id}")
        self.taking[mission_id] = task
        task.add_done_callback(lambda _t: self.taking.pop(mission_id, None))

    async def _take_over(self, mission_id: str) -> None:
        try:
            await self._take_over_now(mission_id)
        except Exception as exc:  # NATS away again mid-way: the lease goes back, a round retries
            log.warning("taking %s over failed (%r); the next round retries", mission_id, exc)
            await self.state.drop_lease(mission_id)

    async def _take_over_now(self, mission_id: str) -> None:
        node = self.node
        missions = node.daemon.missions
        leases = self.state.leases
        last = self.last_term.get(mission_id)
        if not await leases.stamp(mission_id):  # our token on the record first: fenced
            log.warning("could not stamp %s with our lease token; not taking it over", mission_id)
            await self.state.drop_lease(mission_id)
            return
        if last is None or leases.stamped_over.get(mission_id) != last:
            # another daemon led it since (or we never did): the mission's records read afresh
            # (whatever our watchers missed), key by key: a bucket reload needs new consumers,
            # hence NATS's metadata leader, maybe re-electing too (a node died)
            await self._refresh(mission_id)
        # else we led it last (our lease lapsed while NATS re-elected a leader): our mirror holds
        # every write of ours and nobody else wrote since
        if not leases.valid(mission_id) and not await leases.confirm(mission_id):
            log.warning("lease of %s ran out while taking it over; the next round retries", mission_id)
            leases.step_down(mission_id)
            return
        mission = missions.restore_one(mission_id)
        if mission is None:
            return
        self.held.add(mission_id)
        self.takeovers.append((mission_id, time.time()))
        missions.count_arrivals(mission_id, node.store.arrivals(mission_id))
        node.daemon.events.publish(
            "mission_takeover",
            f"{node.daemon_id} leads {mission.task.name} now (previous leader's lease expired)",
            mission_id=mission_id,
        )
        with contextlib.suppress(LeaseUncertain):  # NATS slow again: an agent's report retries
            await missions.release_ready(mission_id)
        await node.heal(mission_id)

    async def _refresh(self, mission_id: str) -> None:
        """The records a takeover rebuilds the mission from: the mission's, each member's
        progress, each barrier's release (arrivals come back in the members' status reports);
        the mirrors are reloaded in the background too."""
        await self.state.refresh("missions", [mission_id])
        stored = self.node.store.mission(mission_id)
        if stored is None:
            return
        task = TaskFile.model_validate_json(stored.task_json)
        steps = sorted({step for plan in task.plans for step in plan.sync_steps()})
        progress = {k for k in self.state.mirror["progress"] if k.startswith(f"{mission_id}.")}
        progress |= {f"{mission_id}.{plan.agent}" for plan in task.plans}  # by name (or a CID: absent)
        await self.state.refresh("progress", sorted(progress))
        await self.state.refresh("barriers", [f"{mission_id}.{step}.released" for step in steps])
        self.state.resync_soon()

    def airspace(self) -> Airspace:
        """Whose collisions we decide: the whole fleet (we hold the airspace lease, good by our
        clock), only our own agents (cut off from NATS longer than ``local_after_s``: nobody else
        can reach them, nor still counts them), or none (another daemon decides). Each decision
        is recorded with its lease term."""
        leases = self.state.leases
        if self.airspace_held and leases.valid(AIRSPACE_LEASE):
            scope: Airspace = "fleet"
        elif self.state.cut_off_s() > self.local_after_s:
            scope = "local"
        else:
            return "none"
        self.decisions.note("airspace", scope, leases.token(AIRSPACE_LEASE) or 0 if scope == "fleet" else 0)
        return scope

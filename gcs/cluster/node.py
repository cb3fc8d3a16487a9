"""A daemon's membership of the cluster: shared state, remote agents, mission leases, takeover.

Each daemon serves the agents linked to it. Everything an agent says is shared: its status on
``fleet.status.<identity>`` (plain subject; the FLEET_TELEMETRY stream keeps it with limits), its
joins, barrier arrivals and losses on ``fleet.up.<identity>``, its arrivals also in the
``fleet_barriers`` bucket. Every other daemon mirrors it as a :class:`RemoteSession`, so its
mission runner and API see the whole fleet; what a runner sends to a remote agent goes out on
``fleet.down.<identity>`` and the daemon holding the link posts it.

One daemon leads each mission: it holds the mission's key in the ``fleet_leases`` bucket (TTL
``cluster_lease_ttl_s``, renewed every third of it, at least every second) and runs its
barriers; the others ignore it (gcs/cluster/leadership.py). When the leader dies the lease
expires, a standby takes it (compare-and-set: one winner), rebuilds the mission from the shared
records and carries on. Agents waiting at a barrier say so in every status report, so the new
leader also heals what died in flight (a 'finished' or a 'release').

Commands for a drone linked to another daemon (a mission's plan, a collision hold or escape, a
return) travel as the type-4 packet on ``fleet.down`` and pass the holding daemon's vehicle
authority there with their original source, so its operator's and its vehicle's orders are never
undone; the holder answers each on ``fleet.result.<sender>`` (delivered or refused, and why), so
the sender records a refusal and its airspace decider sees the drone outranked at once.

Who holds an agent's link comes from one place: its ``fleet_agents`` record, claimed by
compare-and-set on every join. The record's revision is the link's epoch; every message about the
agent carries it, and a message of an older epoch (from a daemon the agent has left) is ignored.

The airspace (the collision check over the whole fleet) is decided by one daemon at a
time, the holder of the ``airspace`` lease (docs/cluster.md); it also prunes finished missions.

A daemon that was paused or stalled does not act on stale state when it wakes: every lease is
judged by its own monotonic clock before any decision (it steps down first when the lease ran
out), and every leader write and forwarded order carries the lease's fencing token, refused
once a newer leader stamped the mission record (gcs/cluster/fencing.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

from gcs.cluster.commands import OperatorRoute
from gcs.cluster.fencing import LeaseUncertain
from gcs.cluster.forwarding import AIRSPACE_LEASE, Forwarder, frame, unframe
from gcs.cluster.housekeeping import prune_round
from gcs.cluster.leadership import Leadership
from gcs.cluster.releases import ReleaseClaims
from gcs.cluster.state import ClusterState
from gcs.cluster.store import ClusterStore
from gcs.control.authority import PRIORITY, VehicleControl
from gcs.cooperation.airspace import Airspace
from gcs.cooperation.return_coordinator import VehicleView
from gcs.cooperation.service import CooperationService
from gcs.core.config import DaemonConfig
from gcs.link.session import AgentSession
from protocol.packets import (
    Body,
    Capabilities,
    GeoPoint,
    Resume,
    StatusReport,
    SyncSignal,
)

if TYPE_CHECKING:
    from nats.aio.msg import Msg

    from gcs.core.context import DaemonParts

log = logging.getLogger("gcs.cluster")

NUDGE_EVERY_S = 1.0  # re-send a release / re-count an arrival seen in status at most this often


def default_daemon_id(config: DaemonConfig) -> str:
    host = "".join(c if c.isalnum() or c in "-_" else "-" for c in socket.gethostname())
    return f"{host}-{os.getpid()}"


@dataclass(eq=False)
class RemoteSession(AgentSession):
    """An agent linked to another daemon: what it reports arrives over NATS, what we post goes back."""

    daemon: str = ""
    node: ClusterNode | None = None
    level: int = 0  # authority level at the holding daemon (from its status headers)
    control: str = ""  # what controls it there above the plan ("operator rtl (...)"), if anything
    collision_held: bool = False  # the holding daemon has it under a collision hold
    epoch: int = 0  # revision of the registry record naming ``daemon`` as the link's holder

    @property
    def last_tx(self) -> float:
        return self.last_rx

    def post(self, body: Body, *, urgent: bool | None = None) -> bool:
        if not self.open or self.node is None:
            return False
        self.node.forward(self.identity, body, bool(urgent))
        return True

    async def send(
        self,
        body: Body,
        timeout: float | None = None,
        max_pending: int | None = None,
        *,
        urgent: bool | None = None,
    ) -> bool:
        return self.post(body, urgent=urgent)

    async def close(
        self, reason: Any, message: str, timeout: float = 1.0, *, code: Any | None = None
    ) -> None:
        self.open = False

    def close_transport(self) -> None:
        self.open = False


def _control(control: VehicleControl) -> str:
    """What controls a drone above its plan, in a few words: "operator rtl", "operator hold (why)"."""
    if control.order is not None:
        return f"{control.order_source} {control.order}"
    if control.holds:
        return ", ".join(f"{owner} hold ({why})" for owner, why in control.holds.items())[:200]
    return f"vehicle failsafe {control.failsafe}" if control.failsafe else control.level


class ClusterNode:
    """Joins a daemon to the cluster (``gcs serve --cluster``); built before the daemon's parts."""

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.daemon_id = config.daemon_id or default_daemon_id(config)
        self.state = ClusterState(
            config.cluster, self.daemon_id, config.cluster_replicas, config.cluster_lease_ttl_s
        )
        self.store = ClusterStore(config.database_path, self.state)
        self._daemon: DaemonParts | None = None
        self._subs: list[Any] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._nudged: dict[tuple[str, str, int], float] = {}
        self._nudging: set[asyncio.Task[None]] = set()
        self.pruned_keys = 0
        self._epochs: dict[str, tuple[int, str]] = {}  # agent -> newest (epoch, holder) known
        self._local_epoch: dict[str, int] = {}  # agent -> epoch of our link to it (0: unknown)
        self.stale_dropped = 0  # messages ignored: sent under an agent's older link epoch
        self.forwarder = Forwarder(self)
        self.operator_route = OperatorRoute(self)
        self.refusals = self.forwarder.refusals  # holders' refusals of our commands
        self.leadership = Leadership(self)  # lease rounds, takeovers, the airspace scope
        self.releases = ReleaseClaims(self)

    @property
    def daemon(self) -> DaemonParts:
        assert self._daemon is not None, "cluster node not started"
        return self._daemon

    # --- lifecycle -------------------------------------------------------------------------------

    async def start(self, daemon: DaemonParts) -> None:
        """Connect, load the shared state, hook into the daemon, take over orphaned missions."""
        self._daemon = daemon
        await self.state.connect()
        agents = daemon.agents
        agents.registry.holder_of = self.holder  # every view names the holder from the registry's epoch
        self.state.on_change.append(self._registry_change)
        for identity, revision in list(self.state.revisions.items()):
            record = self.state.agent_record(identity)
            if record is not None:
                self._note_holder(identity, revision, str(record["daemon"]))
        agents.on_join.append(self._local_join)
        agents.on_status.append(self._local_status)
        agents.on_sync.append(self._local_sync)
        agents.on_lost.append(self._local_lost)
        nc = self.state.nc
        assert nc is not None
        self._subs = [
            await nc.subscribe("fleet.status.>", cb=self._remote_status),
            await nc.subscribe("fleet.up.>", cb=self._remote_up),
            await nc.subscribe("fleet.down.>", cb=self.forwarder.down),
            await nc.subscribe(f"fleet.cmd.{self.daemon_id}", cb=self.operator_route.answer),
            await nc.subscribe(f"fleet.result.{self.daemon_id}", cb=self.forwarder.result),
        ]
        await self.leadership.tick()
        self._tasks.append(asyncio.create_task(self.leadership.loop(), name="cluster-leases"))
        self._tasks.append(asyncio.create_task(self._prune_loop(), name="cluster-prune"))

    def fleet_view(self, local: Callable[[], dict[str, VehicleView]]) -> Callable[[], dict[str, VehicleView]]:
        """The return coordinator's fleet view (plugged in by the composition root): returns
        deconflict against every airborne drone of the cluster, not only ``local``'s."""

        def fleet_view() -> dict[str, VehicleView]:
            view = local()
            if self._daemon is None:
                return view
            for identity, remote in list(self._daemon.agents.remote.items()):
                status = remote.status
                if remote.open and status is not None and status.position is not None:
                    view.setdefault(identity, VehicleView(status, status.position, remote.home))
            return view

        return fleet_view

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        await self.leadership.stop()
        for sub in self._subs:
            with contextlib.suppress(Exception):
                await sub.unsubscribe()
        if self._daemon is not None:
            for mission_id in list(self._daemon.missions.active):
                await self.state.drop_lease(mission_id)  # a clean stop hands over at once
            await self.state.drop_lease(AIRSPACE_LEASE)  # only if still ours
        await self.state.close()

    def _cooperation(self) -> list[CooperationService]:
        return [s for s in self.daemon.services if isinstance(s, CooperationService)]

    # --- leases (gcs/cluster/leadership.py) ---------------------------------------------------------

    async def may_decide(self, mission_id: str) -> bool:
        """The runner asks before every decision about a mission it runs (:meth:`Leadership.may_decide`)."""
        return await self.leadership.may_decide(mission_id)

    async def sweep_remote(self) -> None:
        """Mirrors of agents nobody has reported for ``remote_lost_after_s`` (their daemon died, or
        stalled longer than its agents wait before moving) go."""
        now = time.monotonic()
        agents = self.daemon.agents
        for identity, remote in list(agents.remote.items()):
            if now - remote.last_rx > self.config.remote_lost_after_s:
                await self._remote_gone(identity, remote)

    async def _remote_gone(self, identity: str, remote: AgentSession) -> None:
        remote.open = False
        self.daemon.agents.remote.pop(identity, None)
        for service in self._cooperation():
            await service.remote_lost(identity)
        await self.daemon.missions.agent_lost(identity)

    async def _prune_loop(self) -> None:
        """The airspace lease holder prunes finished missions' keys (gcs/cluster/housekeeping.py)."""
        after = self.config.cluster_prune_after_s
        period = min(30.0, max(1.0, after / 4))
        while True:
            await asyncio.sleep(period)
            if not self.leadership.airspace_held or not self.state.leases.valid(AIRSPACE_LEASE):
                continue
            try:
                self.pruned_keys += await prune_round(self.state, after)
            except Exception:  # NATS away: the next round goes on where this one stopped
                log.warning("prune round failed", exc_info=True)

    async def heal(self, mission_id: str) -> None:
        """After a takeover: what died in flight (a 'finished', a 'release') is healed from the
        members' last status reports."""
        mission = self.daemon.missions.active.get(mission_id)
        for identity in self.daemon.missions.members(mission) if mission is not None else []:
            session = self.daemon.agents.session(identity)
            if session is not None and session.status is not None:
                await self._nudge(session, session.status)

    # --- the mission runner's view of the cluster (gcs.missions.runner.MissionCluster) ---------------------

    async def claim_release(self, mission_id: str, step: int) -> bool:
        """Claim a barrier's release (:meth:`ReleaseClaims.claim`)."""
        return await self.releases.claim(mission_id, step)

    def led_elsewhere(self, mission_id: str) -> bool:
        stored = self.store.mission(mission_id)
        return stored is not None and mission_id not in self.daemon.missions.active

    async def withdraw_elsewhere(self, identity: str, reason: str) -> None:
        """One of our agents leaves its mission (an operator RTL, an emergency) but another daemon
        leads that mission: tell it, so its barriers stop waiting for the agent."""
        session = self.daemon.agents.sessions.get(identity)
        if session is not None and session.open:
            self._up(session, "withdraw", reason.encode()[:500])

    # --- the cooperation service's view of the cluster (gcs.cooperation.airspace.ClusterView) -----

    def airspace(self) -> Airspace:
        """Whose collisions we decide (:meth:`Leadership.airspace`)."""
        return self.leadership.airspace()

    def remote_level(self, ident: str) -> int:
        remote = self.daemon.agents.remote.get(ident)
        return remote.level if isinstance(remote, RemoteSession) and remote.open else 0

    def remote_collision_hold(self, ident: str) -> bool:
        remote = self.daemon.agents.remote.get(ident)
        return isinstance(remote, RemoteSession) and remote.open and remote.collision_held

    def remote_blocker(self, ident: str) -> str | None:
        """What outranks a mission on a drone linked to another daemon (the mission runner's
        submit refuses the drone then, as it does for its own drones' authority)."""
        remote = self.daemon.agents.remote.get(ident)
        if not isinstance(remote, RemoteSession) or not remote.open or remote.level <= PRIORITY["mission"]:
            return None
        return f"{remote.control or f'level {remote.level}'} control at {remote.daemon}"

    # --- who holds each link: the registry record's revision is its epoch ----------------------------

    def _note_holder(self, identity: str, epoch: int, daemon: str) -> None:
        """Remember the newest known holder; a newer epoch naming another daemon means our own
        link to the agent (if we still think we have one) is stale: it moved, so we drop it."""
        known = self._epochs.get(identity)
        if known is not None and known[0] >= epoch:
            return
        self._epochs[identity] = (epoch, daemon)
        if self._daemon is None:
            return
        if daemon == self.daemon_id:
            local = self.daemon.agents.sessions.get(identity)
            if local is not None and local.open and not self._local_epoch.get(identity):
                self._local_epoch[identity] = epoch  # our claim was queued (NATS away): it landed
            return
        remote = self.daemon.agents.remote.get(identity)
        if isinstance(remote, RemoteSession) and remote.open:
            remote.daemon, remote.peer, remote.epoch = daemon, f"via {daemon}", epoch
        local = self.daemon.agents.sessions.get(identity)
        ours = self._local_epoch.get(identity, 0)
        if local is not None and local.open and 0 < ours < epoch:
            log.warning("%s's link moved to %s (epoch %d > %d); dropping ours", identity, daemon, epoch, ours)
            local.close_transport()

    def link_epoch(self, identity: str) -> tuple[int, str] | None:
        """(epoch, daemon) of the newest holder of ``identity``'s link known here."""
        return self._epochs.get(identity)

    def _registry_change(self, bucket: str, key: str, value: bytes | None) -> None:
        if bucket != "agents" or value is None:
            return
        with contextlib.suppress(ValueError, KeyError, TypeError):
            self._note_holder(key, self.state.revisions.get(key, 0), str(json.loads(value)["daemon"]))

    # --- our agents: share what they say ------------------------------------------------------------

    def _headers(self, session: AgentSession) -> dict[str, str]:
        epoch = self._local_epoch.get(session.identity, 0)
        return {"daemon": self.daemon_id, "cid": str(session.cid), "rev": str(epoch)}

    def _up(self, session: AgentSession, kind: str, payload: bytes) -> None:
        nc = self.state.nc
        if nc is None or nc.is_closed:
            return
        headers = {**self._headers(session), "kind": kind}
        self.state.send(f"fleet.up.{session.identity}", payload, headers=headers)

    async def _local_join(self, session: AgentSession, resume: Resume | None) -> None:
        self.daemon.agents.remote.pop(session.identity, None)
        authority = self.daemon.authority
        held = [(o, r) for a, o, r in self.store.holds() if a == session.identity]
        for owner, reason in held:  # an operator hold given while it was linked to another daemon
            if not authority.is_held(session.identity, owner):
                authority.restore_hold(session.identity, owner, reason)
        if held:
            authority.reassert(session.identity)
        epoch = await self.state.claim_agent(session.identity, session.cid)
        self._local_epoch[session.identity] = epoch
        self._note_holder(session.identity, epoch, self.daemon_id)
        join = {
            "resume": resume.model_dump(mode="json") if resume else None,
            "home": session.home.model_dump(mode="json") if session.home else None,
            "capabilities": session.capabilities.model_dump(mode="json"),
        }
        self._up(session, "join", json.dumps(join).encode())

    async def _local_status(self, session: AgentSession, status: StatusReport) -> None:
        nc = self.state.nc
        if nc is not None and not nc.is_closed:
            authority = self.daemon.authority
            level = authority.level(session.identity)
            headers = {
                **self._headers(session),
                "level": str(level),  # the airspace decider and mission submits read these
                "collision": "1" if authority.is_held(session.identity, "collision") else "",
            }
            if level:
                headers["control"] = _control(authority.control(session.identity))
            with contextlib.suppress(Exception):
                await nc.publish(f"fleet.status.{session.identity}", frame(status), headers=headers)
        self._nudge_soon(session, status)

    async def _local_sync(self, session: AgentSession, signal: SyncSignal) -> None:
        key = f"{signal.mission_id}.{signal.step}.arrived.{session.identity}"
        if key not in self.state.mirror["barriers"]:
            self.state.mirror["barriers"][key] = b"1"
            value = self.state.unique()
            self.state.enqueue(lambda: self.state.create("barriers", key, value))
        self._up(session, "sync", frame(signal))

    async def _local_lost(self, identity: str) -> None:
        remote = self.daemon.agents.remote.get(identity)
        known = self._epochs.get(identity)
        if (remote is not None and remote.open) or (known is not None and known[1] != self.daemon_id):
            return  # its link moved to another daemon: lost here only
        session = self.daemon.agents.sessions.get(identity)
        if session is not None:
            self._up(session, "lost", b"")

    # --- other daemons' agents --------------------------------------------------------------------

    def _remote(self, msg: Msg) -> RemoteSession | None:
        """The mirror of the agent a message is about; None if it is ours, from us, or stale (sent
        under an older epoch than the newest holder we know of: the agent has left that daemon)."""
        headers = msg.headers or {}
        daemon = headers.get("daemon", "")
        identity = msg.subject.split(".", 2)[2]
        if daemon == self.daemon_id:
            return None
        try:
            epoch = int(headers.get("rev", "0"))
        except ValueError:
            epoch = 0
        known = self._epochs.get(identity)
        if known is not None and (epoch < known[0] if epoch else known[1] != daemon):
            self.stale_dropped += 1
            return None
        if epoch:
            self._note_holder(identity, epoch, daemon)
        local = self.daemon.agents.sessions.get(identity)
        if local is not None and local.open:
            return None  # it is linked to us now (a newer epoch elsewhere has just dropped a stale link)
        agents = self.daemon.agents
        remote = agents.remote.get(identity)
        if not isinstance(remote, RemoteSession) or not remote.open:
            remote = RemoteSession(
                identity=identity,
                cid=int(headers.get("cid", "0")),
                capabilities=Capabilities(),
                home=None,
                writer=cast(Any, None),
                peer=f"via {daemon}",
                outbox=cast(Any, None),
                daemon=daemon,
                node=self,
            )
            agents.remote[identity] = remote
        remote.daemon, remote.peer = daemon, f"via {daemon}"
        remote.epoch = max(remote.epoch, epoch)
        remote.last_rx = time.monotonic()
        return remote

    async def _remote_status(self, msg: Msg) -> None:
        remote = self._remote(msg)
        if remote is None:
            return
        status = unframe(msg.data)
        if not isinstance(status, StatusReport):
            return
        headers = msg.headers or {}
        with contextlib.suppress(ValueError):
            remote.level = int(headers.get("level", "0"))
        remote.control = headers.get("control", "")
        remote.collision_held = bool(headers.get("collision"))
        if not status.buffered:
            remote.status = status
            self.daemon.authority.observe(remote.identity, status)  # orders we gave it end when it lands
        remote.status_count += 1
        from gcs.observe.live import LiveHub

        for hub in self.daemon.services:  # the dashboard's stream and history show the whole fleet
            if isinstance(hub, LiveHub):
                await hub.remote_status(remote, status)
        for service in self._cooperation():  # the airspace picture spans the cluster
            await service.remote_status(remote, status)
        await self.daemon.missions.agent_status(remote, status)
        self._nudge_soon(remote, status)

    async def _remote_up(self, msg: Msg) -> None:
        remote = self._remote(msg)
        if remote is None:
            return
        kind = (msg.headers or {}).get("kind")
        missions = self.daemon.missions
        if kind == "join":
            join = json.loads(msg.data)
            remote.home = GeoPoint.model_validate(join["home"]) if join["home"] else None
            remote.capabilities = Capabilities.model_validate(join["capabilities"])
            resume = Resume.model_validate(join["resume"]) if join["resume"] else None
            await missions.agent_joined(remote, resume)
        elif kind == "sync":
            signal = unframe(msg.data)
            if isinstance(signal, SyncSignal):
                await missions.agent_finished(remote, signal)
        elif kind == "lost":
            await self._remote_gone(remote.identity, remote)
        elif kind == "withdraw":  # its daemon took it out of a mission (we may lead it)
            await missions.withdraw(remote.identity, msg.data.decode(errors="replace"))

    def _nudge_soon(self, session: AgentSession, status: StatusReport) -> None:
        """:meth:`_nudge` beside the status path (decided here, acted on in its own task): a
        release claim waiting on NATS (a stream re-electing its leader) must not hold up every
        other report behind it."""
        what = self._nudge_wanted(session, status)
        if what is not None:
            task = asyncio.create_task(self._nudge_act(session, status, what))
            self._nudging.add(task)
            task.add_done_callback(self._nudging.discard)

    async def _nudge(self, session: AgentSession, status: StatusReport) -> None:
        what = self._nudge_wanted(session, status)
        if what is not None:
            await self._nudge_act(session, status, what)

    def _nudge_wanted(self, session: AgentSession, status: StatusReport) -> str | None:
        """As leader, what an agent reporting a wait at a barrier needs (at most every
        NUDGE_EVERY_S): the release again ("release", the barrier was released), its arrival
        counted ("arrive", the signal died in flight), or the complete barrier released
        ("retry", an earlier claim got no answer)."""
        step, mission_id = status.waiting_sync, status.mission_id
        if step is None or mission_id is None:
            return None
        mission = self.daemon.missions.active.get(mission_id)
        if mission is None or session.identity not in mission.barriers.members:
            return None
        released = step in mission.barriers.released
        arrived = session.identity in mission.barriers.arrivals.get(step, set())
        if not released and arrived and mission.barriers.missing(step):
            return None
        key = (session.identity, mission_id, step)
        now = time.monotonic()
        if now - self._nudged.get(key, 0.0) < NUDGE_EVERY_S:
            return None
        self._nudged[key] = now
        return "release" if released else "retry" if arrived else "arrive"

    async def _nudge_act(self, session: AgentSession, status: StatusReport, what: str) -> None:
        mission_id, step = status.mission_id or "", status.waiting_sync or 0
        if what == "release":
            self.daemon.commands.release_barrier([session.identity], mission_id, step)
            return
        with contextlib.suppress(LeaseUncertain):  # still no answer: its next report retries
            if what == "retry":
                await self.daemon.missions.release_ready(mission_id)
            else:
                signal = SyncSignal(mission_id=mission_id, step=step, kind="finished")
                await self.daemon.missions.agent_finished(session, signal)

    # --- what other daemons send our agents (gcs/cluster/forwarding.py) -----------------------------

    def forward(self, identity: str, body: Body, urgent: bool) -> None:
        """Post ``body`` through the daemon holding the link (:meth:`Forwarder.forward`)."""
        self.forwarder.forward(identity, body, urgent)

    # --- operator commands for any drone (gcs/cluster/commands.py) ------------------------------

    def holder(self, identity: str) -> str | None:
        """The daemon holding ``identity``'s link: ours if linked here, else the registry's (the
        newest epoch, from its record or a message that arrived before the record did)."""
        local = self.daemon.agents.sessions.get(identity)
        if local is not None and local.open:
            return self.daemon_id
        known = self._epochs.get(identity)
        if known is not None:
            return known[1]
        record = self.state.agent_record(identity)
        return None if record is None else str(record["daemon"])

    async def command(
        self, command: str, agents: list[str] | None, reason: str
    ) -> tuple[list[str], dict[str, str]]:
        """Run an operator command on each drone's own daemon (:meth:`OperatorRoute.command`)."""
        return await self.operator_route.command(command, agents, reason)

    # --- the whole fleet ---------------------------------------------------------------------------------

    def fleet_identities(self) -> set[str]:
        agents = self.daemon.agents
        return {s.identity for s in agents.connected()} | {i for i, s in agents.remote.items() if s.open}

    def fleet(self) -> list[dict[str, Any]]:
        """Every agent the cluster knows: where its link is, and its last status. The session shown
        and the daemon named are the ones every other view uses (``AgentManager.link`` and
        :meth:`holder`), so an agent that moved is shown once, at its new daemon, everywhere."""
        agents = self.daemon.agents
        records = self.state.json_values("agents")
        shown = {s.identity: s for s in agents.fleet()}
        rows = []
        now = time.monotonic()
        for identity in sorted(records.keys() | shown.keys()):
            session = shown.get(identity)
            live = session is not None and session.open and now - session.last_rx < self.config.lost_after_s
            record = records.get(identity)
            rows.append(
                {
                    "identity": identity,
                    "cid": record["cid"] if record is not None else session.cid if session else 0,
                    "daemon": self.holder(identity),
                    "local": session is not None and session is agents.sessions.get(identity),
                    "connected": live,
                    "status": session.status.model_dump(mode="json") if session and session.status else None,
                }
            )
        return rows

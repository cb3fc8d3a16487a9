"""A daemon's membership of the cluster: shared state, remote agents, mission leases, takeover.

Each daemon serves the agents linked to it. Everything an agent says is shared: its status on
``fleet.status.<identity>`` (plain subject; the FLEET_TELEMETRY stream keeps it with limits), its
joins, barrier arrivals and losses on ``fleet.up.<identity>``, its arrivals also in the
``fleet_barriers`` bucket. Every other daemon mirrors it as a :class:`RemoteSession`, so its
mission runner and API see the whole fleet; what a runner sends to a remote agent goes out on
``fleet.down.<identity>`` and the daemon holding the link posts it.

One daemon leads each mission: it holds the mission's key in the ``fleet_leases`` bucket (TTL
``cluster_lease_ttl_s``, renewed every third of it) and runs its barriers; the others ignore it.
When the leader dies the lease expires, a standby takes it (compare-and-set: one winner), rebuilds
the mission from the shared records and carries on. Agents waiting at a barrier say so in every
status report, so the new leader also heals what died in flight (a 'finished' or a 'release').

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
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

from gcs.agents import AgentSession
from gcs.authority import PRIORITY, VehicleControl
from gcs.cluster.housekeeping import prune_round
from gcs.cluster.state import ClusterState
from gcs.cluster.store import ClusterStore
from gcs.config import DaemonConfig
from gcs.cooperation.return_coordinator import VehicleView
from gcs.cooperation.returns import RETURN_PREFIX
from gcs.cooperation.service import Airspace, CooperationService
from protocol.packets import (
    Body,
    Capabilities,
    GeoPoint,
    PerformActions,
    Resume,
    StatusReport,
    SyncSignal,
)
from protocol.wire import FrameDecoder, encode

if TYPE_CHECKING:
    from nats.aio.msg import Msg

    from gcs.daemon import Daemon

log = logging.getLogger("gcs.cluster")

NUDGE_EVERY_S = 1.0  # re-send a release / re-count an arrival seen in status at most this often
COMMAND_TIMEOUT_S = 5.0
PENDING_LIMIT = 2000  # forwarded commands awaiting the holder's answer (oldest dropped beyond)
PENDING_TTL_S = 30.0  # an answer later than this is logged without its command
AIRSPACE_LEASE = "airspace"  # its holder decides collisions for the whole fleet and prunes


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


def _order_kind(owner: str, mission_id: str) -> str | None:
    """The order a forwarded replace gives, as the sending authority recorded it: a return program
    (its mission id says rtl or land) above the mission's level; nothing else is an order."""
    if PRIORITY[owner] > PRIORITY["mission"] and mission_id.startswith(RETURN_PREFIX):
        return mission_id[len(RETURN_PREFIX) :].split("-", 1)[0]
    return None


def _control(control: VehicleControl) -> str:
    """What controls a drone above its plan, in a few words: "operator rtl", "operator hold (why)"."""
    if control.order is not None:
        return f"{control.order_source} {control.order}"
    if control.holds:
        return ", ".join(f"{owner} hold ({why})" for owner, why in control.holds.items())[:200]
    return f"vehicle failsafe {control.failsafe}" if control.failsafe else control.level


def _frame(body: Body) -> bytes:
    return encode(body, 0)


def _body(data: bytes) -> Body | None:
    frames = list(FrameDecoder().feed(data))
    return frames[0].body if frames else None


class ClusterNode:
    """Joins a daemon to the cluster (``gcs serve --cluster``); built before the daemon's parts."""

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.daemon_id = config.daemon_id or default_daemon_id(config)
        self.state = ClusterState(
            config.cluster, self.daemon_id, config.cluster_replicas, config.cluster_lease_ttl_s
        )
        self.store = ClusterStore(config.database_path, self.state)
        self.takeovers: list[tuple[str, float]] = []  # (mission id, wall time) missions taken over
        self._daemon: Daemon | None = None
        self._subs: list[Any] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._nudged: dict[tuple[str, str, int], float] = {}
        self._held_leases: set[str] = set()
        self._airspace = False  # we hold the airspace lease
        self.pruned_keys = 0
        self._epochs: dict[str, tuple[int, str]] = {}  # agent -> newest (epoch, holder) known
        self._local_epoch: dict[str, int] = {}  # agent -> epoch of our link to it (0: unknown)
        self._pending: dict[int, tuple[str, str, float]] = {}  # seq -> (agent, command, sent at)
        self._seq = 0
        self.refusals: deque[dict[str, Any]] = deque(maxlen=200)  # holders' refusals of our commands
        self.stale_dropped = 0  # messages ignored: sent under an agent's older link epoch

    @property
    def daemon(self) -> Daemon:
        assert self._daemon is not None, "cluster node not started"
        return self._daemon

    # --- lifecycle -------------------------------------------------------------------------------

    async def start(self, daemon: Daemon) -> None:
        """Connect, load the shared state, hook into the daemon, take over orphaned missions."""
        self._daemon = daemon
        await self.state.connect()
        agents, missions = daemon.agents, daemon.missions
        agents.assign_cid = self.state.assign_cid
        missions.claim_release = self._claim_release
        missions.led_elsewhere = self._led_elsewhere
        missions.withdraw_elsewhere = self._withdraw_elsewhere
        missions.remote_blocker = self.remote_blocker
        self.state.on_change.append(self._registry_change)
        for identity, revision in list(self.state.revisions.items()):
            record = self.state.agent_record(identity)
            if record is not None:
                self._note_holder(identity, revision, str(record["daemon"]))
        for service in self._cooperation():
            service.cluster = self
        local_view = daemon.returns.fleet

        def fleet_view() -> dict[str, VehicleView]:
            """Returns deconflict against every airborne drone of the cluster, not only ours."""
            view = local_view()
            for identity, remote in list(daemon.agents.remote.items()):
                status = remote.status
                if remote.open and status is not None and status.position is not None:
                    view.setdefault(identity, VehicleView(status, status.position, remote.home))
            return view

        daemon.returns.fleet = fleet_view
        agents.on_join.append(self._local_join)
        agents.on_status.append(self._local_status)
        agents.on_sync.append(self._local_sync)
        agents.on_lost.append(self._local_lost)
        nc = self.state.nc
        assert nc is not None
        self._subs = [
            await nc.subscribe("fleet.status.>", cb=self._remote_status),
            await nc.subscribe("fleet.up.>", cb=self._remote_up),
            await nc.subscribe("fleet.down.>", cb=self._down),
            await nc.subscribe(f"fleet.cmd.{self.daemon_id}", cb=self._command),
            await nc.subscribe(f"fleet.result.{self.daemon_id}", cb=self._result),
        ]
        await self._lease_tick()
        self._tasks.append(asyncio.create_task(self._lease_loop(), name="cluster-leases"))
        self._tasks.append(asyncio.create_task(self._prune_loop(), name="cluster-prune"))

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        for sub in self._subs:
            with contextlib.suppress(Exception):
                await sub.unsubscribe()
        if self._daemon is not None:
            for mission_id in list(self._daemon.missions.active):
                await self.state.drop_lease(mission_id)  # a clean stop hands over at once
            if self._airspace:
                await self.state.drop_lease(AIRSPACE_LEASE)
        await self.state.close()

    def _cooperation(self) -> list[CooperationService]:
        return [s for s in self.daemon.services if isinstance(s, CooperationService)]

    # --- leases ----------------------------------------------------------------------------------

    async def _lease_loop(self) -> None:
        period = self.config.cluster_lease_ttl_s / 3
        while True:
            await asyncio.sleep(period)
            try:
                await self._lease_tick()
            except Exception:  # NATS briefly away (a node failing over): try again next period
                log.warning("lease round failed", exc_info=True)

    async def _lease_tick(self) -> None:
        await self._sweep_remote()
        holder, _ = await self.state.lease_holder(AIRSPACE_LEASE)
        was = self._airspace
        self._airspace = holder in (None, self.daemon_id) and await self.state.renew_lease(AIRSPACE_LEASE)
        if self._airspace != was:
            log.info("%s the airspace lease", "took" if self._airspace else "lost")
        missions = self.daemon.missions
        for mission_id in list(missions.active):
            if not await self.state.renew_lease(mission_id):
                holder, _ = await self.state.lease_holder(mission_id)
                log.warning("lost the lead of %s to %s; following", mission_id, holder)
                missions.forget(mission_id)
        finished = {m.id for m in self.store.missions() if m.state != "running"}
        for mission_id in finished & set(self._held_leases):
            await self.state.drop_lease(mission_id)
            self._held_leases.discard(mission_id)
        for stored in self.store.missions("running"):
            if stored.id in missions.active:
                self._held_leases.add(stored.id)
                continue
            holder, _ = await self.state.lease_holder(stored.id)
            if holder is None and await self.state.take_lease(stored.id):
                await self._take_over(stored.id)

    async def _sweep_remote(self) -> None:
        """Mirrors of agents nobody has reported for ``lost_after_s`` (their daemon died) go."""
        now = time.monotonic()
        agents = self.daemon.agents
        for identity, remote in list(agents.remote.items()):
            if now - remote.last_rx > self.config.lost_after_s:
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
            if not self._airspace:
                continue
            try:
                self.pruned_keys += await prune_round(self.state, after)
            except Exception:  # NATS away: the next round goes on where this one stopped
                log.warning("prune round failed", exc_info=True)

    async def _take_over(self, mission_id: str) -> None:
        missions = self.daemon.missions
        await self.state.resync()  # the freshest shared records, whatever our watchers missed
        mission = missions.restore_one(mission_id)
        if mission is None:
            return
        self._held_leases.add(mission_id)
        self.takeovers.append((mission_id, time.time()))
        missions.count_arrivals(mission_id, self.store.arrivals(mission_id))
        self.daemon.events.publish(
            "mission_takeover",
            f"{self.daemon_id} leads {mission.task.name} now (previous leader's lease expired)",
            mission_id=mission_id,
        )
        await missions.release_ready(mission_id)
        for identity in missions.members(mission):  # heal what died in flight
            session = self.daemon.agents.session(identity)
            if session is not None and session.status is not None:
                await self._nudge(session, session.status)

    async def _claim_release(self, mission_id: str, step: int) -> bool:
        return await self.state.create("barriers", f"{mission_id}.{step}.released", self.state.unique())

    def _led_elsewhere(self, mission_id: str) -> bool:
        stored = self.store.mission(mission_id)
        return stored is not None and mission_id not in self.daemon.missions.active

    async def _withdraw_elsewhere(self, identity: str, reason: str) -> None:
        """One of our agents leaves its mission (an operator RTL, an emergency) but another daemon
        leads that mission: tell it, so its barriers stop waiting for the agent."""
        session = self.daemon.agents.sessions.get(identity)
        if session is not None and session.open:
            self._up(session, "withdraw", reason.encode()[:500])

    # --- the cooperation service's view of the cluster (gcs.cooperation.service.ClusterView) -----

    def airspace(self) -> Airspace:
        """Whose collisions we decide: the whole fleet (we hold the airspace lease), only our own
        agents (cut off from NATS: nobody else can reach them), or none (another daemon does)."""
        nc = self.state.nc
        if nc is None or not nc.is_connected:
            return "local"
        return "fleet" if self._airspace else "none"

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
        self.state.enqueue(lambda: nc.publish(f"fleet.up.{session.identity}", payload, headers=headers))

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
                await nc.publish(f"fleet.status.{session.identity}", _frame(status), headers=headers)
        await self._nudge(session, status)

    async def _local_sync(self, session: AgentSession, signal: SyncSignal) -> None:
        key = f"{signal.mission_id}.{signal.step}.arrived.{session.identity}"
        if key not in self.state.mirror["barriers"]:
            self.state.mirror["barriers"][key] = b"1"
            value = self.state.unique()
            self.state.enqueue(lambda: self.state.create("barriers", key, value))
        self._up(session, "sync", _frame(signal))

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
        status = _body(msg.data)
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
        from gcs.live import LiveHub

        for hub in self.daemon.services:  # the dashboard's stream and history show the whole fleet
            if isinstance(hub, LiveHub):
                await hub.remote_status(remote, status)
        for service in self._cooperation():  # the airspace picture spans the cluster
            await service.remote_status(remote, status)
        await self.daemon.missions.agent_status(remote, status)
        await self._nudge(remote, status)

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
            signal = _body(msg.data)
            if isinstance(signal, SyncSignal):
                await missions.agent_finished(remote, signal)
        elif kind == "lost":
            await self._remote_gone(remote.identity, remote)
        elif kind == "withdraw":  # its daemon took it out of a mission (we may lead it)
            await missions.withdraw(remote.identity, msg.data.decode(errors="replace"))

    async def _nudge(self, session: AgentSession, status: StatusReport) -> None:
        """As leader: an agent reporting a wait at a released barrier gets the release again, one
        waiting at a barrier we have no arrival for counts as arrived (the signal died in flight)."""
        step, mission_id = status.waiting_sync, status.mission_id
        if step is None or mission_id is None:
            return
        mission = self.daemon.missions.active.get(mission_id)
        if mission is None or session.identity not in mission.barriers.members:
            return
        released = step in mission.barriers.released
        if not released and session.identity in mission.barriers.arrivals.get(step, set()):
            return
        key = (session.identity, mission_id, step)
        now = time.monotonic()
        if now - self._nudged.get(key, 0.0) < NUDGE_EVERY_S:
            return
        self._nudged[key] = now
        if released:
            session.post(SyncSignal(mission_id=mission_id, step=step, kind="release"))
        else:
            signal = SyncSignal(mission_id=mission_id, step=step, kind="finished")
            await self.daemon.missions.agent_finished(session, signal)

    # --- what other daemons send our agents ---------------------------------------------------------

    def forward(self, identity: str, body: Body, urgent: bool) -> None:
        """Post ``body`` through the daemon holding the link; a command's answer (delivered or
        refused by that daemon's vehicle authority) comes back on ``fleet.result.<us>``."""
        nc = self.state.nc
        if nc is None or nc.is_closed:
            return
        data, headers = _frame(body), {"daemon": self.daemon_id, "urgent": "1" if urgent else ""}
        reply = ""
        if isinstance(body, PerformActions):
            self._seq += 1
            headers["seq"] = str(self._seq)
            reply = f"fleet.result.{self.daemon_id}"
            self._remember(self._seq, identity, f"{body.source or 'mission'} {body.mode}")
        self.state.enqueue(lambda: nc.publish(f"fleet.down.{identity}", data, reply=reply, headers=headers))

    def _remember(self, seq: int, identity: str, command: str) -> None:
        now = time.monotonic()
        self._pending[seq] = (identity, command, now)
        if len(self._pending) > PENDING_LIMIT or next(iter(self._pending.values()))[2] < now - PENDING_TTL_S:
            for old in [k for k, (_, _, at) in self._pending.items() if at < now - PENDING_TTL_S]:
                del self._pending[old]
            while len(self._pending) > PENDING_LIMIT:
                del self._pending[next(iter(self._pending))]

    async def _down(self, msg: Msg) -> None:
        identity = msg.subject.split(".", 2)[2]
        session = self.daemon.agents.sessions.get(identity)
        if session is None or not session.open or (msg.headers or {}).get("daemon") == self.daemon_id:
            return
        body = _body(msg.data)
        if isinstance(body, PerformActions):
            delivered, why = self._order(identity, body, (msg.headers or {}).get("daemon", "?"))
            if msg.reply:
                answer = {
                    "agent": identity,
                    "seq": (msg.headers or {}).get("seq", ""),
                    "daemon": self.daemon_id,
                    "delivered": delivered,
                    "reason": why,
                    "level": self.daemon.authority.level(identity),
                }
                with contextlib.suppress(Exception):
                    await msg.respond(json.dumps(answer).encode())
        elif body is not None:
            session.post(body, urgent=bool((msg.headers or {}).get("urgent")) or None)

    def _order(self, identity: str, body: PerformActions, sender: str) -> tuple[bool, str]:
        """A command another daemon gave our agent: through our vehicle authority, at its source's
        priority, so nothing undoes what our operator or the vehicle ordered (refusals recorded
        here and answered to the sender)."""
        authority = self.daemon.authority
        owner = body.source or "mission"
        reason = f"{body.reason or body.mode} (via {sender})"
        planned = PRIORITY[owner] <= PRIORITY["mission"]
        if body.mode == "pause":
            if planned:  # a plan-level pause re-sends the sender's holds: ours re-sends our own
                return True, "plan pause: our own holds stand"
            return authority.hold(identity, owner, reason, body.mission_id)
        if body.mode == "resume":
            return authority.release(identity, owner, reason, body.mission_id)
        if body.mode == "replace":
            return authority.replace(
                identity,
                owner,
                body.mission_id,
                list(body.actions),
                reason,
                order=_order_kind(owner, body.mission_id),
                await_release=body.await_release,
                keep_holds=planned,  # a plan queues behind any hold, as the leader's did
            )
        return self.daemon.agents.post(identity, body), body.mode

    async def _result(self, msg: Msg) -> None:
        """The holder's answer to a command we forwarded: a refusal is recorded (event, the
        drone's level raised so the airspace decider treats it as outranked right away)."""
        try:
            answer = json.loads(msg.data)
            identity, delivered = str(answer["agent"]), bool(answer["delivered"])
            seq, holder, why = int(answer.get("seq") or 0), str(answer["daemon"]), str(answer["reason"])
            level = int(answer.get("level", 0))
        except (ValueError, KeyError, TypeError):
            log.warning("bad command answer on %s: %r", msg.subject, msg.data[:200])
            return
        _, command, _ = self._pending.pop(seq, (identity, "command", 0.0))
        if delivered:
            return
        remote = self.daemon.agents.remote.get(identity)
        if isinstance(remote, RemoteSession) and remote.daemon == holder:
            remote.level = max(remote.level, level)
        source, _, mode = command.partition(" ")
        if mode == "resume" or source not in PRIORITY:
            return  # nothing of ours to release there: not a refusal worth recording
        self.refusals.append({"agent": identity, "daemon": holder, "command": command, "reason": why})
        # Our authority takes back what it recorded as given; its decision event says who refused
        # and why (throttled per drone, source and command like every decision event).
        self.daemon.authority.refused_where_linked(identity, source, mode, holder, why)

    # --- operator commands for any drone --------------------------------------------------------------

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
        """Run an operator command on each drone's own daemon (through its vehicle authority);
        returns (delivered, refused: drone -> why, as that daemon answered)."""
        targets = agents if agents is not None else sorted(self.fleet_identities())
        by_daemon: dict[str, list[str]] = {}
        refused: dict[str, str] = {}
        for identity in targets:
            holder = self.holder(identity)
            if holder is None:
                refused[identity] = "no daemon of the cluster holds its link"
            else:
                by_daemon.setdefault(holder, []).append(identity)
        delivered: list[str] = []
        for daemon, group in sorted(by_daemon.items()):
            if daemon == self.daemon_id:
                done, why = await self._apply(command, group, reason)
                delivered += done
                refused.update(why)
                continue
            nc = self.state.nc
            assert nc is not None
            request = json.dumps({"command": command, "agents": group, "reason": reason}).encode()
            try:
                reply = await nc.request(f"fleet.cmd.{daemon}", request, timeout=COMMAND_TIMEOUT_S)
                answer = json.loads(reply.data)
            except Exception as exc:
                log.warning("daemon %s did not answer %s for %s: %r", daemon, command, group, exc)
                late = f"{daemon} did not answer within {COMMAND_TIMEOUT_S:.0f} s"
                refused.update(dict.fromkeys(group, late))
                continue
            delivered += answer.get("delivered", [])
            refused.update(answer.get("refused", {}))
            if answer.get("error"):
                refused.update({i: f"{daemon}: {answer['error']}" for i in group if i not in delivered})
        return delivered, refused

    async def _apply(self, command: str, agents: list[str], reason: str) -> tuple[list[str], dict[str, str]]:
        operator = self.daemon.operator
        if command == "hold":
            delivered = await operator.hold(agents, reason)
        elif command == "resume":
            delivered = await operator.resume(agents, reason)
        elif command in ("rtl", "land"):
            missions = self.daemon.missions
            for identity in agents:  # out of a mission another daemon leads (that one is told)
                if missions.mission_of(identity) is None:
                    await missions.withdraw(identity, f"fleet {command} ({reason})")
            delivered, _ = await operator.bring_down(command, agents, reason)  # type: ignore[arg-type]
        else:
            raise ValueError(f"unknown command {command!r}")
        return delivered, {i: self._why_not(i, command) for i in agents if i not in delivered}

    def _why_not(self, identity: str, command: str) -> str:
        """Why ``command`` did not reach a drone linked here (for the cluster API's answer)."""
        session = self.daemon.agents.sessions.get(identity)
        if session is None or not session.open:
            return f"not linked to {self.daemon_id} any more"
        decisions = self.daemon.authority.control(identity).decisions
        last = decisions[-1] if decisions else None
        if last is not None and not last.accepted and last.source == "operator":
            return f"refused by {self.daemon_id}'s vehicle authority: {last.detail}"
        if command in ("rtl", "land"):
            return "not airborne: nothing to bring down"
        if command == "resume":
            return "still held by the operator"
        return f"not applied by {self.daemon_id}"

    async def _command(self, msg: Msg) -> None:
        try:
            request = json.loads(msg.data)
            delivered, refused = await self._apply(
                request["command"], list(request["agents"]), request["reason"]
            )
            answer: dict[str, Any] = {"delivered": delivered, "refused": refused}
        except Exception as exc:  # a bad request costs its reply, never the subscription
            answer = {"delivered": [], "error": str(exc)}
        await msg.respond(json.dumps(answer).encode())

    # --- the whole fleet ---------------------------------------------------------------------------------

    def fleet_identities(self) -> set[str]:
        agents = self.daemon.agents
        return {s.identity for s in agents.connected()} | {i for i, s in agents.remote.items() if s.open}

    def fleet(self) -> list[dict[str, Any]]:
        """Every agent the cluster knows: where its link is, and its last status."""
        agents = self.daemon.agents
        rows = []
        now = time.monotonic()
        for identity, record in sorted(self.state.json_values("agents").items()):
            local = agents.sessions.get(identity)
            session = local if local is not None and local.open else agents.remote.get(identity)
            live = session is not None and session.open and now - session.last_rx < self.config.lost_after_s
            rows.append(
                {
                    "identity": identity,
                    "cid": record["cid"],
                    "daemon": self.holder(identity),
                    "local": session is local and local is not None,
                    "connected": live,
                    "status": session.status.model_dump(mode="json") if session and session.status else None,
                }
            )
        return rows

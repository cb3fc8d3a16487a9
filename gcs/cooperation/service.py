"""The cooperation service: feeds the monitors the fleet picture and applies what they decide.

I/O lives here and only here. The monitors (collision, emergency, divergence, connectivity) are
pure and return intents; this service applies them through the vehicle authority
(:mod:`gcs.control.authority`), which refuses anything a higher-priority source has overridden, and
publishes their events through a throttle so a persistent condition cannot bury the log. A
ticker re-asserts holds (seed 000: "for safety reasons ... sent periodically"), runs the
fleet-wide checks when reports are scarce and catches drones whose status stopped arriving.

Per status tick the reports go into the fleet's arrays (gcs/cooperation/fleet.py) in one
vectorised pass, with the battery estimators; column compares flag the reports the per-agent
checks (tracking, emergency and divergence edges) may act on (the gate, gcs/cooperation/tick_gate.py),
and only those are built into a ``StatusReport`` and checked, each agent's intents applied before
the next's. The fleet-wide
checks (collision, connectivity: O(fleet) each) run on their own fixed tick of
``collision.min_check_interval_s`` when a report has arrived since the last one, never inside
the status consumer, so their cost does not grow with the report rate.

In a cluster (docs/cluster.md) the node feeds in the drones linked to other daemons
(:meth:`CooperationService.remote_status`) and says who decides the airspace
(gcs/cooperation/airspace.py, :class:`ClusterView`): one daemon at a time runs the collision
check over the whole fleet; its orders for a drone linked elsewhere go out through that daemon's
vehicle authority. The
per-agent checks (emergency, divergence) and connectivity (to this base station) stay with the
daemon holding the drone's link.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import Any

import numpy as np

from gcs.cooperation.airspace import ClusterAirspace, ClusterView
from gcs.cooperation.collision_monitor import CollisionMonitor
from gcs.cooperation.config import CooperationConfig
from gcs.cooperation.connectivity_monitor import ConnectivityMonitor
from gcs.cooperation.divergence import DivergenceJudge
from gcs.cooperation.divergence_monitor import DivergenceMonitor
from gcs.cooperation.emergency_monitor import EmergencyMonitor
from gcs.cooperation.energy import EnergyModel, fallback_model
from gcs.cooperation.energy_logs import EnergyLogRecorder
from gcs.cooperation.event_throttle import EventThrottle
from gcs.cooperation.fleet import Fleet
from gcs.cooperation.intents import (
    EndOrderIntent,
    EventIntent,
    HoldIntent,
    Intent,
    ReleaseIntent,
    ReplaceIntent,
    ReturnIntent,
)
from gcs.cooperation.legs import agent_acceptance_radius
from gcs.cooperation.preflight import PreflightChecks, start_points
from gcs.cooperation.tick_gate import TickGate, sticky
from gcs.cooperation.tracking import Kinematics, TrackedAgent, track
from gcs.core.context import ServiceContext
from gcs.link.agents_table import StatusTick
from gcs.link.session import AgentSession
from gcs.link.status_bus import Subscriptions
from gcs.observe.events import Severity
from gcs.planning.geodesy import LocalFrame
from protocol.actions import Action
from protocol.packets import AgentParameters, Resume, StatusReport
from protocol.status_binary import BUFFERED, HAS_POSITION

log = logging.getLogger("gcs.cooperation")

EMERGENCY_MISSION = "cooperation-emergency"
FLEET_CHECK_DUTY = 4.0  # the fleet-check tick is at least this many times one check's duration
LOST_LINK_ACTION = {"event": "continue", "hold": "hold", "return": "rtl", "rtl": "rtl"}
STALL_S = 1.0  # the ticker woke this much late: we were paused or starved, the drones were not silent


class CooperationService:
    """Collision avoidance, divergence, connectivity, emergency monitor and energy checks."""

    name = "cooperation"

    def __init__(self, config: CooperationConfig, cluster: ClusterView | None = None) -> None:
        self.config = config
        scale = config.vehicle_time_scale
        self.collision = CollisionMonitor(config.collision)
        self.emergency = EmergencyMonitor(config.emergency, scale)
        self.divergence = DivergenceMonitor(config.divergence, scale)
        self.connectivity = ConnectivityMonitor(config.connectivity)
        self.recorder = EnergyLogRecorder(config.energy)
        self.agents: dict[str, TrackedAgent] = {}
        self.fleet = Fleet(config.emergency, config.divergence, scale)  # the agents' newest reports as arrays
        self.built = 0  # reports built for the per-agent checks (the rest only went into the arrays)
        self.energy_model: EnergyModel = fallback_model(config.energy.fallback_power_w)
        self.frame: LocalFrame | None = None
        self.base: tuple[float, float] | None = config.connectivity.base
        self._ctx: ServiceContext | None = None
        self._throttle: EventThrottle | None = None
        self._preflight: PreflightChecks | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._subscriptions: Subscriptions | None = None  # its hooks on the status bus, from start()
        self._fleet_due = False  # a report arrived since the last fleet-wide check
        self.cluster = cluster  # the cluster node, plugged in by the daemon (docs/cluster.md)
        self.remote: set[str] = set()  # tracked drones linked to other daemons
        self.airspace = ClusterAirspace(cluster, self.collision, self.agents, self.remote, lambda: self.ctx)
        self.gate = TickGate(config, self.fleet, self.agents, self.remote, self._adopt, lambda: self.ctx)
        self.fleet_check_s = 0.0  # how long the last fleet-wide check took (loop time)

    # --- lifecycle ------------------------------------------------------------------------------

    async def start(self, ctx: ServiceContext) -> None:
        self._ctx = ctx
        self._throttle = EventThrottle(self._publish)
        self._preflight = PreflightChecks(
            self.config,
            ctx.agents.session,
            ctx.events,
            self._link_range,
            lambda: self.base,
            lambda: self.energy_model,
        )
        self._subscriptions = subscriptions = ctx.agents.subscriptions()  # ended together in stop()
        subscriptions.subscribe("tick", self._on_tick)
        subscriptions.subscribe("join", self._on_join)
        subscriptions.subscribe("lost", self._on_lost)
        ctx.missions.preflight_checks.append(self._preflight)
        if self.config.energy.model_path is not None:
            self.energy_model = EnergyModel.load(self.config.energy.model_path)
        self._tasks = [
            asyncio.create_task(self._ticker(), name="cooperation-ticker"),
            asyncio.create_task(self._fleet_ticker(), name="cooperation-fleet-checks"),
        ]

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        if self._tasks:  # bounded: a cancel swallowed somewhere must not hang the daemon's stop
            await asyncio.wait(self._tasks, timeout=2.0)
        self._tasks = []
        if self._subscriptions is not None:
            self._subscriptions.close()
        ctx = self._ctx
        if ctx is not None and self._preflight is not None:
            with contextlib.suppress(ValueError):
                ctx.missions.preflight_checks.remove(self._preflight)
        for agent in self.agents.values():
            if agent.recorder is not None:
                agent.recorder.close()

    @property
    def ctx(self) -> ServiceContext:
        assert self._ctx is not None, "service not started"
        return self._ctx

    def predict_energy(
        self, plans: dict[str, list[Action]], homes: dict[str, tuple[float, float, float]]
    ) -> dict[str, tuple[float, float, float]]:
        """Per agent: (plan time s, plan distance m, predicted Wh)."""
        assert self._preflight is not None, "service not started"
        return self._preflight.predict_energy(plans, homes)

    # --- applying intents -----------------------------------------------------------------------

    def _publish(
        self, kind: str, message: str, severity: str, agent: str | None, data: dict[str, Any]
    ) -> None:
        mission = self.agents[agent].state.mission_id if agent in self.agents else None
        level: Severity = "error" if severity == "error" else "warning" if severity == "warning" else "info"
        self.ctx.events.publish(kind, message, severity=level, agent=agent, mission_id=mission, data=data)

    def _mission_id(self, ident: str) -> str:
        agent = self.agents.get(ident)
        status = agent.state if agent else None
        return status.mission_id if status is not None and status.mission_id else EMERGENCY_MISSION

    async def apply(self, intents: list[Intent]) -> None:
        """Hand each intent to the authority (which may refuse it) or to the event log."""
        authority = self.ctx.authority
        for intent in intents:
            target = self.agents.get(getattr(intent, "ident", None) or "")
            if target is not None:
                self.fleet.stick(target)
            if isinstance(intent, EventIntent):
                assert self._throttle is not None
                self._throttle.publish(
                    intent.kind, intent.message, intent.severity, intent.agent, intent.data
                )
            elif isinstance(intent, HoldIntent):
                authority.hold(intent.ident, intent.owner, intent.reason, self._mission_id(intent.ident))
            elif isinstance(intent, ReleaseIntent):
                authority.release(intent.ident, intent.owner, intent.reason, self._mission_id(intent.ident))
            elif isinstance(intent, ReplaceIntent):
                ok, _ = authority.replace(
                    intent.ident, intent.owner, self._mission_id(intent.ident), intent.actions, intent.reason
                )
                if not ok and intent.owner == "collision":
                    self.collision.avoider.escaping.pop(intent.ident, None)
            elif isinstance(intent, EndOrderIntent):
                authority.end_order(intent.ident, intent.owner, intent.reason)
            elif isinstance(intent, ReturnIntent):
                await self._return(intent)

    async def _return(self, intent: ReturnIntent) -> None:
        """The bring-down use case (gcs/control/bring_down.py) at the intent's priority: refused (and
        recorded) if outranked; else the collision picture forgets the drone, it leaves its
        mission (so its landing does not finish it) and starts its return."""
        await self.ctx.bring_down(
            [intent.ident],
            intent.action,
            intent.owner,
            intent.reason,
            on_allowed=self.collision.forget,
        )

    # --- hooks ----------------------------------------------------------------------------------

    async def _on_join(self, session: AgentSession, resume: Resume | None) -> None:
        if self.base is None and session.home is not None:
            self.base = (session.home.lat, session.home.lon)
        cfg = self.config.connectivity
        w = self._link_range()
        if cfg.enabled and cfg.push_lost_link_action and w is not None:
            parameters = AgentParameters(link_range_m=w, lost_link_action=LOST_LINK_ACTION[cfg.policy])  # type: ignore[arg-type]
            self.ctx.commands.set_parameters(parameters, [session.identity])

    async def _on_lost(self, identity: str) -> None:
        if self.cluster is not None:
            session = self.ctx.agents.session(identity)
            if session is not None and session.open:  # lost here, but linked to another daemon now
                self.remote.add(identity)
                if self.cluster.airspace() != "fleet":  # its collision holds are the decider's
                    self.ctx.authority.drop_holds(identity, ("collision",), "linked to another daemon")
                return
        self.remote.discard(identity)
        agent = self.agents.pop(identity, None)
        if agent is not None:
            self.fleet.release(agent)
            if agent.recorder is not None:
                agent.recorder.close()
        self.collision.forget(identity)
        self.ctx.authority.drop_holds(identity, ("collision",), "agent lost")

    async def remote_status(self, session: AgentSession, status: StatusReport) -> None:
        """Cluster: a drone linked to another daemon reported; it joins the airspace picture only
        (its own daemon runs its per-agent checks)."""
        if status.buffered or status.position is None:
            return
        self.remote.add(session.identity)
        try:
            self._track(session, status, time.monotonic(), local=False, row=False)
            self._fleet_due = True
        except Exception:
            log.exception("cooperation: remote status failed for %s", session.identity)

    async def remote_lost(self, identity: str) -> None:
        """Cluster: a drone linked to another daemon left the picture (lost, or its daemon died)."""
        if identity in self.remote:
            await self._on_lost(identity)

    def _adopt(self, session: AgentSession, status: StatusReport, now: float, local: bool) -> TrackedAgent:
        """The agent's picture, made (with a fleet slot) on its first positioned report."""
        ident = session.identity
        agent = self.agents.get(ident)
        if agent is not None:
            return agent
        position = status.position
        assert position is not None
        agent = TrackedAgent(ident, session.cid, session.home, status, position, now)
        self.agents[ident] = agent
        self.fleet.attach(agent, session)
        if self.frame is None:
            self.frame = LocalFrame(position.lat, position.lon)
        if self.base is None and local:  # this base station: where our own agents start
            home = session.home
            self.base = (home.lat, home.lon) if home else (position.lat, position.lon)
        return agent

    def _track(
        self, session: AgentSession, status: StatusReport, now: float, local: bool = True, row: bool = True
    ) -> TrackedAgent:
        """Update the agent's picture (position, plan position) from a positioned report
        (``row``: the status tick wrote the report's row into the fleet's arrays already)."""
        agent = self._adopt(session, status, now, local)
        fleet, slot = self.fleet, agent.slot
        if not row:
            fleet.put_report(slot, status, now)
        fleet.link(slot, session)
        agent.seen(status, now)
        ident = session.identity
        agent.connected = session.open
        if session.home is not None and agent.home is not session.home:
            agent.home = session.home
            fleet.home[slot] = (session.home.lat, session.home.lon)
        track(
            agent,
            status,
            self._plan_of(ident, status),
            agent_acceptance_radius(
                self.ctx.config.agent_parameters.acceptance_radius_m,
                self.config.divergence.acceptance_radius_m,
            ),
            self._new_judge,
        )
        return agent

    async def _on_tick(self, tick: StatusTick) -> None:
        """A status tick: the positioned live rows (picked on the columns) go into the fleet's
        arrays; the rows a gate flags (:meth:`_gate`) are built into reports and checked, each
        agent's intents applied before the next agent's checks, as per report before."""
        flags = tick.cols["flags"]
        rows = np.flatnonzero(((flags & HAS_POSITION) != 0) & ((flags & BUFFERED) == 0))
        if not len(rows):
            return
        self._fleet_due = True
        now = time.monotonic()
        try:
            flagged = self._gate(tick, rows, now)
        except Exception:  # a bug here must not cost the agents their checks: every row is checked
            log.exception("cooperation: status tick gate failed")
            flagged = rows.tolist()
        owners = tick.owners  # a tick slice (gcs/link/status_tick.py TICK_SLICE): no yield needed in here
        for i in flagged:
            session = owners[i]
            self.built += 1
            intents = self._checks(session, tick.report(i), now)
            if intents:
                try:
                    await self.apply(intents)
                except Exception:  # a bug here must not cost the agent its connection
                    log.exception("cooperation: status handling failed for %s", session.identity)

    def _gate(self, tick: StatusTick, rows: np.ndarray[Any, np.dtype[np.intp]], now: float) -> list[int]:
        """The rows of ``rows`` the per-agent checks must see, the rest only fed into the fleet's
        arrays (gcs/cooperation/tick_gate.py)."""
        return self.gate.flag(tick, rows, now)

    def _checks(self, session: AgentSession, status: StatusReport, now: float) -> list[Intent]:
        """Track one positioned live report and run the per-report checks; the intents to apply."""
        ident = session.identity
        self.remote.discard(ident)  # linked here (again)
        intents: list[Intent] = []
        try:
            agent = self._track(session, status, now)
            self._record(agent, status)
            if self.config.emergency.enabled:
                intents += self.emergency.on_status(agent, status, self.ctx.geofences.get(ident), now)
            if self.config.divergence.enabled:
                busy = self.ctx.authority.is_held(ident) or self._outranked(ident, "divergence")
                intents += self.divergence.on_status(agent, status, busy, now)
            self.fleet.settle(agent, sticky(agent, status))
        except Exception:  # a bug here must not cost the agent its connection
            log.exception("cooperation: status handling failed for %s", ident)
        return intents

    def _new_judge(self) -> DivergenceJudge:
        return DivergenceJudge(self.config.divergence)

    def _plan_of(self, ident: str, status: StatusReport) -> tuple[str, list[Action]] | None:
        """The running mission's plan for the drone (led here or, in a cluster, elsewhere)."""
        if not status.mission_id:
            return None
        actions = self.ctx.missions.plan_of(status.mission_id, ident)
        return None if actions is None else (status.mission_id, actions)

    def _record(self, agent: TrackedAgent, status: StatusReport) -> None:
        if self.config.energy.record_dir is None:
            return
        mission = self.ctx.missions.active.get(status.mission_id) if status.mission_id else None
        plans = (mission.id, mission.plans) if mission else None
        homes = start_points(mission.plans, self.ctx.agents.session) if mission else {}
        self.recorder.record(agent, status, plans, homes)

    # --- fleet-wide checks ----------------------------------------------------------------------

    def _outranked(self, ident: str, owner: str) -> bool:
        return self.airspace.outranked(ident, owner)

    def _stale_limit(self) -> float:
        cfg = self.config.emergency
        return max(cfg.stale_after_periods * self.ctx.config.status_period_s, cfg.stale_min_s)

    def _fresh(self, now: float) -> list[TrackedAgent]:
        limit = self._stale_limit()
        received = self.fleet.received.tolist()
        return [a for a in self.agents.values() if a.connected and now - received[a.slot] <= limit]

    def _kinematics(self, agents: list[TrackedAgent]) -> Kinematics:
        """The agents' newest positions and velocities, read from the fleet's arrays."""
        return Kinematics.of(self.fleet.cols[[a.slot for a in agents]])

    def _collision_pass(self, fresh: list[TrackedAgent], now: float) -> list[Intent]:
        """One fleet-wide collision check; drones under a higher source's control never yield."""
        assert self.frame is not None
        outranked = lambda i: self._outranked(i, "collision")  # noqa: E731
        return self.collision.check(fresh, self._kinematics(fresh), self.frame, outranked, now)

    def _collision_scope(self, now: float) -> list[TrackedAgent]:
        """The fresh drones this daemon's collision check decides for (gcs/cooperation/airspace.py)."""
        return self.airspace.scope(self._fresh(now), now)

    def _fleet_checks(self, now: float) -> list[Intent]:
        intents: list[Intent] = []
        if self.frame is None:
            return intents
        fresh = self._fresh(now)
        if self.config.collision.enabled:
            intents += self._collision_pass(self._collision_scope(now), now)
        w = self._link_range()
        if self.config.connectivity.enabled and w is not None and self.base is not None:
            own = [a for a in fresh if a.ident not in self.remote]  # links to this base station
            intents += self.connectivity.check(own, self._kinematics(own), self.frame, self.base, w, now)
        return intents

    def _link_range(self) -> float | None:
        cfg = self.config.connectivity
        if cfg.link_range_m is not None:
            return cfg.link_range_m
        return self._ctx.config.agent_parameters.link_range_m if self._ctx else None

    async def _fleet_ticker(self) -> None:
        """The fleet-wide checks on a fixed tick, over the latest picture of every agent.

        The tick is ``min_check_interval_s``, stretched to ``FLEET_CHECK_DUTY`` times the last
        check's own duration when a very large fleet makes one pass long: the checks never take
        more than a quarter of the event loop, whatever the fleet size.
        """
        base = max(0.01, self.config.collision.min_check_interval_s)
        period = base
        while True:
            await asyncio.sleep(period)
            if not self._fleet_due:
                continue
            self._fleet_due = False
            started = time.monotonic()
            try:
                await self.apply(self._fleet_checks(started))
            except Exception:  # a bug here must not end the checks
                log.exception("cooperation: fleet-wide check failed")
            self.fleet_check_s = time.monotonic() - started
            period = max(base, FLEET_CHECK_DUTY * self.fleet_check_s)

    async def _ticker(self) -> None:
        """Re-assert holds periodically, run checks between reports, catch drones whose reports stopped."""
        last_reassert = time.monotonic()
        while True:
            period = min(self.config.emergency.check_period_s, self.config.collision.reassert_period_s)
            asked = time.monotonic() + period
            await asyncio.sleep(period)
            now = time.monotonic()
            stalled = now - asked > STALL_S  # reports waited unread: judge silence next pass
            try:
                if now - last_reassert >= self.config.collision.reassert_period_s:
                    last_reassert = now
                    for ident in [i for i in self.agents if i not in self.remote]:
                        if self.ctx.authority.is_held(ident) and self.ctx.agents.session(ident) is not None:
                            self.ctx.authority.reassert(ident)
                intents: list[Intent] = []
                if self.config.emergency.enabled and not stalled:
                    intents += self.emergency.stale(list(self.agents.values()), self._stale_limit(), now)
                if self.config.collision.enabled and self.frame is not None and self.collision.avoider.holds:
                    intents += self._collision_pass(self._collision_scope(now), now)
                await self.apply(intents)
            except Exception:
                log.exception("cooperation ticker failed")

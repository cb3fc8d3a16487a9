"""The cooperation service's gate: which rows of a status tick the per-agent checks must see.

Why apart from the service: this is the vectorised half of a status tick (docs/cooperation.md).
Every positioned live row goes into the fleet's arrays (gcs/cooperation/fleet.py) and the
battery estimators in one pass; column compares then flag the few reports the per-agent checks
(tracking, emergency and divergence edges) may act on, and only those are built into a
``StatusReport``. The service (gcs/cooperation/service.py) runs the checks and applies intents.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from gcs.cooperation.config import CooperationConfig
from gcs.cooperation.fleet import Fleet
from gcs.cooperation.tracking import TrackedAgent
from gcs.core.context import ServiceContext
from gcs.link.agents_table import StatusTick
from gcs.link.session import AgentSession
from protocol.actions import Waypoints
from protocol.packets import Geofence, StatusReport

Adopt = Callable[[AgentSession, StatusReport, float, bool], TrackedAgent]


def carries_more(report: StatusReport | None) -> bool:
    """A report that came decoded with fields the columns do not hold (exceptions, a failsafe)."""
    return report is not None and bool(report.exceptions or report.failsafe or report.failure)


def sticky(agent: TrackedAgent, status: StatusReport) -> bool:
    """Must every report of the agent go to the per-agent checks? While its mission's plan is
    not known here yet, it flies a detour or a waypoints action (the plan position follows each
    report), a divergence error is being timed or a condition is pending or in force (its edge
    must see it clear), or it is marked disconnected."""
    plan, judge = agent.plan, agent.judge
    return (
        (status.mission_id is not None and plan is None)  # its plan may turn up
        or not agent.connected
        or agent.detour_step is not None
        or (plan is not None and isinstance(plan.current_action, Waypoints))  # (waypoint by position)
        or (judge is not None and judge.persisting)
        or any(name in agent.conditions for name in ("fence", "battery", "gps"))
    )


class TickGate:
    """Feeds a tick's rows into the fleet's arrays and flags the ones the per-agent checks need."""

    def __init__(
        self,
        config: CooperationConfig,
        fleet: Fleet,
        agents: Mapping[str, TrackedAgent],
        remote: set[str],
        adopt: Adopt,
        ctx: Callable[[], ServiceContext],
    ) -> None:
        self.config = config
        self._fleet = fleet
        self._agents = agents  # the service's tracked agents (by identity)
        self._remote = remote  # the service's drones linked to other daemons (always checked)
        self._adopt = adopt  # a new agent's picture, made with its fleet slot
        self._ctx = ctx  # the service's context (geofences, mission plans), once started

    def flag(self, tick: StatusTick, rows: np.ndarray[Any, np.dtype[np.intp]], now: float) -> list[int]:
        """Write the tick's ``rows`` into the fleet's arrays (and battery estimators); the rows whose
        report the per-agent checks must see: a new or relinked agent, a report that came decoded
        with exceptions or a failsafe (not in the columns), a fence to check, a changed state, a sticky slot
        (mission, condition in force), or a column gate (``Fleet.gate``)."""
        owners, fleet, ctx = tick.owners, self._fleet, self._ctx()
        picked = [owners[i] for i in rows.tolist()]
        known = fleet.by_session.get
        slots = np.array([known(session, -1) for session in picked], dtype=np.intp)
        forced = slots < 0  # new agent, or a new session of a known one
        if not all([session.open for session in picked]):
            forced |= ~np.array([session.open for session in picked], dtype=bool)
        built = tick.built()
        if built:
            more = {i for i in built if carries_more(tick.decoded(i))}
            forced |= np.isin(rows, list(more))
        remote = self._remote
        if remote:
            forced |= np.array([s.identity in remote for s in picked], dtype=bool)
        for k in np.flatnonzero(slots < 0).tolist():
            session = picked[k]
            agent = self._agents.get(session.identity)
            if agent is None:
                agent = self._adopt(session, tick.report(rows[k]), now, True)
            slots[k] = agent.slot
        raw, cols = tick.whole_rows(rows)  # whole rows: mode, mission too
        flag = fleet.write(slots, raw, now)
        flag |= forced | fleet.sticky[slots]
        if self.config.emergency.enabled:
            fleet.feed_battery(slots, cols)
            flag |= fleet.gate(slots, cols)
            if ctx.geofences:
                flag |= self._fence_gate(picked, cols, ctx.geofences)
        if self.config.energy.record_dir is not None:  # the flight log takes every report
            flag[:] = True
        planned = fleet.planned[slots]
        if planned.any():
            flag |= self._plan_gate(slots, cols, planned & ~flag, ctx)
            for k in np.flatnonzero(planned & flag & fleet.skipped[slots]).tolist():
                agent = fleet.agents[slots[k]]
                if agent is not None and agent.plan is not None:  # as if the report before was tracked
                    agent.plan.passed(fleet.previous(agent.slot))
        fleet.skipped[slots] = ~flag
        checked: list[int] = rows[flag].tolist()
        return checked

    def _fence_gate(
        self, picked: list[AgentSession], cols: np.ndarray[Any, Any], fences: Mapping[str, Geofence]
    ) -> np.ndarray[Any, Any]:
        """The rows of drones with a fence that are outside it or near its edge (``Fleet.fence_gate``,
        one pass per fence: usually the fleet shares one)."""
        flag = np.zeros(len(picked), dtype=bool)
        groups: dict[int, tuple[Geofence, list[int]]] = {}
        for k, session in enumerate(picked):
            fence = fences.get(session.identity)
            if fence is not None:
                groups.setdefault(id(fence), (fence, []))[1].append(k)
        for fence, members in groups.values():
            flag[members] = self._fleet.fence_gate(cols[members], fence)
        return flag

    def _plan_gate(
        self,
        slots: np.ndarray[Any, np.dtype[np.intp]],
        cols: np.ndarray[Any, Any],
        rows: np.ndarray[Any, Any],
        ctx: ServiceContext,
    ) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """Of ``rows`` (drones in a plan, not flagged yet): those whose plan is gone (tracking must
        drop it) or whose position is near a divergence limit (``Fleet.leg_gate``)."""
        flag = np.zeros(len(slots), dtype=bool)
        plan_of, agents = ctx.missions.plan_of, self._fleet.agents
        for k in np.flatnonzero(rows).tolist():
            agent = agents[slots[k]]
            mission = agent.state.mission_id if agent is not None else None
            flag[k] = agent is None or mission is None or plan_of(mission, agent.ident) is None
        if self.config.divergence.enabled:
            rest = rows & ~flag
            if rest.any():
                flag[rest] = self._fleet.leg_gate(slots[rest], cols[rest])
        return flag


__all__ = ["TickGate", "carries_more", "sticky"]

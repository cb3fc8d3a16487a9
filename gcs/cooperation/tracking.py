"""The cooperation services' memory of each agent: last status, plan position, per-check state.

:func:`track` follows where a drone is in its mission plan (pure: the mission lookup is passed
in), so every monitor reads the same picture.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gcs.cooperation.divergence import DivergenceJudge
from gcs.cooperation.emergency import BatteryEstimator
from gcs.cooperation.flightlog import FlightLogWriter
from gcs.cooperation.geo import LocalFrame
from gcs.cooperation.legs import AgentPlanState, Point
from protocol.actions import Action
from protocol.packets import GeoPoint, Position, StatusReport


@dataclass(slots=True)
class TrackedAgent:
    """What the services keep per agent between status reports."""

    ident: str
    cid: int
    home: GeoPoint | None
    status: StatusReport
    position: Position  # the last reported position (the service tracks positioned reports only)
    received: float  # monotonic
    connected: bool = True
    plan: AgentPlanState | None = None
    completed: int = -1
    detour_step: int | None = None
    judge: DivergenceJudge | None = None
    battery: BatteryEstimator | None = None
    conditions: dict[str, float] = field(default_factory=dict)  # condition -> since (monotonic)
    acted: set[str] = field(default_factory=set)
    emergency: str | None = None
    disconnected_since: float | None = None
    link_acted: bool = False
    warned: set[tuple[int, int]] = field(default_factory=set)
    recorder: FlightLogWriter | None = None

    @property
    def airborne(self) -> bool:
        return self.status.armed and not self.status.landed


def track(
    agent: TrackedAgent,
    status: StatusReport,
    plan_of: tuple[str, list[Action]] | None,
    acceptance_radius_m: float,
    new_judge: Callable[[], DivergenceJudge],
) -> None:
    """Follow the drone's position in its plan (``plan_of``: mission id and its actions, or None)."""
    if plan_of is None:
        agent.plan = None
        if status.landed and not status.armed:
            agent.emergency = None
        return
    mission_id, actions = plan_of
    if agent.plan is None or agent.plan.mission_id != mission_id:
        home = agent.home
        here = agent.position
        origin: Point = (home.lat, home.lon, 0.0) if home else (here.lat, here.lon, 0.0)
        agent.plan = AgentPlanState(mission_id, actions, origin, acceptance_radius_m)
        agent.completed, agent.detour_step, agent.emergency = -1, None, None
        agent.judge = new_judge()
        agent.warned.clear()
    agent.completed = max(agent.completed, status.completed_step)
    if agent.detour_step is not None:
        if status.step == agent.detour_step and status.waiting_sync is None:
            return  # flying a detour the service inserted; the plan position is unchanged
        agent.detour_step = None
    agent.plan.update(status)


def leg_remaining_m(agent: TrackedAgent, frame: LocalFrame) -> float | None:
    """Distance (3-D, metres) to the target of the leg the drone flies, where it will stop."""
    plan = agent.plan
    if plan is None:
        return None
    leg = plan.leg(agent.status.waiting_sync)
    if leg is None:
        return None
    here = frame.point(agent.position.lat, agent.position.lon)
    there = frame.point(leg.target[0], leg.target[1])
    return float(
        np.linalg.norm([there[0] - here[0], there[1] - here[1], leg.target[2] - agent.position.alt_rel])
    )


def leg_target_velocity(
    agent: TrackedAgent, frame: LocalFrame, default_speed: float
) -> tuple[float, float, float] | None:
    """Where a held drone wants to go: toward its leg target at the planned speed."""
    plan, status = agent.plan, agent.status
    if plan is None:
        return None
    leg = plan.leg(status.waiting_sync)
    if leg is None or leg.start is None:
        return (0.0, 0.0, 0.0) if status.waiting_sync is not None else None
    position = agent.position
    here = frame.point(position.lat, position.lon)
    there = frame.point(leg.target[0], leg.target[1])
    delta = np.array([there[0] - here[0], there[1] - here[1], leg.target[2] - position.alt_rel])
    norm = float(np.linalg.norm(delta))
    if norm < 0.5:
        return (0.0, 0.0, 0.0)
    v = delta / norm * (leg.speed or default_speed)
    return (float(v[0]), float(v[1]), float(v[2]))

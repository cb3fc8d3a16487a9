"""The cooperation services' memory of each agent: last status, plan position, per-check state.

:func:`track` follows where a drone is in its mission plan (pure: the mission lookup is passed
in), so every monitor reads the same picture.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import numpy as np

from gcs.cooperation.divergence import DivergenceJudge
from gcs.cooperation.emergency import BatteryView
from gcs.cooperation.flightlog import FlightLogWriter
from gcs.cooperation.legs import AgentPlanState, Point
from gcs.planning.geodesy import LocalFrame
from protocol.actions import Action
from protocol.packets import GeoPoint, Position, StatusReport


class Rows(Protocol):
    """Where a tracked agent's newest report lives (gcs/cooperation/fleet.py ``Fleet``)."""

    version: np.ndarray[Any, np.dtype[np.int64]]
    received: np.ndarray[Any, np.dtype[np.float64]]

    def report(self, slot: int) -> StatusReport: ...


class TrackedAgent:
    """What the services keep per agent between status reports.

    The newest report's numbers live in the fleet's arrays (``rows``, row ``slot``); most reports
    only update those (gcs/cooperation/service.py, the status tick). :attr:`status` and
    :attr:`position` are that newest report, built on first use after such an update;
    :attr:`state` is the last report built, whose *state* (flags, steps, mode, mission) is always
    the newest's, because a report whose state changed is always built, so readers of state
    only (collision eligibility, airborne) never build one.
    """

    __slots__ = (
        "_received",
        "_status",
        "_version",
        "acted",
        "battery",
        "cid",
        "completed",
        "conditions",
        "connected",
        "detour_step",
        "disconnected_since",
        "emergency",
        "home",
        "ident",
        "judge",
        "link_acted",
        "plan",
        "recorder",
        "rows",
        "slot",
        "warned",
    )

    def __init__(
        self,
        ident: str,
        cid: int,
        home: GeoPoint | None,
        status: StatusReport,
        position: Position,
        received: float,  # monotonic
        connected: bool = True,
    ) -> None:
        del position  # the report's own (kept in the signature: the report is positioned)
        self.ident, self.cid, self.home = ident, cid, home
        self._status, self._received, self._version = status, received, -1
        self.rows: Rows | None = None  # set with ``slot`` when the fleet gives the agent a row
        self.slot = -1
        self.connected = connected
        self.plan: AgentPlanState | None = None
        self.completed = -1
        self.detour_step: int | None = None
        self.judge: DivergenceJudge | None = None
        self.battery: BatteryView | None = None
        self.conditions: dict[str, float] = {}  # condition -> since (monotonic)
        self.acted: set[str] = set()
        self.emergency: str | None = None
        self.disconnected_since: float | None = None
        self.link_acted = False
        self.warned: set[tuple[int, int]] = set()
        self.recorder: FlightLogWriter | None = None

    def seen(self, status: StatusReport, received: float) -> None:
        """``status`` is the newest report (its row in ``rows`` written already, if any)."""
        self._status, self._received = status, received
        rows = self.rows
        if rows is not None:
            self._version = int(rows.version[self.slot])
            rows.received[self.slot] = received

    @property
    def status(self) -> StatusReport:
        """The newest report (built from the fleet's row when only the row was updated)."""
        rows = self.rows
        if rows is not None and rows.version[self.slot] != self._version:
            self._status = rows.report(self.slot)
            self._version = int(rows.version[self.slot])
        return self._status

    @property
    def state(self) -> StatusReport:
        """The last report built: the newest state, numbers (position, battery...) maybe older."""
        return self._status

    @property
    def position(self) -> Position:
        """The last reported position (the service tracks positioned reports only)."""
        position = self.status.position
        assert position is not None
        return position

    @property
    def received(self) -> float:
        """When the newest report arrived (monotonic)."""
        rows = self.rows
        return float(rows.received[self.slot]) if rows is not None else self._received

    @property
    def airborne(self) -> bool:
        state = self._status
        return state.armed and not state.landed


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


Here = tuple[float, float, float]  # lat, lon, alt_rel of the newest report


class Kinematics(NamedTuple):
    """Newest positions and velocities of a list of agents, one array element per agent."""

    lat: np.ndarray[Any, np.dtype[np.float64]]
    lon: np.ndarray[Any, np.dtype[np.float64]]
    alt_rel: np.ndarray[Any, np.dtype[np.float64]]
    alt_amsl: np.ndarray[Any, np.dtype[np.float64]]
    vn: np.ndarray[Any, np.dtype[np.float64]]
    ve: np.ndarray[Any, np.dtype[np.float64]]
    vd: np.ndarray[Any, np.dtype[np.float64]]

    @classmethod
    def of(cls, cols: np.ndarray[Any, Any]) -> Kinematics:
        """From status columns (``gcs.link.agents_table.ROW_DTYPE``)."""
        return cls(*(np.asarray(cols[name], dtype=np.float64) for name in cls._fields))

    def take(self, rows: list[int]) -> Kinematics:
        """The elements at ``rows``, in that order."""
        return Kinematics(*(column[rows] for column in self))

    @classmethod
    def of_agents(cls, agents: list[TrackedAgent]) -> Kinematics:
        """From the agents' reports (built if need be)."""
        reports = [a.status for a in agents]
        positions = [a.position for a in agents]
        return cls(
            np.array([p.lat for p in positions]),
            np.array([p.lon for p in positions]),
            np.array([p.alt_rel for p in positions]),
            np.array([p.alt_amsl for p in positions]),
            np.array([r.velocity.vn for r in reports]),
            np.array([r.velocity.ve for r in reports]),
            np.array([r.velocity.vd for r in reports]),
        )


def _here(agent: TrackedAgent, here: Here | None) -> Here:
    if here is not None:
        return here
    p = agent.position
    return (p.lat, p.lon, p.alt_rel)


Velocity = tuple[float, float, float]


def leg_motion(
    agent: TrackedAgent,
    frame: LocalFrame,
    default_speed: float,
    here: Here | None = None,
    here_local: tuple[float, float] | None = None,
) -> tuple[Velocity | None, float | None]:
    """Where the drone wants to go (toward its leg target at the planned speed; still while it
    waits at a barrier) and how far it has left to the target, where it will stop (3-D metres),
    from one look at its leg, in plain floats (the collision check asks for both for every drone
    of the fleet on each pass; ``here_local``: ``here`` already in ``frame``, as that check has it)."""
    plan, waiting = agent.plan, agent.state.waiting_sync
    if plan is None:
        return None, None
    leg = plan.leg(waiting)
    if leg is None:
        return ((0.0, 0.0, 0.0) if waiting is not None else None), None
    lat, lon, alt_rel = _here(agent, here)
    e, n = here_local if here_local is not None else frame.local_point(lat, lon)
    te, tn = frame.local_point(leg.target[0], leg.target[1])
    de, dn, du = te - e, tn - n, leg.target[2] - alt_rel
    norm = math.sqrt(dn * dn + de * de + du * du)
    if leg.start is None:
        return ((0.0, 0.0, 0.0) if waiting is not None else None), norm
    if norm < 0.5:
        return (0.0, 0.0, 0.0), norm
    k = (leg.speed or default_speed) / norm
    return (de * k, dn * k, du * k), norm

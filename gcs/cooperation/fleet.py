"""The tracked agents' newest reports as arrays, and the gates that pick who needs a closer look.

Why: at 2,000 agents and 10 Hz, building a ``StatusReport`` and running every per-agent check
(plan tracking, emergency edges, divergence) for each report cost the event loop ~16 us a report.
Almost every report of a healthy fleet changes nothing those checks act on. Here a status tick's
rows are copied into per-agent rows (the fleet status table's raw layout, read as NumPy columns),
the battery estimators are fed in one vectorised pass, and cheap column compares (:meth:`Fleet.gate`)
flag the rows that need the per-agent Python checks: a new agent, a changed state (flags, steps,
mode, mission), a mission or a condition in force, GPS below 3D, a battery near the return-home
need. Only those get a report built and checked; the others cost a few array writes.

A gate must flag *every* row the per-report checks would act on (tests/cooperation/units/
test_fleet_gates.py checks that against the checks themselves for random reports).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from gcs.cooperation.config import DivergenceConfig, EmergencyConfig
from gcs.cooperation.emergency import NO_RETURN_MODES, BatteryColumns
from gcs.cooperation.legs import Point
from gcs.cooperation.tracking import TrackedAgent
from gcs.link.agents_table import ROW_BYTES, ROW_DTYPE, STATE_BYTES, row_report
from gcs.planning.geodesy import distance_m_array, ned_offset_m_array
from protocol import status_binary
from protocol.packets import Geofence, StatusReport
from protocol.status_binary import ARMED, LANDED

IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]
STATE_INDEX = np.array(STATE_BYTES, dtype=np.intp)
LEG_MARGIN_M = 0.5
"""A drone within this many metres of a divergence limit (cross-track, hover drift, lag) gets the
exact check; the columns' flat-earth estimate agrees with it to millimetres."""
FENCE_MARGIN_M = 0.5
"""A drone within this many metres of its fence's circle or ceiling gets the exact check."""
BATTERY_MARGIN_PCT = 1.0
"""A battery within this many % of its return-home need gets the exact (scalar) check; the
vectorised estimate agrees with it to ~1e-9 %, so the margin only guards rounding."""


class Fleet:
    """Per agent slot: the newest raw report row, its version and arrival, home, battery history.

    ``rows`` are :data:`gcs.link.agents_table.ROW_BYTES` bytes each, the status table's layout, so a
    tick's rows copy in with one assignment and :attr:`cols` reads them as columns. ``version``
    counts the rows written; a :class:`TrackedAgent` builds its report again only when its row's
    version moved on (``TrackedAgent.status``).
    """

    def __init__(
        self,
        emergency: EmergencyConfig,
        divergence: DivergenceConfig,
        vehicle_time_scale: float,
        capacity: int = 64,
    ) -> None:
        self.config = emergency
        self.divergence = divergence
        self.vehicle_time_scale = vehicle_time_scale
        n = max(1, capacity)
        self.raw = np.zeros((n, ROW_BYTES), dtype=np.uint8)
        self.version = np.zeros(n, dtype=np.int64)
        self.received = np.zeros(n)  # monotonic
        self.home = np.full((n, 2), np.nan)  # lat, lon (NaN: none)
        self.sticky = np.zeros(n, dtype=bool)  # every report goes to the per-agent checks
        self.no_return = np.zeros(n, dtype=bool)  # mode RTL or LAND (as of the last built report)
        self.prev = np.zeros((n, 3))  # lat, lon, alt_rel of the row before the newest
        # The leg the drone flies as of its last built report (gcs/cooperation/legs.py Leg):
        self.leg_kind = np.zeros(n, dtype=np.int8)  # 0 none (or no plan), 1 a line, 2 a hover point
        self.leg = np.zeros((n, 4))  # start lat, lon (a line), target lat, lon
        self.leg_speed = np.full(n, np.nan)  # planned speed (NaN: none)
        self.leg_started = np.zeros(n)  # report time the running segment started (lag)
        self.lag_pending = np.zeros(n, dtype=bool)  # a lag event may still come on this leg
        self.planned = np.zeros(n, dtype=bool)  # tracked in a mission plan
        self.skipped = np.zeros(n, dtype=bool)  # the newest row was not built (not tracked)
        self.battery = BatteryColumns(emergency.battery_window_s, n)
        self.agents: list[TrackedAgent | None] = [None] * n
        self.sessions: list[Any] = [None] * n  # the session whose reports fill the slot
        self.by_session: dict[Any, int] = {}  # that session -> the slot
        self._free: list[int] = []
        self._used = 0

    @property
    def capacity(self) -> int:
        return len(self.version)

    @property
    def cols(self) -> np.ndarray[Any, Any]:
        """Every slot's newest report as the status table's columns (a view, no copy)."""
        return self.raw.view(ROW_DTYPE)[:, 0]

    def attach(self, agent: TrackedAgent, session: object) -> int:
        """A cleared slot for a new tracked agent (its row written by the caller)."""
        if self._free:
            slot = self._free.pop()
            self.battery.reset(np.array([slot], dtype=np.intp))  # a fresh row is clear already
        else:
            if self._used == self.capacity:
                self._grow()
            slot = self._used
            self._used += 1
        self.raw[slot] = 0
        self.version[slot] += 1
        self.home[slot] = np.nan
        self.sticky[slot] = True
        self.no_return[slot] = False
        self.leg_kind[slot] = 0
        self.planned[slot] = False
        self.skipped[slot] = False
        self.agents[slot] = agent
        self.link(slot, session)
        agent.rows, agent.slot = self, slot
        if agent.home is not None:
            self.home[slot] = (agent.home.lat, agent.home.lon)
        agent.battery = self.battery.view(slot)
        return slot

    def release(self, agent: TrackedAgent) -> None:
        """The agent left: its slot is free (the agent keeps its last report)."""
        slot = agent.slot
        if slot < 0 or self.agents[slot] is not agent:
            return
        agent.rows, agent.slot = None, -1
        self.link(slot, None)
        self.agents[slot] = None
        self._free.append(slot)

    def link(self, slot: int, session: object) -> None:
        """``session``'s reports fill ``slot`` from now on (None: no session)."""
        old = self.sessions[slot]
        if old is session:
            return
        if old is not None and self.by_session.get(old) == slot:
            del self.by_session[old]
        self.sessions[slot] = session
        if session is not None:
            self.by_session[session] = slot

    def _grow(self) -> None:
        """Double every array (views taken before stay on the old ones)."""
        old = self.capacity
        n = old * 2
        self.raw = np.concatenate([self.raw, np.zeros((old, ROW_BYTES), dtype=np.uint8)])
        self.version = np.concatenate([self.version, np.zeros(old, dtype=np.int64)])
        self.received = np.concatenate([self.received, np.zeros(old)])
        self.home = np.concatenate([self.home, np.full((old, 2), np.nan)])
        self.sticky = np.concatenate([self.sticky, np.zeros(old, dtype=bool)])
        self.no_return = np.concatenate([self.no_return, np.zeros(old, dtype=bool)])
        self.prev = np.concatenate([self.prev, np.zeros((old, 3))])
        self.leg_kind = np.concatenate([self.leg_kind, np.zeros(old, dtype=np.int8)])
        self.leg = np.concatenate([self.leg, np.zeros((old, 4))])
        self.leg_speed = np.concatenate([self.leg_speed, np.full(old, np.nan)])
        self.leg_started = np.concatenate([self.leg_started, np.zeros(old)])
        self.lag_pending = np.concatenate([self.lag_pending, np.zeros(old, dtype=bool)])
        self.planned = np.concatenate([self.planned, np.zeros(old, dtype=bool)])
        self.skipped = np.concatenate([self.skipped, np.zeros(old, dtype=bool)])
        self.battery.grow(n)
        self.agents += [None] * old
        self.sessions += [None] * old

    def put_report(self, slot: int, report: StatusReport, now: float) -> None:
        """A report that came as an object only (cluster): its fixed fields into the row. The row
        has no mode or mission, so the next row from a tick counts as a changed state."""
        self._keep_previous(np.array([slot], dtype=np.intp))
        self.raw[slot] = 0
        body = status_binary.encode(report)[: status_binary.FIXED_SIZE]
        self.raw[slot, : len(body)] = np.frombuffer(body, dtype=np.uint8)
        self.version[slot] += 1
        self.received[slot] = now
        self.skipped[slot] = False

    def stick(self, agent: TrackedAgent) -> None:
        """The agent's next report goes to the per-agent checks (a decision about it was made
        outside them: its plan position or orders may have changed)."""
        if agent.slot >= 0:
            self.sticky[agent.slot] = True

    def report(self, slot: int) -> StatusReport:
        """The slot's newest report built from its row (the row passed the tick's range check)."""
        return row_report(self.raw[slot].tobytes())

    def write(self, slots: IntArray, raw: NDArray[np.uint8], now: float) -> BoolArray:
        """A tick's rows (``raw``, one per slot) become the slots' newest reports; which changed
        state (:data:`STATE_BYTES`) from the row before."""
        planned = self.planned[slots]
        if planned.any():  # (only the plan tracking reads where a drone was a report ago)
            self._keep_previous(slots[planned])
        changed: BoolArray = (self.raw[slots] != raw)[:, STATE_INDEX].any(axis=1)
        self.raw[slots] = raw
        self.version[slots] += 1
        self.received[slots] = now
        return changed

    def _keep_previous(self, slots: IntArray) -> None:
        cols = self.cols
        self.prev[slots, 0], self.prev[slots, 1] = cols["lat"][slots], cols["lon"][slots]
        self.prev[slots, 2] = cols["alt_rel"][slots]

    def previous(self, slot: int) -> Point:
        """Where the drone was at the report before its newest (lat, lon, alt_rel); kept for drones
        in a plan only (their rows are written with the plan known: :meth:`settle`)."""
        lat, lon, alt_rel = self.prev[slot].tolist()
        return (lat, lon, alt_rel)

    def leg_gate(self, slots: IntArray, cols: np.ndarray[Any, Any]) -> BoolArray:
        """Which rows of drones in a plan may be acted on by divergence: within
        :data:`LEG_MARGIN_M` of the correction limit off the leg (``divergence.leg_error`` on
        columns, the same flat-earth offsets from the leg's start) or of a lag event."""
        flag = np.zeros(len(slots), dtype=bool)
        kind = self.leg_kind[slots]
        if not kind.any():
            return flag
        cfg, margin = self.divergence, LEG_MARGIN_M
        leg = self.leg[slots]
        lat, lon = cols["lat"], cols["lon"]
        hover = kind == 2
        if hover.any():
            n, e = ned_offset_m_array(leg[hover, 2], leg[hover, 3], lat[hover], lon[hover])
            flag[hover] = np.hypot(n, e) >= cfg.hover_drift_m - margin
        line = kind == 1
        if line.any():
            s = slots[line]
            sn, se = ned_offset_m_array(leg[line, 0], leg[line, 1], leg[line, 2], leg[line, 3])
            pn, pe = ned_offset_m_array(leg[line, 0], leg[line, 1], lat[line], lon[line])
            length = np.hypot(sn, se)
            point = length < 1e-6
            safe = np.where(point, 1.0, length)
            un, ue = sn / safe, se / safe
            along = np.where(point, 0.0, pn * un + pe * ue)
            clamped = np.minimum(np.maximum(along, 0.0), length)
            cross = np.where(point, np.hypot(pn, pe), np.hypot(pn - clamped * un, pe - clamped * ue))
            near = cross >= cfg.correct_m - margin
            elapsed = (cols["time"][line] - self.leg_started[s]) * self.vehicle_time_scale
            with np.errstate(invalid="ignore"):
                expected = np.minimum(np.where(point, 0.0, length), self.leg_speed[s] * elapsed)
                near |= self.lag_pending[s] & (expected - along > cfg.lag_event_m - margin)
            flag[line] = near
        return flag

    @staticmethod
    def fence_gate(cols: np.ndarray[Any, Any], fence: Geofence) -> BoolArray:
        """Which rows may be outside ``fence`` (``Geofence.violation`` on columns, the same
        haversine): above its ceiling or off its circle, or within :data:`FENCE_MARGIN_M` of them.
        A polygon is tested per report (every row flagged)."""
        if fence.polygon is not None:
            return np.ones(len(cols), dtype=bool)
        flag = np.zeros(len(cols), dtype=bool)
        if fence.max_alt_m is not None:
            flag |= cols["alt_rel"] > fence.max_alt_m - FENCE_MARGIN_M
        circle = fence.circle
        if circle is not None:
            off = distance_m_array(cols["lat"], cols["lon"], circle.lat, circle.lon)
            flag |= off > circle.radius_m - FENCE_MARGIN_M
        return flag

    def feed_battery(self, slots: IntArray, cols: np.ndarray[Any, Any]) -> None:
        """Every armed, flying report with a battery % into its slot's estimator (``cols``: the rows)."""
        flags, pct = cols["flags"], cols["battery_pct"]
        take = ((flags & (ARMED | LANDED)) == ARMED) & ~np.isnan(pct)
        if take.all():  # (the usual case: no subsets to copy)
            self.battery.add(slots, cols["time"], pct, cols["lat"], cols["lon"])
        elif take.any():
            self.battery.add(slots[take], cols["time"][take], pct[take], cols["lat"][take], cols["lon"][take])

    def gate(self, slots: IntArray, cols: np.ndarray[Any, Any]) -> BoolArray:
        """Which rows the emergency checks may act on beyond a changed state or a sticky slot: GPS
        below 3D in the air, or a battery within :data:`BATTERY_MARGIN_PCT` of its return need
        (the same estimate ``emergency.return_home_shortfall`` makes, on columns)."""
        flags, pct = cols["flags"], cols["battery_pct"]
        flying = (flags & (ARMED | LANDED)) == ARMED
        flag: BoolArray = flying & (cols["fix"] < 3)
        home = self.home[slots]
        battery = self.battery
        check = flying & ~np.isnan(pct) & ~np.isnan(home[:, 0]) & ~self.no_return[slots]
        check &= battery.rate[slots] > 0  # (NaN: not enough history) no drop, no return need
        check &= ~np.isnan(battery.speed[slots])
        if check.any():
            s = slots[check]
            cfg = self.config
            rate, speed = battery.rate[s], battery.speed[s]
            dist = distance_m_array(cols["lat"][check], cols["lon"][check], home[check, 0], home[check, 1])
            descent = np.maximum(cols["alt_rel"][check], 0.0) / (cfg.descent_mps * self.vehicle_time_scale)
            needed = rate * (dist / speed + descent) * cfg.battery_safety_factor + cfg.battery_reserve_pct
            flag[check] |= pct[check] < needed + BATTERY_MARGIN_PCT
        return flag

    def settle(self, agent: TrackedAgent, sticky: bool) -> None:
        """After the per-agent checks of a built report: whether every report of the agent needs
        them (a condition in force...), its mode for the battery gate, its leg for the leg gate."""
        slot = agent.slot
        if slot < 0:
            return
        self.sticky[slot] = sticky
        self.no_return[slot] = agent.state.mode in NO_RETURN_MODES
        plan = agent.plan
        self.planned[slot] = plan is not None
        leg = plan.leg(agent.state.waiting_sync) if plan is not None else None
        if plan is None or leg is None:
            self.leg_kind[slot] = 0
            return
        self.leg_kind[slot] = 2 if leg.start is None else 1
        start = leg.start or leg.target
        self.leg[slot] = (start[0], start[1], leg.target[0], leg.target[1])
        self.leg_speed[slot] = np.nan if leg.speed is None else leg.speed
        self.leg_started[slot] = plan.segment_started
        self.lag_pending[slot] = agent.judge is not None and agent.judge.lag_pending(leg)

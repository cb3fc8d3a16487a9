"""Where each drone is in its plan: the leg it flies now, as the agent flies it, and what is left.

The daemon sent the whole action list at mission start (docs/protocol.md section 5); status
reports say which step runs. From the two this module derives the current leg (start and
target) for divergence and collision checks, and rebuilds the remaining actions from the
drone's current position, which a ``replace`` needs: the running action becomes what is left of
it (a ``go_by`` becomes a ``goto`` to its fixed target, ``waypoints`` keep the points not yet
reached), later actions follow unchanged. Pure code: no sockets, no asyncio.

Legs are modelled the way the agent flies them (agent/executor.py): an action (or a waypoint)
is complete as soon as the vehicle is within the acceptance radius of its target, and the next
one starts from wherever the vehicle is at that moment, so a chain of legs cuts each corner by
up to the radius. A ``go_by`` offset is taken from the previous planned target (the agent's
anchor), so its target is the dead-reckoned plan's: the same point here and on the agent,
whatever the reports' lag. (It used to be taken from the switch point, which the daemon could
only estimate: a chain drifted by a radius per leg, and a detour or replan rebuilt the running
go_by's target from the estimate, metres off at a simulator's speed-up.) Where a leg starts
is estimated from the two reports around the switch (see :func:`switch_point`), never from
the plan alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from protocol.actions import Action, GoBy, Goto, Hold, SetSpeed, Takeoff, Waypoints
from protocol.geo import distance_m, ned_offset_m, offset_latlon
from protocol.packets import StatusReport

Point = tuple[float, float, float]  # lat, lon, alt_rel


@dataclass(frozen=True)
class Leg:
    """A straight planned segment; ``start`` is None for a point (hover target)."""

    step: int
    start: Point | None
    target: Point
    speed: float | None


def planned_targets(actions: list[Action], home: Point) -> list[Point | None]:
    """The planned position after each action (None where it is not a place: rtl, land...)."""
    here: Point = home
    out: list[Point | None] = []
    for action in actions:
        if isinstance(action, Takeoff):
            here = (here[0], here[1], action.alt)
        elif isinstance(action, Goto):
            here = (action.lat, action.lon, action.alt)
        elif isinstance(action, GoBy):
            lat, lon = offset_latlon(here[0], here[1], action.north, action.east)
            here = (lat, lon, here[2] + action.up)
        elif isinstance(action, Waypoints):
            last = action.points[-1]
            here = (last.lat, last.lon, last.alt)
        elif action.kind in ("land", "rtl"):
            out.append(None)
            continue
        out.append(here)
    return out


def agent_acceptance_radius(pushed_m: float | None, assumed_m: float) -> float:
    """The radius the agent judges arrival with: the one the daemon pushed, else the assumed one."""
    return pushed_m if pushed_m is not None else assumed_m


def switch_point(target: Point | None, before: Point | None, after: Point, radius: float) -> Point:
    """Where the agent was when it left a leg ending at ``target`` for the next one.

    The agent switches the first time it is within ``radius`` of ``target``; it flies straight at
    the target until then. The model point is therefore ``radius`` short of the target on the
    line from the last report of the old leg (``before``); the estimate is the point of the
    observed chord ``before -> after`` (the reports on either side of the switch) nearest to it,
    so it always lies on the flown track whatever the error of ``target``. With no target (the
    vehicle hovered: barrier, hold, pause) it is ``before``; with no report before the switch,
    ``after``.
    """
    if before is None:
        return after
    if target is None:
        return before
    lat0, lon0 = before[0], before[1]
    an, ae = ned_offset_m(lat0, lon0, after[0], after[1])
    tn, te = ned_offset_m(lat0, lon0, target[0], target[1])
    gap = math.hypot(tn, te)
    back = min(radius, gap) / gap if gap > 1e-9 else 0.0
    mn, me = tn * (1.0 - back), te * (1.0 - back)  # radius short of the target, toward ``before``
    chord2 = an * an + ae * ae
    f = 0.0 if chord2 <= 1e-12 else min(max((mn * an + me * ae) / chord2, 0.0), 1.0)
    lat, lon = offset_latlon(lat0, lon0, f * an, f * ae)
    return (lat, lon, before[2] + f * (after[2] - before[2]))


def _speed_before(actions: list[Action], index: int) -> float | None:
    for action in reversed(actions[:index]):
        if isinstance(action, SetSpeed):
            return action.speed
    return None


@dataclass
class AgentPlanState:
    """Tracks one agent through its plan from its status reports.

    ``acceptance_m`` must be the agent's own arrival radius (:func:`agent_acceptance_radius`).
    ``step_start_pos`` is where the agent was when the running step started (estimated with
    :func:`switch_point`); ``segment_start`` the same for the running waypoint segment.
    """

    mission_id: str
    actions: list[Action]
    home: Point
    acceptance_m: float = 2.5
    step: int = -1
    index: int = -1  # index into actions of the running action
    step_started: float = 0.0
    step_start_pos: Point | None = None
    waypoint: int = 0  # index of the next waypoint of a running waypoints action
    segment_started: float = 0.0
    segment_start: Point | None = None
    replans: int = 0
    blocked_since: float | None = None  # report time the drone stopped flying its plan (lag clock)
    _targets: list[Point | None] = field(default_factory=list)
    _last_pos: Point | None = None
    _last_target: Point | None = None  # where the agent was heading at the last report

    def __post_init__(self) -> None:
        self._targets = planned_targets(self.actions, self.home)

    def update(self, status: StatusReport) -> None:
        if status.position is None:
            return  # no fix: nothing to place on the plan
        pos = (status.position.lat, status.position.lon, status.position.alt_rel)
        if status.paused and status.step < 0:
            self._last_pos, self._last_target = pos, None  # held in place: resumes from here
            return  # a pause puts the running action back in the queue: still the same step
        if status.step != self.step:
            previous = self._last_target
            self.step = status.step
            self.index = next((k for k, a in enumerate(self.actions) if a.step == status.step), -1)
            self.step_started = status.time
            self.segment_started = status.time
            self.step_start_pos = switch_point(previous, self._last_pos, pos, self.acceptance_m)
            self.segment_start = self.step_start_pos
            self.waypoint = 0
            self.replans = 0
        action = self.current_action
        if isinstance(action, Waypoints):
            self._advance_waypoints(action, pos, status.time)
        self._last_pos = pos
        # At a barrier the vehicle keeps flying to its target and hovers there: the next leg
        # starts from the last waiting report (switch_point with target None keeps ``before``).
        self._last_target = None if status.waiting_sync is not None else self._heading()

    def stop_clock(self, blocked: bool, now: float) -> None:
        """Stop the running segment's clock while the drone may not fly its plan (paused, held...).

        Why: the along-track lag compares progress with the time since the segment started; a
        drone held by an operator for 20 s was then reported "51-86 m behind the planned speed"
        as soon as it flew again. A step that starts while blocked starts its own clock.
        """
        if blocked:
            if self.blocked_since is None:
                self.blocked_since = now
        elif self.blocked_since is not None:
            self.segment_started += max(0.0, now - max(self.blocked_since, self.segment_started))
            self.blocked_since = None

    def passed(self, pos: Point) -> None:
        """A report that changed nothing here was not tracked (gcs/cooperation/fleet.py): the drone
        was last at ``pos``, where :meth:`update` would have put it (the next switch point is
        estimated from there). Only valid when the running step, waypoint and barrier wait did
        not change since the last :meth:`update` (the gates build every report that changes them)."""
        self._last_pos = pos

    def _heading(self) -> Point | None:
        """The target the agent flies to now, as the agent computed it."""
        action = self.current_action
        if isinstance(action, Goto):
            return (action.lat, action.lon, action.alt)
        if isinstance(action, GoBy):
            return self._go_by_target(action)
        if isinstance(action, Waypoints):
            p = action.points[self.waypoint]
            return (p.lat, p.lon, p.alt)
        if isinstance(action, Takeoff) and self.step_start_pos is not None:
            return (self.step_start_pos[0], self.step_start_pos[1], action.alt)
        return None

    @property
    def current_action(self) -> Action | None:
        return self.actions[self.index] if 0 <= self.index < len(self.actions) else None

    def _advance_waypoints(self, action: Waypoints, pos: Point, now: float) -> None:
        """Move to the next point when this one is reached, or when the drone is nearer the next
        segment than this one (sparse reports can skip the arrival itself)."""
        points = action.points
        advanced = False
        while self.waypoint < len(points) - 1:
            p = points[self.waypoint]
            reached = distance_m(pos[0], pos[1], p.lat, p.lon) <= self.acceptance_m
            here = self._segment_distance(action, self.waypoint, pos)
            following = self._segment_distance(action, self.waypoint + 1, pos)
            if not (reached or (here is not None and following is not None and following < here)):
                break
            self.waypoint += 1
            self.segment_started = now
            advanced = True
        if advanced:
            p = points[self.waypoint - 1]
            self.segment_start = switch_point((p.lat, p.lon, p.alt), self._last_pos, pos, self.acceptance_m)

    def _segment_distance(self, action: Waypoints, k: int, pos: Point) -> float | None:
        start = self._waypoint_start(action, k)
        if start is None:
            return None
        end = action.points[k]
        en, ee = ned_offset_m(start[0], start[1], end.lat, end.lon)
        pn, pe = ned_offset_m(start[0], start[1], pos[0], pos[1])
        length2 = en * en + ee * ee
        f = 0.0 if length2 <= 0 else min(max((pn * en + pe * ee) / length2, 0.0), 1.0)
        return math.hypot(pn - f * en, pe - f * ee)

    def _waypoint_start(self, action: Waypoints, k: int) -> Point | None:
        """Start of segment k (the previous point; for the first, where the step started), used to
        tell which segment a report is on."""
        if k > 0:
            p = action.points[k - 1]
            return (p.lat, p.lon, p.alt)
        return self.step_start_pos if self.step_start_pos is not None else self._previous_target()

    def _leg_start(self) -> Point | None:
        """Where the running segment started as the agent flew it, else the planned previous target."""
        return self.segment_start if self.segment_start is not None else self._previous_target()

    def _previous_target(self) -> Point | None:
        for k in range(self.index - 1, -1, -1):
            target = self._targets[k]
            if target is not None:
                return target
        return self.step_start_pos

    def _speed(self, action: Action) -> float | None:
        speed = getattr(action, "speed", None)
        return speed if speed is not None else _speed_before(self.actions, self.index)

    def leg(self, waiting_sync: int | None) -> Leg | None:
        """The leg being flown (from where the agent started it), or the hover point at a barrier."""
        if waiting_sync is not None:
            k = max((i for i, a in enumerate(self.actions) if a.step == waiting_sync), default=-1)
            if k < 0:
                return None
            target = self._targets[k]
            return Leg(waiting_sync, None, target, None) if target is not None else None
        action = self.current_action
        if action is None:
            return None
        if isinstance(action, Goto):
            return Leg(
                action.step, self._leg_start(), (action.lat, action.lon, action.alt), self._speed(action)
            )
        if isinstance(action, GoBy):
            return Leg(action.step, self._leg_start(), self._go_by_target(action), self._speed(action))
        if isinstance(action, Waypoints):
            p = action.points[self.waypoint]
            return Leg(action.step, self._leg_start(), (p.lat, p.lon, p.alt), self._speed(action))
        return None

    def _go_by_target(self, action: GoBy) -> Point:
        """The running go_by's target: its offset from the previous planned target, as the agent
        anchors it (agent/executor.py ``go_by_target``)."""
        target = self._targets[self.index] if 0 <= self.index < len(self._targets) else None
        if target is not None:
            return target
        base = self.step_start_pos or self.home  # pragma: no cover - a go_by always has a target
        lat, lon = offset_latlon(base[0], base[1], action.north, action.east)
        return (lat, lon, base[2] + action.up)

    def remaining(self, status: StatusReport, completed: int) -> list[Action]:
        """What is left of the plan from here: the running action's remainder, then later actions.

        ``completed`` is the highest step the daemon saw completed (the agent's own counter
        restarts at -1 after a ``replace``).
        """
        if status.waiting_sync is not None:
            return [a for a in self.actions if a.step > status.waiting_sync]
        action = self.current_action
        if action is None:
            return [a for a in self.actions if a.step > completed]
        rest = self.actions[self.index + 1 :]
        if isinstance(action, GoBy):
            lat, lon, alt = self._go_by_target(action)
            head: Action = action.as_goto(lat, lon, alt)
        elif isinstance(action, Waypoints):
            head = action.model_copy(update={"points": action.points[self.waypoint :]})
        elif isinstance(action, Hold):
            left = max(0.0, action.seconds - (status.time - self.step_started))
            head = action.model_copy(update={"seconds": left})
        else:
            head = action
        return [head, *rest]

    def detour(self, status: StatusReport, via: Point, completed: int) -> list[Action] | None:
        """A replace batch: fly to ``via`` first, then what is left of the plan; None if impossible.

        While waiting at sync step k the detour carries step k with sync, so the agent reports
        k again and waits for its (possibly already sent) release. Otherwise it carries the last
        completed step, so finishing it reports nothing new to the barrier or the progress.
        """
        lat, lon, alt = via
        if status.waiting_sync is not None:
            k = status.waiting_sync
            return [Goto(step=k, sync=True, lat=lat, lon=lon, alt=alt), *self.remaining(status, completed)]
        if completed < 0 or self.current_action is None:
            return None  # still taking off (or idle): no step number that would not lie about progress
        return [Goto(step=completed, lat=lat, lon=lon, alt=alt), *self.remaining(status, completed)]

"""Where each drone is in its plan: the planned leg it flies now, and what is left of its plan.

The daemon sent the whole action list at mission start (docs/protocol.md section 5); status
reports say which step runs. From the two this module derives the current planned leg (start
and target) for divergence and collision checks, and rebuilds the remaining actions from the
drone's current position, which a ``replace`` needs: the running action becomes what is left of
it (a ``go_by`` becomes a ``goto`` to its fixed target, ``waypoints`` keep the points not yet
reached), later actions follow unchanged. Pure code: no sockets, no asyncio.
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


def _speed_before(actions: list[Action], index: int) -> float | None:
    for action in reversed(actions[:index]):
        if isinstance(action, SetSpeed):
            return action.speed
    return None


@dataclass
class AgentPlanState:
    """Tracks one agent through its plan from its status reports."""

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
    replans: int = 0
    _targets: list[Point | None] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._targets = planned_targets(self.actions, self.home)

    def update(self, status: StatusReport) -> None:
        pos = (status.position.lat, status.position.lon, status.position.alt_rel)
        if status.paused and status.step < 0:
            return  # a pause puts the running action back in the queue: still the same step
        if status.step != self.step:
            self.step = status.step
            self.index = next((k for k, a in enumerate(self.actions) if a.step == status.step), -1)
            self.step_started = status.time
            self.segment_started = status.time
            self.step_start_pos = pos
            self.waypoint = 0
            self.replans = 0
        action = self.current_action
        if isinstance(action, Waypoints):
            self._advance_waypoints(action, pos, status.time)

    @property
    def current_action(self) -> Action | None:
        return self.actions[self.index] if 0 <= self.index < len(self.actions) else None

    def _advance_waypoints(self, action: Waypoints, pos: Point, now: float) -> None:
        """Move to the next point when this one is reached, or when the drone is nearer the next
        segment than this one (sparse reports can skip the arrival itself)."""
        points = action.points
        while self.waypoint < len(points) - 1:
            p = points[self.waypoint]
            reached = distance_m(pos[0], pos[1], p.lat, p.lon) <= self.acceptance_m
            here = self._segment_distance(action, self.waypoint, pos)
            following = self._segment_distance(action, self.waypoint + 1, pos)
            if not (reached or (here is not None and following is not None and following < here)):
                break
            self.waypoint += 1
            self.segment_started = now

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
        if k > 0:
            p = action.points[k - 1]
            return (p.lat, p.lon, p.alt)
        return self._previous_target()

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
        """The planned leg being flown, or the hover point while waiting at a sync step."""
        if waiting_sync is not None:
            k = max((i for i, a in enumerate(self.actions) if a.step == waiting_sync), default=-1)
            target = self._targets[k] if k >= 0 else None
            return Leg(waiting_sync, None, target, None) if target is not None else None
        action = self.current_action
        if action is None:
            return None
        if isinstance(action, Goto):
            return Leg(
                action.step,
                self._previous_target(),
                (action.lat, action.lon, action.alt),
                self._speed(action),
            )
        if isinstance(action, GoBy):
            return Leg(action.step, self._previous_target(), self._go_by_target(action), self._speed(action))
        if isinstance(action, Waypoints):
            p = action.points[self.waypoint]
            return Leg(
                action.step,
                self._waypoint_start(action, self.waypoint),
                (p.lat, p.lon, p.alt),
                self._speed(action),
            )
        return None

    def _go_by_target(self, action: GoBy) -> Point:
        """Offset from where the action started (as the agent computes it), else from the plan."""
        base = (
            self.step_start_pos if self.step_start_pos is not None else self._previous_target() or self.home
        )
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

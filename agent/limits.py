"""The agent's own limits on where its orders take the vehicle (pure: no I/O, no asyncio).

Each order alone can look harmless while the sum of them is not: 20 ``go_by`` legs of 9,999 m
end 200 km from home, 3 climbs of 499 m end 1.5 km above it. So the limits bound the vehicle's
*resulting state*: the orders are applied in sequence from where the vehicle is (or will be,
after what is already queued), and every place an order takes it to must stay within
``max_distance_from_home_m`` of home, between ``min_alt_m`` and ``max_alt_m`` relative to home,
and inside the geofence when one is installed. The first order that would cross a limit is
named with the numbers (:class:`Refusal`); the caller decides what happens to the rest
(agent/runtime.py: the orders before it fly, it and everything after it are refused).

Orders that end a flight are never refused for where they go: ``land`` here, and ``rtl`` (home
is where the limits are measured from); only an ``rtl`` altitude above the ceilings is.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from agent.config import SanityLimits
from protocol.actions import Action, GoBy, Goto, Hold, Land, ReturnToLaunch, Takeoff, Waypoints
from protocol.geo import distance_m, offset_latlon
from protocol.packets import Geofence


@dataclass(frozen=True, slots=True)
class Place:
    """Where the vehicle is or would be: ``lat``/``lon`` None while no position is known."""

    lat: float | None
    lon: float | None
    alt: float  # metres relative to home

    def moved_by(self, north: float, east: float, up: float) -> Place:
        if self.lat is None or self.lon is None:
            return Place(None, None, self.alt + up)
        lat, lon = offset_latlon(self.lat, self.lon, north, east)
        return Place(lat, lon, self.alt + up)


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why an order is refused. ``index`` is its position in the checked list (None: the batch)."""

    index: int | None
    step: int
    kind: str
    reason: str


def places(action: Action, start: Place, home: tuple[float, float] | None) -> list[Place]:
    """Every place ``action`` takes the vehicle to from ``start``, in order; the last is where it ends.

    Empty for orders that do not move it (``hold``, ``set_speed``).
    """
    if isinstance(action, Takeoff):
        return [Place(start.lat, start.lon, action.alt)]
    if isinstance(action, Goto):
        return [Place(action.lat, action.lon, action.alt)]
    if isinstance(action, GoBy):
        return [start.moved_by(action.north, action.east, action.up)]
    if isinstance(action, Waypoints):
        return [Place(p.lat, p.lon, p.alt) for p in action.points]
    if isinstance(action, Land):
        if action.lat is not None and action.lon is not None:
            return [Place(action.lat, action.lon, 0.0)]
        return [Place(start.lat, start.lon, 0.0)]
    if isinstance(action, ReturnToLaunch):
        return [Place(home[0], home[1], 0.0) if home else Place(None, None, 0.0)]
    return []


def project(actions: Iterable[Action], start: Place, home: tuple[float, float] | None) -> Place:
    """Where the vehicle ends after ``actions`` from ``start``, limits not applied."""
    place = start
    for action in actions:
        reached = places(action, place, home)
        if reached:
            place = reached[-1]
    return place


def _crossing(
    place: Place, limits: SanityLimits, home: tuple[float, float] | None, fence: Geofence | None
) -> str | None:
    """Which limit ``place`` is beyond, with the numbers, or None."""
    if place.alt > limits.max_alt_m:
        return f"{place.alt:.0f} m above home, beyond max_alt_m {limits.max_alt_m:g} m"
    if place.alt < limits.min_alt_m:
        return f"{-place.alt:.0f} m below home, beyond min_alt_m {limits.min_alt_m:g} m"
    if place.lat is None or place.lon is None:
        return None
    if home is not None:
        off = distance_m(home[0], home[1], place.lat, place.lon)
        if off > limits.max_distance_from_home_m:
            return (
                f"{off / 1000:.1f} km from home, beyond max_distance_from_home_m "
                f"{limits.max_distance_from_home_m:g} m"
            )
    if fence is not None:
        why = fence.violation(place.lat, place.lon, place.alt)
        if why is not None:
            return f"outside the geofence ({why})"
    return None


def _order_refusal(
    action: Action,
    start: Place,
    limits: SanityLimits,
    home: tuple[float, float] | None,
    fence: Geofence | None,
) -> str | None:
    """Why ``action`` from ``start`` is refused, or None."""
    if isinstance(action, Hold) and not limits.min_hold_s <= action.seconds <= limits.max_hold_s:
        return f"hold of {action.seconds:g} s outside {limits.min_hold_s:g}..{limits.max_hold_s:g} s"
    if isinstance(action, ReturnToLaunch):
        if action.alt is None:
            return None
        ceiling = min(limits.max_alt_m, fence.max_alt_m if fence and fence.max_alt_m else math.inf)
        if action.alt > ceiling:
            return f"return altitude {action.alt:g} m above the ceiling {ceiling:g} m (max_alt_m, geofence)"
        return None
    if isinstance(action, Land) and (action.lat is None or action.lon is None):
        return None  # landing where it is: never refused
    for number, place in enumerate(places(action, start, home)):
        why = _crossing(place, limits, home, fence)
        if why is not None:
            where = f"point {number + 1} would be" if isinstance(action, Waypoints) else "would end"
            return f"{where} {why}"
    return None


def first_crossing(
    actions: Sequence[Action],
    start: Place,
    limits: SanityLimits,
    home: tuple[float, float] | None,
    fence: Geofence | None = None,
) -> Refusal | None:
    """The first of ``actions`` (applied in order from ``start``) that would cross a limit, or None.

    ``home`` (lat, lon) is where horizontal distances are measured from; None (no home yet):
    distances unchecked, altitudes and the geofence still are. ``fence``: the installed geofence,
    ignored when ``limits.check_geofence`` is off.
    """
    if not limits.check_geofence:
        fence = None
    place = start
    for index, action in enumerate(actions):
        why = _order_refusal(action, place, limits, home, fence)
        if why is not None:
            return Refusal(index, action.step, action.kind, f"{action.kind} (step {action.step}) {why}")
        reached = places(action, place, home)
        if reached:
            place = reached[-1]
    return None


def queue_refusal(count: int, queued: int, limits: SanityLimits) -> Refusal | None:
    """A batch of ``count`` orders behind ``queued`` ones refused whole for the queue's length."""
    if queued + count > limits.max_queue_actions:
        return Refusal(
            None,
            -1,
            "queue",
            f"{queued + count} queued actions exceed max_queue_actions {limits.max_queue_actions}",
        )
    return None

"""Editing a running member's plan (pure): a re-tasked drone's new legs go in before its return.

Why a module of its own: the mission runner's plans are the truth its barriers, completion and
rejoin re-sends read (``ActiveMission.plans``), so an edit must keep their rules: steps only
grow (a step the agent reported done never names new work), the survey's barrier is kept, and
the return (RTL, or goto home and land) stays last with its layered altitude.
"""

from __future__ import annotations

from collections.abc import Sequence

from protocol.actions import MAX_WAYPOINTS_PER_ACTION, Action, Goto, Takeoff, Waypoint, Waypoints

LatLon = tuple[float, float]


def survey_points(plan: Sequence[Action]) -> list[LatLon]:
    """Every survey waypoint of a plan, in flying order."""
    return [(p.lat, p.lon) for a in plan if isinstance(a, Waypoints) for p in a.points]


def ready_step(plan: Sequence[Action]) -> int:
    """The step after which new legs may start: the plan's last survey (waypoints) action, else its
    last barrier, else its last step."""
    marks = [a.step for a in plan if isinstance(a, Waypoints)] or [a.step for a in plan if a.sync]
    return max(marks) if marks else max(a.step for a in plan)


def survey_alt(plan: Sequence[Action], default: float) -> float:
    """The height the plan surveys at (its last waypoint's), for legs flown in its place."""
    alts = [p.alt for a in plan if isinstance(a, Waypoints) for p in a.points]
    return alts[-1] if alts else default


def extend_plan(
    plan: Sequence[Action], points: Sequence[LatLon], alt: float, speed: float | None
) -> tuple[list[Action], list[Action], int]:
    """``plan`` with a survey leg over ``points`` flown after its own survey, before its return.

    Returns (the whole new plan, what to send the agent once it has done ``ready``, ``ready``).
    The new steps start above every step of the plan, with a takeoff: the receiver may be on
    its way home or down by the time the legs reach it (the agent's takeoff of an airborne drone
    is a climb to ``alt`` where it is). The return follows them.
    """
    ready = ready_step(plan)
    head = [a for a in plan if a.step <= ready]
    tail = [a for a in plan if a.step > ready]
    base = max(a.step for a in plan) + 1
    first = points[0]
    added: list[Action] = [  # the takeoff: airborne it only climbs to alt; landed by then, it flies again
        Takeoff(step=base, alt=alt),
        Goto(step=base + 1, lat=first[0], lon=first[1], alt=alt, speed=speed),
    ]
    chunks = [
        points[i : i + MAX_WAYPOINTS_PER_ACTION] for i in range(0, len(points), MAX_WAYPOINTS_PER_ACTION)
    ]
    for k, chunk in enumerate(chunks):
        added.append(
            Waypoints(
                step=base + 2 + k,
                points=[Waypoint(lat=a, lon=b, alt=alt) for a, b in chunk],
                speed=speed,
            )
        )
    after = base + 2 + len(chunks)
    tail = [a.model_copy(update={"step": after + i}) for i, a in enumerate(tail)]
    return head + added + tail, added + tail, ready

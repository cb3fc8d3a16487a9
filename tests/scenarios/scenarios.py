"""Scenario building blocks shared by the authority scenario tests and bench/bench_safety.py.

Missions that make the services meet (crossing legs, head-on pairs, a barrier one drone reaches
long before the other) and the ground-truth separation measure.
"""

from __future__ import annotations

import math

from gcs.api_planning import DroneInfo
from protocol.actions import Goto, Hold, Land, Takeoff
from protocol.taskfile import AgentPlan, TaskFile
from tests.cooperation.rig import HOME, Rig, at

H_MARGIN, V_MARGIN = 4.0, 2.0


def separation(truth: list[list[tuple[float, ...]]], since: int = 0) -> tuple[float, int]:
    """(min 3-D distance, samples with a pair inside the h x v cylinder), airborne pairs only."""
    closest, inside = math.inf, 0
    for row in truth[since:]:
        for i in range(len(row)):
            for j in range(i + 1, len(row)):
                a, b = row[i], row[j]
                if a[3] < 0.5 or b[3] < 0.5 or a[2] - HOME[2] < 0.5 or b[2] - HOME[2] < 0.5:
                    continue  # on (or at) the ground
                h = math.hypot(a[0] - b[0], a[1] - b[1])
                v = abs(a[2] - b[2])
                closest = min(closest, math.hypot(h, v))
                inside += h < H_MARGIN and v < V_MARGIN
    return closest, inside


def infos(r: Rig) -> list[DroneInfo]:
    out = []
    for name in r.names:
        session = r.daemon.agents.session(name)
        assert session is not None
        home = session.home
        assert home is not None
        out.append(DroneInfo(name=name, home=(home.lat, home.lon), status=session.status))
    return out


def area(north: float, east: float, size_n: float, size_e: float) -> list[tuple[float, float]]:
    return [
        at(north, east),
        at(north + size_n, east),
        at(north + size_n, east + size_e),
        at(north, east + size_e),
    ]


def crossing_task(names: list[str], alt: float = 12.0) -> TaskFile:
    """Each drone takes off, then flies long legs that cross the others' (room for holds)."""
    plans = []
    for k, name in enumerate(names):
        a, b = at(60, -40 + 25 * k), at(60 + 20 * k, 60 - 25 * k)
        plans.append(
            AgentPlan(
                agent=name,
                actions=[
                    Takeoff(step=0, alt=alt, sync=True),
                    Goto(step=1, lat=a[0], lon=a[1], alt=alt, speed=4.0),
                    Goto(step=2, lat=b[0], lon=b[1], alt=alt, speed=4.0),
                    Land(step=3),
                ],
            )
        )
    return TaskFile(name="crossing", plans=plans)


def head_on(names: list[str], alt: float = 10.0) -> TaskFile:
    east = 2.5
    south, north = at(-25.0, east), at(25.0, east)
    ends = [(south, north), (north, south)]
    return TaskFile(
        name="head-on",
        plans=[
            AgentPlan(
                agent=name,
                actions=[
                    Takeoff(step=0, alt=alt, sync=True),
                    Goto(step=1, lat=a[0], lon=a[1], alt=alt, speed=5.0, sync=True),
                    Goto(step=2, lat=b[0], lon=b[1], alt=alt, speed=5.0, sync=True),
                    Land(step=3),
                ],
            )
            for name, (a, b) in zip(names, ends, strict=True)
        ],
    )


def barrier_task(names: list[str]) -> TaskFile:
    """drone-1's leg to barrier 1 is short, drone-2's long: drone-1 waits there a while."""
    near, far = at(5.0, 0.0), at(80.0, 5.0)
    nxt = at(20.0, -20.0)
    legs = {names[0]: near, names[1]: far}
    return TaskFile(
        name="barrier",
        sync_timeout_s=300,
        plans=[
            AgentPlan(
                agent=name,
                actions=[
                    Takeoff(step=0, alt=8.0 + 4 * k, sync=True),
                    Goto(step=1, lat=legs[name][0], lon=legs[name][1], alt=8.0 + 4 * k, speed=3.0, sync=True),
                    Goto(step=2, lat=nxt[0] + 1e-4 * k, lon=nxt[1], alt=8.0 + 4 * k, speed=5.0),
                    Land(step=3),
                ],
            )
            for k, name in enumerate(names)
        ],
    )


def stack_task(names: list[str], hold_s: float = 200.0) -> TaskFile:
    """The drones hover in a vertical stack (8, 13, 18 m ...) over one point, then hold."""
    spot = at(30, 5)
    return TaskFile(
        name="stack",
        plans=[
            AgentPlan(
                agent=name,
                actions=[
                    Takeoff(step=0, alt=8.0 + 5 * k, sync=True),
                    Goto(step=1, lat=spot[0], lon=spot[1], alt=8.0 + 5 * k, speed=4.0, sync=True),
                    Hold(step=2, seconds=hold_s),
                    Land(step=3),
                ],
            )
            for k, name in enumerate(names)
        ],
    )

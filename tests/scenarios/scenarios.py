"""Scenario building blocks shared by the authority scenario tests and bench/bench_safety.py.

Missions that make the services meet (crossing legs, head-on pairs, a barrier one drone reaches
long before the other) and the ground-truth separation measure.
"""

from __future__ import annotations

import math
import time
from typing import Any

from gcs.http.planning_requests import DroneInfo
from protocol.actions import Goto, Hold, Land, Takeoff
from protocol.geo import distance_m
from protocol.taskfile import AgentPlan, TaskFile
from sitl.fleet import SimFleet
from tests.cooperation.rig import HOME, SPEEDUP, Rig, at, wait_for
from tests.faults.links import LinkRig

H_MARGIN, V_MARGIN = 4.0, 2.0
# Commands that ask for data, not movement: an agent keeps sending them while a pilot flies.
NOT_MOVING = frozenset({410, 511, 512, 519, 520})  # GET_HOME_POSITION, SET/REQUEST_MESSAGE, ...


def moving_commands(fleet: SimFleet, index: int, since: float) -> list[tuple[Any, ...]]:
    """What the agent's link asked of vehicle ``index`` that moves it, since sim time ``since``."""
    log = list(fleet.vehicle(index).command_log)
    return [e for e in log if e[0] >= since and e[1] == "gcs" and e[3] not in NOT_MOVING]


async def rtl_delivery(r: Rig, reason: str) -> dict[str, float]:
    """Operator RTL to all; wall seconds from the call until the first moving command of the
    return reaches each vehicle from its agent's link (the safety-order latency)."""
    since = r.fleet.sim_time
    started = time.monotonic()
    delivered, _ = await r.daemon.operator.bring_down("rtl", None, reason)
    assert sorted(delivered) == r.names, delivered
    reached: dict[str, float] = {}

    def all_reached() -> bool:
        for i, name in enumerate(r.names):
            if name not in reached and moving_commands(r.fleet, i, since):
                reached[name] = time.monotonic() - started
        return len(reached) == len(r.names)

    await wait_for(all_reached, 30, "the RTL at every vehicle", poll=0.01)
    return reached


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


async def outage_on_first_leg(r: Rig, links: LinkRig, name: str) -> float:
    """Stall ``name``'s daemon link for its profile's outage once it flies step 1; the wall seconds."""
    await wait_for(lambda: (s := r.status(name)) is not None and s.step == 1, 60, f"{name} on its leg")
    outage = links.profile.outage_wall_s(SPEEDUP)
    await links.proxies[name].partition_for(outage, "stall")
    return outage


def link_task(names: list[str]) -> TaskFile:
    """Take off, 40 m out, back, a short hover (they stay up for an RTL); every leg a barrier."""
    plans = []
    for k, name in enumerate(names):
        east, alt = 6.0 * k, 10.0 + 2 * k
        out, back = at(40.0, east), at(8.0, east)
        plans.append(
            AgentPlan(
                agent=name,
                actions=[
                    Takeoff(step=0, alt=alt, sync=True),
                    Goto(step=1, lat=out[0], lon=out[1], alt=alt, speed=6.0, sync=True),
                    Goto(step=2, lat=back[0], lon=back[1], alt=alt, speed=6.0, sync=True),
                    Hold(step=3, seconds=1.0),
                ],
            )
        )
    return TaskFile(name="link-legs", sync_timeout_s=300, plans=plans)


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


def legs_task(names: list[str]) -> TaskFile:
    """Three drones: take off, a 120 m leg out at 5 m/s, a leg back, land; every step a barrier."""
    plans = []
    for k, name in enumerate(names):
        east = 6.0 * k
        out, back = at(120.0, east), at(10.0, east)
        plans.append(
            AgentPlan(
                agent=name,
                actions=[
                    Takeoff(step=0, alt=10.0 + 2 * k, sync=True),
                    Goto(step=1, lat=out[0], lon=out[1], alt=10.0 + 2 * k, speed=5.0, sync=True),
                    Goto(step=2, lat=back[0], lon=back[1], alt=10.0 + 2 * k, speed=5.0, sync=True),
                    Land(step=3),
                ],
            )
        )
    return TaskFile(name="pilot-legs", plans=plans)


async def on_leg(r: Rig, name: str, metres: float) -> None:
    """Wait until ``name`` flies its first leg, ``metres`` out from its home."""
    home = r.daemon.agents.session(name).home  # type: ignore[union-attr]
    assert home is not None

    def out() -> bool:
        s = r.status(name)
        return bool(
            s
            and s.step == 1
            and s.position
            and distance_m(home.lat, home.lon, s.position.lat, s.position.lon) > metres
        )

    await wait_for(out, 60, f"{name} {metres:.0f} m into its leg")


def hover_task(name: str) -> TaskFile:
    """One drone: take off to 10 m and hover (a long hold), then land."""
    return TaskFile(
        name="pilot-hover",
        plans=[
            AgentPlan(
                agent=name, actions=[Takeoff(step=0, alt=10.0), Hold(step=1, seconds=300.0), Land(step=2)]
            )
        ],
    )


def refusals(r: Rig, name: str) -> list[str]:
    return [e.message for e in r.events("agent_exception", name) if "command_refused" in e.message]

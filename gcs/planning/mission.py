"""Turning planned paths into a fleetgcs task file (protocol.taskfile.TaskFile).

Every drone's plan has the same shape, so the sync steps match across agents by construction:

  step 0              takeoff to its transit altitude            (sync: all airborne)
  step 1              goto the first survey point
  steps 2 .. S        survey waypoints, split in legs of <= 2000 points;
                      the last leg is always at step S and syncs (all surveys done)
  step S+1            return: RTL, or goto home (S+1) and land (S+2)

A drone with no survey points holds for 0 s at step S so it still reaches the barrier.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from protocol.actions import (
    MAX_WAYPOINTS_PER_ACTION,
    Action,
    Goto,
    Hold,
    Land,
    ReturnToLaunch,
    Takeoff,
    Waypoint,
    Waypoints,
)
from protocol.taskfile import AgentPlan, SurveyArea, TaskFile

LatLon = tuple[float, float]


def _chunks(points: Sequence[LatLon], size: int) -> list[Sequence[LatLon]]:
    return [points[i : i + size] for i in range(0, len(points), size)]


def mission_from_paths(
    paths_latlon: Sequence[Sequence[LatLon]],
    alt: float,
    speed: float | None = None,
    agent_names: Sequence[str] | None = None,
    *,
    cids: Sequence[int] | None = None,
    homes_latlon: Sequence[LatLon] | None = None,
    return_mode: Literal["rtl", "land_home"] = "rtl",
    transit_alt_step: float = 0.0,
    name: str = "search",
    sync_timeout_s: float = 120.0,
    chunk: int = MAX_WAYPOINTS_PER_ACTION,
    survey: SurveyArea | None = None,
) -> TaskFile:
    """A validated :class:`TaskFile` flying ``paths_latlon[i]`` with agent ``i``.

    ``alt`` is the survey altitude (m above home); drone i transits at
    ``alt + i * transit_alt_step`` so transit legs of different drones are vertically separated.
    Agents are addressed by ``agent_names`` (default ``drone-1``...) or by ``cids``.
    ``return_mode="land_home"`` needs ``homes_latlon`` (goto home then land there).
    """
    n = len(paths_latlon)
    if n == 0:
        raise ValueError("no paths to fly")
    if cids is not None and len(cids) != n:
        raise ValueError("one cid per path")
    names = list(agent_names) if agent_names is not None else [f"drone-{i + 1}" for i in range(n)]
    if cids is None and len(names) != n:
        raise ValueError(f"{n} paths but {len(names)} agent names")
    if return_mode == "land_home" and (homes_latlon is None or len(homes_latlon) != n):
        raise ValueError("return_mode='land_home' needs one home per path")
    if not 0 < chunk <= MAX_WAYPOINTS_PER_ACTION:
        raise ValueError(f"chunk must be within 1..{MAX_WAYPOINTS_PER_ACTION}")
    legs = [_chunks(list(p), chunk) for p in paths_latlon]
    last = 1 + max(1, max(len(lg) for lg in legs))  # step S of the final (synced) survey leg
    plans = []
    for i, pts in enumerate(legs):
        transit = alt + i * transit_alt_step
        actions: list[Action] = [Takeoff(step=0, sync=True, alt=transit)]
        if pts:
            first = pts[0][0]
            actions.append(Goto(step=1, lat=first[0], lon=first[1], alt=transit, speed=speed))
            for k, leg in enumerate(pts):
                is_last = k == len(pts) - 1
                actions.append(
                    Waypoints(
                        step=last if is_last else 2 + k,
                        sync=is_last,
                        points=[Waypoint(lat=a, lon=b, alt=alt) for a, b in leg],
                        speed=speed,
                    )
                )
        else:
            actions.append(Hold(step=last, sync=True, seconds=0.0))
        if return_mode == "rtl":
            actions.append(ReturnToLaunch(step=last + 1))
        else:
            assert homes_latlon is not None
            h = homes_latlon[i]
            actions.append(Goto(step=last + 1, lat=h[0], lon=h[1], alt=transit, speed=speed))
            actions.append(Land(step=last + 2, lat=h[0], lon=h[1]))
        if cids is not None:
            plans.append(AgentPlan(cid=cids[i], actions=actions))
        else:
            plans.append(AgentPlan(agent=names[i], actions=actions))
    return TaskFile(name=name, sync_timeout_s=sync_timeout_s, plans=plans, survey=survey)

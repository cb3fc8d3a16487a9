"""PSA trajectories -> task file, with a barrier wherever the formation turns (every sub-step).

``gcs.planning.mission.mission_from_paths`` syncs only once at the end of the survey, which
would let a line formation drift apart at corners; here every leg of the common-knot trajectory
is one Waypoints action with the same step for every drone and ``sync=True``, so the daemon
holds the fleet together at each turn (the CoUAS synchronisation the paper relies on).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gcs.planning._psa_trajectory import FleetTrajectory
from gcs.planning.geodesy import LocalFrame
from protocol.actions import (
    MAX_WAYPOINTS_PER_ACTION,
    Action,
    Goto,
    Hold,
    Land,
    Takeoff,
    Waypoint,
    Waypoints,
)
from protocol.taskfile import AgentPlan, TaskFile


def _legs_latlon(trajectory: FleetTrajectory, frame: LocalFrame) -> list[list[list[tuple[float, float]]]]:
    """legs[leg][drone] = lat/lon points after the leg's first knot (consecutive repeats removed)."""
    flat = trajectory.positions.reshape(-1, 2)
    lat, lon = frame.to_geodetic(flat[:, 0], flat[:, 1])
    ll = np.stack([lat, lon], axis=-1).reshape(trajectory.positions.shape)
    out = []
    for first, last in trajectory.legs():
        leg = []
        for j in range(trajectory.drones):
            seg = trajectory.positions[j, first : last + 1]
            keep = [k for k in range(1, len(seg)) if np.any(np.abs(seg[k] - seg[k - 1]) > 1e-9)]
            pts = [(float(ll[j, first + k, 0]), float(ll[j, first + k, 1])) for k in keep]
            leg.append(pts or [(float(ll[j, last, 0]), float(ll[j, last, 1]))])
        out.append(leg)
    return out


# Seconds a drone holds (brakes) at the far end of an excursion before the barrier: long enough to
# stop from the ~3 m/s it still has at the acceptance radius (ArduCopter BRAKE decelerates hard).
STOP_BEFORE_REVERSAL_S = 0.5


def _reversals(trajectory: FleetTrajectory) -> set[int]:
    """Legs after which some drone flies back the way it came (the far end of an excursion).

    The agent completes a leg within its acceptance radius, still moving, so the last drone to
    reach such a barrier must first stop and turn while the others, long hovering, already fly:
    it lags its neighbours head-on along the formation line. A ``hold`` before the barrier stops
    every drone first, so the next leg starts from rest for all (``hold`` time is the agent's
    wall clock: a sped-up simulator stretches it, harmlessly).
    """
    out = set()
    for index, (_, last) in enumerate(trajectory.legs()[:-1]):
        into = trajectory.positions[:, last] - trajectory.positions[:, last - 1]
        onward = trajectory.positions[:, last + 1] - trajectory.positions[:, last]
        if np.any((into * onward).sum(axis=1) < -1e-9):
            out.add(index)
    return out


def psa_mission(
    trajectory: FleetTrajectory,
    frame: LocalFrame,
    alt: float,
    speed: float | None = None,
    names: Sequence[str] | None = None,
    name: str = "psa",
    assembly: FleetTrajectory | None = None,
    assembly_speeds: Sequence[Sequence[float]] | None = None,
) -> TaskFile:
    """Takeoff (sync) -> goto formation start (sync) -> one synced Waypoints per leg -> land.

    ``assembly`` and ``assembly_speeds[k][j]`` (from :func:`gcs.planning.psa.plan_assembly`)
    replace the single goto by one synced goto per assembly sub-step, timed so that every drone
    arrives together; without them all fly to the formation start at ``speed``.
    Every leg, formation-turn sub-steps included, ends at a barrier: within a leg all drones fly
    the same speed, which keeps the formation's shape only between barriers.
    """
    m = trajectory.drones
    labels = list(names) if names is not None else [f"drone-{j + 1}" for j in range(m)]
    plans: list[list[Action]] = [[Takeoff(step=0, sync=True, alt=alt)] for _ in range(m)]
    if assembly is not None and assembly_speeds is not None:
        knots = [assembly.positions[:, k] for k in range(1, assembly.positions.shape[1])]
        speeds: list[list[float | None]] = [list(map(float, row)) for row in assembly_speeds]
    else:
        knots = [trajectory.positions[:, 0]]
        speeds = [[speed] * m]
    step = 1
    for knot, row in zip(knots, speeds, strict=True):
        lat, lon = frame.to_geodetic(knot[:, 0], knot[:, 1])
        for j in range(m):
            plans[j].append(
                Goto(step=step, sync=True, lat=float(lat[j]), lon=float(lon[j]), alt=alt, speed=row[j])
            )
        step += 1
    stops = _reversals(trajectory)
    for index, leg in enumerate(_legs_latlon(trajectory, frame)):
        chunks = max(1, max(-(-len(p) // MAX_WAYPOINTS_PER_ACTION) for p in leg))
        stop = index in stops
        for c in range(chunks):
            for j in range(m):
                size = -(-len(leg[j]) // chunks)
                part = leg[j][c * size : (c + 1) * size] or leg[j][-1:]
                plans[j].append(
                    Waypoints(
                        step=step,
                        sync=c == chunks - 1 and not stop,
                        points=[Waypoint(lat=a, lon=b, alt=alt) for a, b in part],
                        speed=speed,
                    )
                )
            step += 1
        if stop:
            for j in range(m):
                plans[j].append(Hold(step=step, sync=True, seconds=STOP_BEFORE_REVERSAL_S))
            step += 1
    for j in range(m):
        plans[j].append(Land(step=step))
    return TaskFile(name=name, plans=[AgentPlan(agent=labels[j], actions=plans[j]) for j in range(m)])

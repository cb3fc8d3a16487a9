"""Independent checker of fleet plans: connectivity (eq. 3), coverage (eq. 5), speed (eq. 1).

The planner's own claims are not trusted: this re-derives every constraint from the timed
trajectories alone, so the tests and the daemon (before flying a plan) use the same verdict.
Connectivity is checked at every knot and at every ``sample_dt`` seconds in between; coverage is
exact (distance from each target to every flown segment).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from gcs.planning._psa_geometry import FloatArray
from gcs.planning._psa_trajectory import FleetTrajectory


@dataclass(frozen=True)
class Violation:
    """One broken constraint: what, when (seconds, or None) and a readable detail."""

    kind: str  # "connectivity" | "fleet-split" | "coverage" | "speed"
    time: float | None
    detail: str


@dataclass(frozen=True)
class PlanReport:
    """Verdict of :func:`check_plan`; ``ok`` when there is no violation at all."""

    violations: tuple[Violation, ...]
    samples: int
    max_neighbour_distance: float  # worst over time of each drone's nearest-drone distance
    max_target_miss: float  # worst distance from a target to the nearest flown segment
    lengths: tuple[float, ...] = field(default=())

    @property
    def ok(self) -> bool:
        return not self.violations

    def count(self, kind: str) -> int:
        return sum(1 for v in self.violations if v.kind == kind)


def _sample_times(trajectory: FleetTrajectory, sample_dt: float) -> FloatArray:
    t0, t1 = float(trajectory.times[0]), float(trajectory.times[-1])
    regular = np.arange(t0, t1, sample_dt) if sample_dt > 0 and t1 > t0 else np.zeros(0)
    return np.unique(np.concatenate([trajectory.times, regular, [t1]]))


def _connectivity(
    trajectory: FleetTrajectory, link_range: float, times: FloatArray, limit: int
) -> tuple[list[Violation], float]:
    pos = trajectory.at(times)  # (m, S, 2)
    m = pos.shape[0]
    if m < 2:
        return [], 0.0
    diff = pos[:, None, :, :] - pos[None, :, :, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])  # (m, m, S)
    idx = np.arange(m)
    dist[idx, idx, :] = np.inf
    nearest = dist.min(axis=1)  # (m, S)
    worst = float(nearest.max())
    out: list[Violation] = []
    tol = 1e-6 * max(1.0, link_range)
    for j, s in zip(*np.nonzero(nearest > link_range + tol), strict=True):
        if len(out) >= limit:
            break
        out.append(
            Violation(
                "connectivity", float(times[s]), f"drone {j} is {nearest[j, s]:.2f} m from its nearest drone"
            )
        )
    adjacency = dist <= link_range + tol
    # with three drones or fewer, "everyone has a neighbour" already means connected
    suspects = range(len(times)) if m > 3 else []
    if m <= 3:
        for s in np.flatnonzero((nearest > link_range + tol).any(axis=0))[:limit]:
            out.append(Violation("fleet-split", float(times[s]), "a drone is cut off from the fleet"))
    complete = adjacency.sum(axis=(0, 1)) == m * (m - 1)
    for s in suspects:
        if complete[s]:
            continue
        if len(out) >= 2 * limit:
            break
        n_comp, _ = connected_components(csr_matrix(adjacency[:, :, s]), directed=False)
        if n_comp > 1:
            out.append(Violation("fleet-split", float(times[s]), f"fleet splits into {n_comp} groups"))
    return out, worst


def _coverage(
    trajectory: FleetTrajectory, targets: FloatArray, visit_tol: float, limit: int
) -> tuple[list[Violation], float]:
    if not len(targets):
        return [], 0.0
    segs = []
    for j in range(trajectory.drones):
        p = trajectory.positions[j]
        keep = np.concatenate([[True], np.any(np.abs(np.diff(p, axis=0)) > 0, axis=1)])
        p = p[keep]
        if len(p) == 1:
            segs.extend(shapely.points(p[:1]))
        else:
            segs.extend(shapely.linestrings(np.stack([p[:-1], p[1:]], axis=1)))
    tree = shapely.STRtree(np.asarray(segs, dtype=object).ravel())
    pts = shapely.points(targets)
    _, dist = tree.query_nearest(pts, return_distance=True, all_matches=False)
    miss = np.full(len(targets), np.inf)
    # query_nearest returns one (input, tree) pair per point when all_matches is False
    miss[:] = dist
    out = [
        Violation(
            "coverage",
            None,
            f"target {i} at ({targets[i, 0]:.2f}, {targets[i, 1]:.2f}) missed by {miss[i]:.3f} m",
        )
        for i in np.flatnonzero(miss > visit_tol)[:limit]
    ]
    return out, float(miss.max())


def _speed(trajectory: FleetTrajectory, max_speed: float | None, limit: int) -> list[Violation]:
    if max_speed is None or len(trajectory.times) < 2:
        return []
    dt = np.diff(trajectory.times)
    step = np.hypot(*np.moveaxis(np.diff(trajectory.positions, axis=1), -1, 0))  # (m, K-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(dt > 0, step / dt, np.where(step > 0, np.inf, 0.0))
    bad = np.argwhere(v > max_speed * (1 + 1e-6))
    return [
        Violation("speed", float(trajectory.times[k]), f"drone {j} flies at {v[j, k]:.2f} m/s")
        for j, k in bad[:limit]
    ]


def check_plan(
    trajectory: FleetTrajectory,
    targets: FloatArray,
    link_range: float,
    *,
    sample_dt: float = 0.25,
    visit_tol: float = 0.05,
    max_speed: float | None = None,
    limit: int = 50,
) -> PlanReport:
    """Check eq. 3 (each drone within ``link_range`` of another), whole-fleet connectivity and eq. 5.

    ``visit_tol`` is how close (metres) a drone must pass to a target to count as visiting it;
    at most ``limit`` violations of each kind are listed.
    """
    times = _sample_times(trajectory, sample_dt)
    conn, worst = _connectivity(trajectory, link_range, times, limit)
    cov, miss = _coverage(trajectory, np.asarray(targets, dtype=float).reshape(-1, 2), visit_tol, limit)
    spd = _speed(trajectory, max_speed, limit)
    return PlanReport(
        violations=tuple(conn + cov + spd),
        samples=len(times),
        max_neighbour_distance=worst,
        max_target_miss=miss,
        lengths=tuple(float(x) for x in trajectory.lengths()),
    )

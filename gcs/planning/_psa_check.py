"""Independent checker of fleet plans: connectivity (eq. 3), coverage (eq. 5), speed (eq. 1), separation.

The planner's own claims are not trusted: this re-derives every constraint from the timed
trajectories alone, so the tests and the daemon (before flying a plan) use the same verdict.
Connectivity is checked at every knot and at every ``sample_dt`` seconds in between; coverage is
exact (distance from each target to every flown segment); separation is exact (closest approach
of every pair on every interval between knots). With ``flown_speed`` the time-dependent checks
run on the tracks as the task file flies them (:meth:`FleetTrajectory.flown`: one speed per leg,
barriers at sync knots), not on the planner's own timing.
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

    kind: str  # "connectivity" | "fleet-split" | "coverage" | "speed" | "separation"
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
    min_separation: float = float("inf")  # closest approach of any pair (exact), inf for one drone

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


def _separation(
    trajectory: FleetTrajectory, min_separation: float | None, limit: int
) -> tuple[list[Violation], float]:
    """Exact closest approach of every pair: each pair's offset is linear between two knots."""
    m = trajectory.drones
    if m < 2:
        return [], float("inf")
    jj, kk = np.triu_indices(m, 1)
    rel = trajectory.positions[jj] - trajectory.positions[kk]  # (P, K, 2)
    if rel.shape[1] == 1:
        dist = np.hypot(rel[:, 0, 0], rel[:, 0, 1])[:, None]
        when = np.zeros((len(jj), 1))
    else:
        a, d = rel[:, :-1], np.diff(rel, axis=1)
        dd = (d * d).sum(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(dd > 1e-18, np.clip(-(a * d).sum(-1) / dd, 0.0, 1.0), 0.0)
        closest = a + f[..., None] * d
        dist = np.hypot(closest[..., 0], closest[..., 1])  # (P, K-1)
        t = trajectory.times
        when = t[:-1][None, :] + f * np.diff(t)[None, :]
    worst = float(dist.min())
    out: list[Violation] = []
    if min_separation is not None:
        tol = 1e-6 * max(1.0, min_separation)
        for p, k in np.argwhere(dist < min_separation - tol)[:limit]:
            out.append(
                Violation(
                    "separation",
                    float(when[p, k]),
                    f"drones {jj[p]} and {kk[p]} {dist[p, k]:.2f} m apart (floor {min_separation:.2f} m)",
                )
            )
    return out, worst


def check_plan(
    trajectory: FleetTrajectory,
    targets: FloatArray,
    link_range: float,
    *,
    sample_dt: float = 0.25,
    visit_tol: float = 0.05,
    max_speed: float | None = None,
    limit: int = 50,
    min_separation: float | None = None,
    flown_speed: float | None = None,
) -> PlanReport:
    """Check eq. 3 (each drone within ``link_range`` of another), whole-fleet connectivity and eq. 5.

    ``visit_tol`` is how close (metres) a drone must pass to a target to count as visiting it;
    ``min_separation`` (metres) is the floor every pair must keep (collision margin);
    ``flown_speed`` checks connectivity, separation and speed on the tracks as the task file
    flies them at that speed rather than on the planner's timing. At most ``limit`` violations
    of each kind are listed.
    """
    timed = trajectory.flown(flown_speed) if flown_speed is not None else trajectory
    times = _sample_times(timed, sample_dt)
    conn, worst = _connectivity(timed, link_range, times, limit)
    sep, closest = _separation(timed, min_separation, limit)
    cov, miss = _coverage(trajectory, np.asarray(targets, dtype=float).reshape(-1, 2), visit_tol, limit)
    spd = _speed(timed, max_speed, limit)
    return PlanReport(
        violations=tuple(conn + sep + cov + spd),
        samples=len(times),
        max_neighbour_distance=worst,
        max_target_miss=miss,
        lengths=tuple(float(x) for x in trajectory.lengths()),
        min_separation=closest,
    )

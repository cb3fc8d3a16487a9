"""Timed fleet trajectories on common time knots, and a builder that moves a line formation.

All drones share the same knots and move linearly between them, so the position of every drone
at any instant is known exactly (what the checker samples) and every leg between two sync
knots becomes one task-file action per drone with the same step number.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gcs.planning._psa_geometry import FloatArray

MAX_PIVOT_STEP_RAD = np.pi / 2  # a formation turn larger than this is split so spacing stays >= w cos 45°
MAX_PIVOT_SUBSTEPS = 64  # bound on the split when the separation floor asks for smaller sub-steps


@dataclass(frozen=True)
class FleetTrajectory:
    """``positions[j, k]`` is drone j at ``times[k]``; ``sync[k]`` marks knots that end a leg."""

    times: FloatArray  # (K,)
    positions: FloatArray  # (m, K, 2)
    sync: np.ndarray  # (K,) bool
    labels: tuple[str, ...] = ()

    @property
    def drones(self) -> int:
        return int(self.positions.shape[0])

    def lengths(self) -> FloatArray:
        """Distance flown by each drone (metres)."""
        steps = np.diff(self.positions, axis=1)
        return np.asarray(np.hypot(steps[..., 0], steps[..., 1]).sum(axis=1), dtype=float)

    def at(self, t: FloatArray) -> FloatArray:
        """Positions (m, len(t), 2) at the instants ``t`` (clamped to the mission)."""
        tt = np.clip(np.asarray(t, dtype=float), self.times[0], self.times[-1])
        out = np.empty((self.drones, len(tt), 2))
        for j in range(self.drones):
            out[j, :, 0] = np.interp(tt, self.times, self.positions[j, :, 0])
            out[j, :, 1] = np.interp(tt, self.times, self.positions[j, :, 1])
        return out

    def legs(self) -> list[tuple[int, int]]:
        """(first, last) knot index of each leg; legs end at sync knots (and at the final knot)."""
        ends = [int(k) for k in np.flatnonzero(self.sync) if k > 0]
        if not ends or ends[-1] != len(self.times) - 1:
            ends.append(len(self.times) - 1)
        legs, first = [], 0
        for end in ends:
            if end > first:
                legs.append((first, end))
            first = end
        return legs

    def flown(self, speed: float) -> FleetTrajectory:
        """The tracks as the task file makes the agents fly them, on common time knots.

        Within a leg every drone flies its own polyline at the same ``speed`` (one speed per
        ``Waypoints`` action) and, once at the leg's end, hovers until the barrier releases
        the fleet; the next leg starts for everybody when the slowest arrives. The result is
        exact for that model (each drone is linear between the union of all drones' knot
        times), so the checker can sample it like a planned trajectory.
        """
        if speed <= 0:
            raise ValueError("speed must be positive")
        times: list[FloatArray] = [np.zeros(1)]
        chunks: list[FloatArray] = [self.positions[:, :1]]
        sync: list[FloatArray] = [np.ones(1, dtype=bool)]
        t0 = float(self.times[0])
        times[0] += t0
        for first, last in self.legs():
            seg = self.positions[:, first : last + 1]
            cum = np.concatenate(
                [
                    np.zeros((self.drones, 1)),
                    np.cumsum(np.hypot(*np.moveaxis(np.diff(seg, axis=1), -1, 0)), 1),
                ],
                axis=1,
            )
            total = cum[:, -1]
            duration = float(total.max()) / speed
            if duration <= 1e-6:
                sync[-1][-1] = True
                continue
            arrivals = np.unique(np.concatenate([cum.ravel() / speed, [duration]]))
            # knots closer than a microsecond are one knot (float noise would read as infinite speed)
            arrivals = arrivals[np.diff(np.concatenate([[0.0], arrivals])) > 1e-6]
            arrivals[-1] = duration
            out = np.empty((self.drones, len(arrivals), 2))
            for j in range(self.drones):
                keep = np.concatenate([[True], np.diff(cum[j]) > 1e-12])
                s = np.minimum(arrivals * speed, total[j])
                for axis in (0, 1):
                    out[j, :, axis] = np.interp(s, cum[j, keep], seg[j, keep, axis])
            leg_sync = np.zeros(len(arrivals), dtype=bool)
            leg_sync[-1] = True
            times.append(t0 + arrivals)
            chunks.append(out)
            sync.append(leg_sync)
            t0 += duration
        return FleetTrajectory(
            times=np.concatenate(times),
            positions=np.concatenate(chunks, axis=1),
            sync=np.concatenate(sync),
            labels=self.labels,
        )


@dataclass
class TrajectoryBuilder:
    """Appends synchronised moves; each move lasts as long as its longest displacement at ``speed``."""

    start: FloatArray  # (m, 2)
    speed: float
    _points: list[FloatArray] = field(default_factory=list)
    _times: list[float] = field(default_factory=list)
    _sync: list[bool] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._points = [np.asarray(self.start, dtype=float).copy()]
        self._times = [0.0]
        self._sync = [True]

    @property
    def current(self) -> FloatArray:
        return self._points[-1]

    def move_to(self, positions: FloatArray, sync: bool = False) -> None:
        """All drones fly straight to ``positions`` and arrive together; zero moves are dropped."""
        pos = np.asarray(positions, dtype=float)
        step = float(np.max(np.hypot(*(pos - self.current).T)))
        if step <= 1e-12:
            if sync:
                self._sync[-1] = True
            return
        self._points.append(pos.copy())
        self._times.append(self._times[-1] + step / self.speed)
        self._sync.append(sync)

    def mark_sync(self) -> None:
        """End the current leg here (a barrier in the task file)."""
        self._sync[-1] = True

    def build(self) -> FleetTrajectory:
        positions = np.stack(self._points, axis=1)
        return FleetTrajectory(
            times=np.asarray(self._times), positions=positions, sync=np.asarray(self._sync, dtype=bool)
        )


def formation(anchor: FloatArray, inward: FloatArray, spacing: float, drones: int) -> FloatArray:
    """Drone j at ``anchor + j * spacing * inward``: the evenly spaced line of the paper."""
    offsets = np.arange(drones, dtype=float)[:, None] * spacing
    return np.asarray(anchor, dtype=float)[None, :] + offsets * np.asarray(inward, dtype=float)[None, :]


def _substep_clearance(s0: float, a0: float, s1: float, a1: float) -> float:
    """Closest approach of two neighbours during one pivot sub-step flown at equal speed.

    Drone j's chord is ``j`` times drone 1's, and all chords are parallel, so at equal speed the
    offset between neighbours moves along the straight segment from ``s0 u(a0)`` to
    ``s1 u(a1)`` whatever the (shared) acceleration profile: its distance to the origin is the
    closest the pair gets (pairs further apart in the line get proportionally more).
    """
    a = s0 * np.array([np.cos(a0), np.sin(a0)])
    b = s1 * np.array([np.cos(a1), np.sin(a1)])
    d = b - a
    dd = float(d @ d)
    f = 0.0 if dd <= 1e-18 else min(max(-float(a @ d) / dd, 0.0), 1.0)
    return float(np.hypot(*(a + f * d)))


def pivot(
    builder: TrajectoryBuilder,
    anchor: FloatArray,
    n_from: FloatArray,
    n_to: FloatArray,
    spacing: float,
    spacing_to: float | None = None,
    min_separation: float = 0.0,
) -> float:
    """Turn the formation about its outer drone from inward ``-n_from`` to ``-n_to``.

    Also re-spaces it to ``spacing_to`` when given. Returns the distance the innermost drone flies
    (the turn's cost the paper leaves out). The turn goes in equal sub-steps of at most 90
    degrees, more when needed so that neighbours stay ``min_separation`` apart all along each
    sub-step; every sub-step ends at a sync knot (a barrier in the task file), because only
    within one straight sub-step do equal-speed drones keep the formation's shape.
    """
    drones = builder.current.shape[0]
    target = spacing if spacing_to is None else spacing_to
    a0 = float(np.arctan2(n_from[1], n_from[0]))
    delta = float(np.arctan2(n_to[1], n_to[0])) - a0
    delta = (delta + np.pi) % (2 * np.pi) - np.pi
    if abs(delta) < 1e-12 and abs(target - spacing) < 1e-12:
        return 0.0
    steps = max(1, int(np.ceil(abs(delta) / MAX_PIVOT_STEP_RAD - 1e-9)))

    def clear(n: int) -> bool:
        return all(
            _substep_clearance(
                spacing + (target - spacing) * (i - 1) / n,
                a0 + delta * (i - 1) / n,
                spacing + (target - spacing) * i / n,
                a0 + delta * i / n,
            )
            >= min_separation - 1e-9
            for i in range(1, n + 1)
        )

    while drones > 1 and not clear(steps):
        if steps >= MAX_PIVOT_SUBSTEPS:
            raise ValueError(
                f"a formation turn cannot keep neighbours {min_separation:.1f} m apart at spacing "
                f"{min(spacing, target):.1f} m"
            )
        steps += 1
    before = builder.current[-1].copy()
    cost = 0.0
    for i in range(1, steps + 1):
        ang = a0 + delta * i / steps
        normal = np.array([np.cos(ang), np.sin(ang)])
        builder.move_to(
            formation(anchor, -normal, spacing + (target - spacing) * i / steps, drones), sync=True
        )
        cost += float(np.hypot(*(builder.current[-1] - before)))
        before = builder.current[-1].copy()
    return cost

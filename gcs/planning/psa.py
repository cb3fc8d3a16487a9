"""Polygon-guided Scanning Algorithm (PSA, CoUAS seed 004, Algorithms 1-2, Theorem 1).

A line formation of ``m`` drones spaced ``w`` apart (width ``w_max = (m - 1) w``) flies round the
convex hull of the unvisited targets; targets within ``w_max`` of the hull (the ring ``R_k``) are
visited on scan lines perpendicular to the current edge by short excursions of the whole
formation; the rest are handled in later rounds on smaller hulls, joined by the transfer line
``c_1 ... c_K``. Pure function in a local metric frame; see docs/fleet-planners.md for the
places where this differs from the paper (excursions may go outward, formation turns are costed,
Theorem 1's bound is not a bound on the optimum).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import numpy as np

from gcs.planning._psa_check import PlanReport, check_plan
from gcs.planning._psa_geometry import (
    EPS,
    EdgeFrame,
    FloatArray,
    convex_hull,
    edge_frame,
    entry_parameter,
    locate,
)
from gcs.planning._psa_trajectory import FleetTrajectory, TrajectoryBuilder, formation, pivot

__all__ = [
    "Assembly",
    "FleetTrajectory",
    "PlanReport",
    "PsaCosts",
    "PsaInfeasible",
    "PsaPlan",
    "PsaRound",
    "check_plan",
    "plan_assembly",
    "plan_psa",
    "spacing_bounds",
]

SCAN_TOL = 1e-6  # targets closer than this along an edge share a scan line (the paper's F_s)
# The narrowest formation is this much wider than the separation floor, so that formation turns
# need sub-steps of at most 2 * arccos(1 / 1.0824) = 45 degrees (cos 22.5 degrees = 1 / 1.0824).
TURN_SPACING_FACTOR = 1.0 / float(np.cos(np.pi / 8))


# a flown leg starts up to the agent's acceptance radius (2 m) from its planned start; the library,
# the CLI's target files and the API all plan with this margin unless told otherwise
DEFAULT_TRACK_MARGIN_M = 2.0


class PsaInfeasible(ValueError):
    """The link range cannot hold both the connectivity bound and the separation floor."""


def spacing_bounds(link_range: float, min_separation: float, track_margin: float) -> tuple[float, float]:
    """(narrowest, widest) formation spacing for a link range, a separation floor and a track margin.

    Each flown track may stray ``track_margin`` from the plan, so neighbours must be planned at
    most ``w - 2 track_margin`` apart (connectivity) and at least ``min_separation + 2
    track_margin`` apart everywhere, turns included; the narrowest spacing leaves room for turns
    in 45-degree sub-steps. Raises :class:`PsaInfeasible` when the two bounds cross.
    """
    widest = link_range - 2.0 * track_margin
    floor = min_separation + 2.0 * track_margin
    narrowest = floor * TURN_SPACING_FACTOR
    if widest < narrowest - 1e-9 or widest <= 0:
        raise PsaInfeasible(
            f"PSA cannot keep neighbours within the link range w = {link_range:g} m and at least "
            f"{min_separation:g} m apart (collision margin) with {track_margin:g} m of tracking error: "
            f"it needs w >= {narrowest + 2.0 * track_margin:.1f} m, or a smaller separation or track margin"
        )
    return narrowest, widest


@dataclass(frozen=True)
class PsaRound:
    """One round: hull ``V_k``, the targets of ring ``R_k`` and where the round starts (``c_k``)."""

    hull: FloatArray
    targets: np.ndarray  # indices into the input points
    entry: FloatArray  # c_k
    perimeter: float  # L_k


@dataclass(frozen=True)
class PsaCosts:
    """The paper's accounting next to what the trajectories really cost (metres)."""

    round_lengths: tuple[float, ...]  # L_k, hull perimeters
    transfer: float  # L_trans = |c_1 c_K|
    scan_adjust: float  # sum of 2 L(F_s): the paper's L_adjust
    turn_adjust: float  # formation turns at corners and round entries (Remark 1 calls it negligible)
    fleet_length: float  # L_fleet = longest measured route

    @property
    def lower_bound(self) -> float:
        """Theorem 1's ``sum L_k + L_trans`` (not a true bound on the optimum, see the docs)."""
        return float(sum(self.round_lengths) + self.transfer)

    @property
    def adjust(self) -> float:
        """Honest ``L_adjust``: scan-line excursions plus formation turns."""
        return self.scan_adjust + self.turn_adjust


@dataclass(frozen=True)
class Assembly:
    """The flight from the homes to the formation start, in synchronised sub-steps.

    ``order[j]`` is the formation slot drone j takes; ``trajectory`` has one knot per sub-step
    (homes first, formation start last), every knot a barrier, and ``speeds[k, j]`` is drone j's
    speed on sub-step k: its distance over the sub-step's duration, so all drones arrive
    together and each pair's offset moves in a straight line within a sub-step. The sub-steps
    turn and stretch the homes' layout into the formation's about their centroid (a rigid
    rotation when both are lines) so neighbours never cut across each other.
    """

    homes: FloatArray  # (m, 2)
    order: np.ndarray  # (m,) int
    speeds: FloatArray  # (K, m)
    trajectory: FleetTrajectory  # K + 1 knots: homes ... formation start


MIN_ASSEMBLY_SPEED = 0.2  # m/s; a drone already at its slot still gets a valid speed
ASSEMBLY_ENUMERATE_UP_TO = 6  # drones: every slot order is tried up to this many (720 orders)
ASSEMBLY_STEP_RAD = np.pi / 8  # the layout turns at most 22.5 degrees per sub-step


def _pair_clearance(a: FloatArray, b: FloatArray) -> float:
    """Closest approach of any pair whose offsets move linearly from rows of ``a`` to rows of ``b``."""
    m = len(a)
    if m < 2:
        return float("inf")
    jj, kk = np.triu_indices(m, 1)
    ra, rb = a[jj] - a[kk], b[jj] - b[kk]
    d = rb - ra
    dd = (d * d).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(dd > 1e-18, np.clip(-(ra * d).sum(-1) / dd, 0.0, 1.0), 0.0)
    closest = ra + f[:, None] * d
    return float(np.hypot(closest[:, 0], closest[:, 1]).min())


def _assembly_knots(homes: FloatArray, target: FloatArray) -> list[FloatArray]:
    """Layouts from ``homes`` to ``target``: centroid moves straight, offsets turn and blend."""
    ch, ct = homes.mean(axis=0), target.mean(axis=0)
    h, f = homes - ch, target - ct
    phi = float(np.arctan2((h[:, 0] * f[:, 1] - h[:, 1] * f[:, 0]).sum(), (h * f).sum()))
    steps = max(1, int(np.ceil(abs(phi) / ASSEMBLY_STEP_RAD - 1e-9)))

    def rot(a: float) -> FloatArray:
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    back = f @ rot(-phi).T  # the formation's offsets turned back onto the homes' orientation
    knots = []
    for i in range(steps + 1):
        lam = i / steps
        offsets = ((1.0 - lam) * h + lam * back) @ rot(lam * phi).T
        knots.append((1.0 - lam) * ch + lam * ct + offsets)
    knots[0], knots[-1] = homes.copy(), target.copy()
    return knots


def plan_assembly(homes: FloatArray, start: FloatArray, speed: float) -> Assembly:
    """Assign formation slots to drones and time the assembly flight (see :class:`Assembly`).

    The order maximises the closest approach during the assembly, then minimises the longest
    flight; every order is tried for up to six drones, identity and reversed beyond.
    """
    homes = np.asarray(homes, dtype=float).reshape(-1, 2)
    start = np.asarray(start, dtype=float).reshape(-1, 2)
    m = len(start)
    if len(homes) != m:
        raise ValueError(f"{len(homes)} homes for {m} drones")
    orders: list[tuple[int, ...]] = (
        list(itertools.permutations(range(m)))
        if m <= ASSEMBLY_ENUMERATE_UP_TO
        else [tuple(range(m)), tuple(range(m - 1, -1, -1))]
    )
    best: tuple[float, float, tuple[int, ...]] | None = None
    best_knots: list[FloatArray] = []
    for o in orders:
        knots = _assembly_knots(homes, start[list(o)])
        clearance = min(_pair_clearance(a, b) for a, b in itertools.pairwise(knots))
        length = float(sum(np.hypot(*(b - a).T).max() for a, b in itertools.pairwise(knots)))
        key = (-round(clearance, 6), round(length, 6), o)
        if best is None or key < best:
            best, best_knots = key, knots
    assert best is not None
    times, speeds = [0.0], []
    for a, b in itertools.pairwise(best_knots):
        dist = np.hypot(*(b - a).T)
        duration = max(float(dist.max()) / speed, 1e-6)
        times.append(times[-1] + duration)
        speeds.append(np.clip(dist / duration, MIN_ASSEMBLY_SPEED, speed))
    traj = FleetTrajectory(
        times=np.asarray(times),
        positions=np.stack(best_knots, axis=1),
        sync=np.ones(len(times), dtype=bool),
    )
    return Assembly(homes=homes, order=np.asarray(best[2]), speeds=np.asarray(speeds), trajectory=traj)


@dataclass(frozen=True)
class PsaPlan:
    """Trajectories, rounds and costs of a PSA plan."""

    trajectory: FleetTrajectory
    rounds: tuple[PsaRound, ...]
    costs: PsaCosts
    link_range: float
    points: FloatArray = field(repr=False)
    speed: float = 4.0
    min_separation: float = 0.0
    track_margin: float = DEFAULT_TRACK_MARGIN_M
    assembly: Assembly | None = None

    def from_homes(self, homes: FloatArray) -> PsaPlan:
        """This plan with drone j flying from ``homes[j]``: slots assigned, assembly timed.

        The trajectory's rows are reordered so that row j is drone j's track.
        """
        assembly = plan_assembly(homes, self.trajectory.positions[:, 0], self.speed)
        traj = replace(self.trajectory, positions=self.trajectory.positions[assembly.order])
        return replace(self, trajectory=traj, assembly=assembly)

    @property
    def flown(self) -> FleetTrajectory:
        """The tracks as the task file flies them (equal speed per leg, a barrier at each sync knot)."""
        return self.trajectory.flown(self.speed)

    def check(self, sample_dt: float = 0.25) -> PlanReport:
        """Re-verify connectivity, separation and coverage on the tracks as they will be flown.

        The bounds are the planning ones (``w - 2 track_margin`` and ``min_separation + 2
        track_margin``), so any flight that stays within ``track_margin`` of its planned track
        keeps every nearest neighbour within ``w`` and every pair ``min_separation`` apart.
        """
        sep = self.min_separation + 2.0 * self.track_margin if self.trajectory.drones > 1 else None
        report = check_plan(
            self.trajectory,
            self.points,
            self.link_range - 2.0 * self.track_margin,
            sample_dt=sample_dt,
            min_separation=sep,
            flown_speed=self.speed,
            max_speed=self.speed,
        )
        if self.assembly is None:
            return report
        # The assembly starts from the real homes: checked against w and the bare separation.
        first = check_plan(
            self.assembly.trajectory,
            np.zeros((0, 2)),
            self.link_range,
            sample_dt=sample_dt,
            min_separation=self.min_separation if self.trajectory.drones > 1 else None,
        )
        return PlanReport(
            violations=first.violations + report.violations,
            samples=first.samples + report.samples,
            max_neighbour_distance=max(first.max_neighbour_distance, report.max_neighbour_distance),
            max_target_miss=report.max_target_miss,
            lengths=report.lengths,
            min_separation=min(first.min_separation, report.min_separation),
        )


def _split_rounds(points: FloatArray, w_max: float) -> list[tuple[FloatArray, np.ndarray]]:
    """Algorithm 1 lines 2-10: peel hulls; each round takes the targets within w_max of its hull."""
    remaining = np.arange(len(points))
    rounds = []
    while len(remaining):
        hull = convex_hull(points[remaining])
        if len(hull) == 1:
            rounds.append((hull, remaining))
            break
        depth, _, _ = locate(edge_frame(hull), points[remaining])
        inside = depth <= w_max + 1e-9
        rounds.append((hull, remaining[inside]))
        remaining = remaining[~inside]
    return rounds


def _transfer_points(hulls: list[FloatArray]) -> list[FloatArray]:
    """c_1 ... c_K: the shortest segment from a vertex of V_K to the outer boundary, cut by each hull."""
    inner = hulls[-1]
    if len(hulls) == 1 or len(hulls[0]) == 1:
        return [inner[0].copy()]
    outer = edge_frame(hulls[0])
    depth, edge, t = locate(outer, inner)
    best = int(np.argmin(depth))
    c_k = inner[best]
    c_1 = outer.point(int(edge[best]), float(t[best]))
    entries = [c_1]
    for hull in hulls[1:-1]:
        s = entry_parameter(edge_frame(hull), c_1, c_k)
        entries.append(c_1 + s * (c_k - c_1))
    entries.append(c_k.copy())
    return entries


def _edge_of(frame: EdgeFrame, point: FloatArray) -> tuple[int, float]:
    """The edge holding a boundary point (a vertex belongs to the edge it starts)."""
    for e in range(len(frame.length)):
        rel = point - frame.start[e]
        if abs(float(rel @ frame.normal[e])) <= 1e-6 * max(1.0, frame.length[e]):
            t = float(rel @ frame.direction[e])
            if -1e-6 <= t < frame.length[e] - 1e-9:
                return e, max(t, 0.0)
    _, edge, tt = locate(frame, point.reshape(1, 2))
    return int(edge[0]), float(tt[0])


def excursion_shifts(depths: FloatArray, spacing: float, drones: int) -> tuple[float, float]:
    """Smallest (outward a, inward b) shifts putting a drone on every target of one scan line.

    Drone j sits at depth j*spacing; shifting the formation inward by b covers residues
    [0, b] and outward by a covers [spacing - a, spacing). Choosing the largest gap between sorted
    residues as the uncovered part minimises a + b (the paper only flies inward, never cheaper).
    """
    if drones == 1 or spacing <= EPS:
        return 0.0, 0.0
    res = np.sort(np.clip(np.asarray(depths) - np.floor(np.asarray(depths) / spacing) * spacing, 0, spacing))
    res = res[(res > 1e-9) & (res < spacing - 1e-9)]
    if not len(res):
        return 0.0, 0.0
    knots = np.concatenate([[0.0], res, [spacing]])
    gap = int(np.argmax(np.diff(knots)))
    inward, outward_edge = float(knots[gap]), float(knots[gap + 1])
    return spacing - outward_edge, inward


@dataclass
class _RoundScanner:
    """Algorithm 2 for one ring: fly round the hull from the entry, excursions on scan lines."""

    builder: TrajectoryBuilder
    spacing: float
    drones: int
    link_range: float
    min_spacing: float
    min_separation: float = 0.0
    scan_cost: float = 0.0
    turn_cost: float = 0.0

    def ring_spacing(self, depth: FloatArray) -> float:
        """Narrow the formation to the ring's deepest target: turns cost less, links only get shorter."""
        if self.drones == 1:
            return self.link_range
        need = float(depth.max()) / (self.drones - 1) if len(depth) else 0.0
        return float(np.clip(need, min(self.min_spacing, self.link_range), self.link_range))

    def normal_now(self) -> FloatArray:
        pos = self.builder.current
        if self.drones == 1:
            return self._last_normal
        inward = pos[1] - pos[0]
        return np.asarray(-inward / max(float(np.hypot(*inward)), EPS), dtype=float)

    _last_normal: FloatArray = field(default_factory=lambda: np.array([0.0, 1.0]))

    def turn_to(self, anchor: FloatArray, normal: FloatArray, spacing: float | None = None) -> None:
        if self.drones > 1:
            old = self.spacing
            self.spacing = old if spacing is None else spacing
            self.turn_cost += pivot(
                self.builder, anchor, self.normal_now(), normal, old, self.spacing, self.min_separation
            )
        else:
            self.builder.move_to(anchor.reshape(1, 2))
        self._last_normal = normal
        self.builder.mark_sync()

    def fly_edge(
        self, frame: EdgeFrame, e: int, t_from: float, t_to: float, stops: list[tuple[float, FloatArray]]
    ) -> None:
        """Along edge e from t_from to t_to, stopping for excursions at scan lines ``stops``.

        Every excursion runs along the formation line, so each of its ends is a barrier: a drone
        that lags its neighbours there closes on them head-on (and the collision service sees a
        conflict), while a lag along the edge only stretches the line a little. The drones stop
        at both ends anyway (the excursion reverses), so the barriers cost almost nothing.
        """
        inward = -frame.normal[e]
        for t, depths in sorted(stops, key=lambda s: s[0]):
            base = formation(frame.point(e, t), inward, self.spacing, self.drones)
            self.builder.move_to(base)
            out, inn = excursion_shifts(depths, self.spacing, self.drones)
            for shift in (inn, -out):
                if shift > 0 or shift < 0:
                    self.builder.mark_sync()
                    self.builder.move_to(base + shift * inward, sync=True)
                    self.builder.move_to(base, sync=True)
                    self.scan_cost += 2.0 * abs(shift)
        self.builder.move_to(formation(frame.point(e, t_to), inward, self.spacing, self.drones))
        self.builder.mark_sync()

    def scan(self, hull: FloatArray, points: FloatArray, entry: FloatArray) -> None:
        frame = edge_frame(hull)
        h = len(frame.length)
        e0, t0 = _edge_of(frame, entry)
        depth, edge, tpos = (
            locate(frame, points) if len(points) else (np.zeros(0), np.zeros(0, int), np.zeros(0))
        )
        self.turn_to(entry, frame.normal[e0], self.ring_spacing(depth))
        groups: dict[int, list[tuple[float, FloatArray]]] = {}
        for e in range(h):
            sel = np.flatnonzero(edge == e)
            order = sel[np.argsort(tpos[sel])]
            lines: list[tuple[float, FloatArray]] = []
            for i in order:
                if lines and tpos[i] - lines[-1][0] <= SCAN_TOL:
                    lines[-1] = (lines[-1][0], np.append(lines[-1][1], depth[i]))
                else:
                    lines.append((float(tpos[i]), np.array([depth[i]])))
            groups[e] = lines
        first = [s for s in groups[e0] if s[0] >= t0 - SCAN_TOL]
        last = [s for s in groups[e0] if s[0] < t0 - SCAN_TOL]
        self.fly_edge(frame, e0, t0, float(frame.length[e0]), first)
        for k in range(1, h + 1):
            e = (e0 + k) % h
            self.turn_to(frame.start[e], frame.normal[e])
            if e == e0:
                self.fly_edge(frame, e, 0.0, t0, last)
            else:
                self.fly_edge(frame, e, 0.0, float(frame.length[e]), groups[e])


def plan_psa(
    points: FloatArray,
    drones: int,
    link_range: float,
    speed: float = 4.0,
    *,
    min_separation: float = 5.0,
    track_margin: float = DEFAULT_TRACK_MARGIN_M,
    adaptive_width: bool = True,
) -> PsaPlan:
    """Plan the fleet's timed trajectories visiting every target with a connected line formation.

    Neighbours are planned at most ``link_range - 2 track_margin`` apart and every pair at least
    ``min_separation + 2 track_margin`` apart at every instant of the flown tracks, formation
    turns included (default floor 5 m: the collision service's 4 m horizontal margin times its
    1.25 release factor; default track margin the agent's 2 m acceptance radius, as the CLI: with
    0 a plan certified at ``w`` is flown with neighbours up to ``w + 2 x`` the tracking error
    apart). ``adaptive_width`` narrows the formation to a ring's deepest target
    (never below what the separation floor needs); ``False`` flies the widest spacing.
    Raises :class:`PsaInfeasible` when the link range cannot satisfy both bounds.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) == 0:
        raise ValueError("PSA needs at least one target")
    if drones < 1 or link_range <= 0 or speed <= 0 or min_separation < 0 or track_margin < 0:
        raise ValueError("PSA needs drones >= 1, link_range > 0, speed > 0 and non-negative margins")
    if drones > 1:
        narrowest, widest = spacing_bounds(link_range, min_separation, track_margin)
    else:
        narrowest = widest = link_range
    floor_sep = min_separation + 2.0 * track_margin if drones > 1 else 0.0
    link_range_plan = widest
    w_max = (drones - 1) * widest
    split = _split_rounds(pts, w_max)
    hulls = [h for h, _ in split]
    entries = _transfer_points(hulls)
    first_frame = edge_frame(hulls[0]) if len(hulls[0]) > 1 else None
    normal0 = (
        first_frame.normal[_edge_of(first_frame, entries[0])[0]] if first_frame else np.array([0.0, 1.0])
    )
    floor = narrowest if adaptive_width else widest
    builder = TrajectoryBuilder(formation(entries[0], -normal0, widest, drones), speed)
    scanner = _RoundScanner(
        builder, widest, drones, link_range_plan, floor, min_separation=floor_sep, _last_normal=normal0
    )
    if first_frame is not None:  # start already at the first ring's width (no re-spacing cost)
        scanner.spacing = scanner.ring_spacing(locate(first_frame, pts[split[0][1]])[0])
        builder = TrajectoryBuilder(formation(entries[0], -normal0, scanner.spacing, drones), speed)
        scanner.builder = builder
    rounds = []
    for k, ((hull, idx), entry) in enumerate(zip(split, entries, strict=True)):
        if k > 0:  # transfer c_{k-1} -> c_k keeping the formation's shape
            builder.move_to(builder.current + (entry - entries[k - 1]), sync=True)
        perimeter = 0.0
        if len(hull) > 1:
            scanner.scan(hull, pts[idx], entry)
            perimeter = edge_frame(hull).perimeter
        rounds.append(PsaRound(hull=hull, targets=idx, entry=entry, perimeter=perimeter))
    trajectory = builder.build()
    costs = PsaCosts(
        round_lengths=tuple(r.perimeter for r in rounds),
        transfer=float(np.hypot(*(entries[-1] - entries[0]))),
        scan_adjust=scanner.scan_cost,
        turn_adjust=scanner.turn_cost,
        fleet_length=float(trajectory.lengths().max()),
    )
    return PsaPlan(
        trajectory=trajectory,
        rounds=tuple(rounds),
        costs=costs,
        link_range=link_range,
        points=pts,
        speed=speed,
        min_separation=min_separation if drones > 1 else 0.0,
        track_margin=track_margin,
    )

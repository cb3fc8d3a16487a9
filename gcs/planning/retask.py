"""Re-tasking a dropped drone's share (issue 27): what is left unseen of it, and who flies it.

A drone that leaves a survey (battery failsafe, lost link, pilot takeover, withdrawal) leaves
part of its share unflown. The decision is pure (no I/O, no clock), so it is unit-tested on
real numpy/shapely data and the daemon (gcs/missions/retask.py) only gathers its inputs:

1. The share is the dropped drone's planned survey path swept by the swath (the same eq. 5
   footprint that :mod:`gcs.planning.seen` rasterises the flown tracks with); its *gap* is the
   cells of the area inside that sweep the fleet has not seen.
2. The path is sampled every half cell; a sample is needed when it is the nearest sample of a
   gap cell. Runs of needed samples (joined over short seen stretches) are the legs to re-fly,
   in the order the dropped drone would have flown them: one route.
3. Path division: the route is cut into one contiguous piece per remaining drone, each piece
   to the drone nearest its start; a piece's cost is the extra way the drone flies (to the
   piece, along it, home from its end, minus the way home it had anyway) at its speed and
   power. Equal pieces first; if one drone's margin is short, pieces in proportion to the
   margins; if the whole fleet is short, "not feasible" with the numbers. Fewer drones are
   tried too; the fitting division with the least makespan plus total added time wins.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np
import shapely
from scipy.spatial import cKDTree
from shapely.geometry import LineString
from shapely.ops import substring

from gcs.planning.seen import SeenGrid, sweep

LatLon = tuple[float, float]
Verdict = Literal["proposed", "nothing_to_do", "not_feasible"]

MIN_GAP_PCT = 1.0  # a gap under this share of the dropped share is tracking noise, not a hole


@dataclass(frozen=True)
class Candidate:
    """A drone still flying the mission, as the decision needs it.

    ``start``: where its new legs would begin (the end of its own survey); ``margin_wh``: the
    energy it may spend beyond its own remaining plan and its reserve.
    """

    ident: str
    start: LatLon
    home: LatLon
    margin_wh: float
    speed_mps: float
    power_w: float


@dataclass(frozen=True)
class NewLeg:
    """One drone's added work: the survey points and what it costs beyond its own plan."""

    ident: str
    points: list[LatLon]
    survey_m: float
    extra_m: float  # flown in all beyond its own plan: to the leg, along it, and the longer way home
    time_s: float
    energy_wh: float
    margin_wh: float


@dataclass(frozen=True)
class RetaskProposal:
    """What to do about ``dropped``'s share: legs for the others, nothing, or why not."""

    verdict: Verdict
    reason: str
    dropped: str
    gap_m2: float
    share_m2: float
    legs: list[NewLeg] = field(default_factory=list)
    gap: dict[str, Any] = field(default_factory=lambda: {"type": "MultiPolygon", "coordinates": []})

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def share_gap(grid: SeenGrid, share: Sequence[LatLon], swath_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(share mask, gap mask) on ``grid``: the cells the path's swath covers inside the area, and
    those of them not seen."""
    mask = np.zeros_like(grid.seen)
    if len(share) > 0:
        pts = grid.frame.points_to_local([(float(a), float(b)) for a, b in share])
        sweep(mask, pts, np.full(len(pts), swath_m / 2.0), grid.x0, grid.y0, grid.cell_m)
    mask &= grid.inside
    return mask, mask & ~grid.seen


def gap_route(grid: SeenGrid, share: Sequence[LatLon], gap: np.ndarray, swath_m: float) -> LineString | None:
    """The part of the share's path (local metres) that sees the gap cells, as one route in flying
    order; seen stretches shorter than two swaths inside it are flown through."""
    if len(share) < 1 or not gap.any():
        return None
    xy = grid.frame.points_to_local([(float(a), float(b)) for a, b in share])
    line = LineString(xy) if len(xy) > 1 else LineString([xy[0], xy[0]])
    step = max(grid.cell_m / 2.0, 0.25)
    dist = np.arange(0.0, line.length + step, step).clip(max=line.length)
    samples = shapely.get_coordinates(shapely.line_interpolate_point(line, dist))
    rows, cols = np.nonzero(gap)
    centres = np.column_stack([grid.x0 + (cols + 0.5) * grid.cell_m, grid.y0 + (rows + 0.5) * grid.cell_m])
    _, nearest = cKDTree(samples).query(centres)
    needed = np.zeros(len(samples), dtype=bool)
    needed[nearest] = True
    idx = np.flatnonzero(needed)
    pad = swath_m / 2.0  # fly half a swath past the last gap cell's nearest sample, both ends
    start, end = max(0.0, dist[idx[0]] - pad), min(line.length, dist[idx[-1]] + pad)
    if end - start < step:
        end = min(line.length, start + step)
    return substring(line, start, end)


def _cost(c: Candidate, piece: LineString, grid: SeenGrid) -> tuple[float, float]:
    """(extra metres, survey metres) for ``c`` to fly ``piece`` before going home."""
    sx, sy = grid.frame.local_point(*c.start)
    hx, hy = grid.frame.local_point(*c.home)
    (ax, ay), (bx, by) = piece.coords[0], piece.coords[-1]
    there = math.hypot(ax - sx, ay - sy)
    back = math.hypot(hx - bx, hy - by)
    had = math.hypot(hx - sx, hy - sy)
    return max(0.0, there + piece.length + back - had), piece.length


def _assign(
    route: LineString, drones: Sequence[Candidate], weights: Sequence[float], grid: SeenGrid
) -> list[NewLeg]:
    """Cut ``route`` into pieces in proportion to ``weights``, each to the nearest free drone."""
    total = sum(weights)
    cuts = np.concatenate([[0.0], np.cumsum(weights) / total * route.length])
    free = list(drones)
    legs = []
    for k in range(len(weights)):
        piece = substring(route, float(cuts[k]), float(cuts[k + 1]))
        if piece.geom_type != "LineString" or len(piece.coords) < 2:
            continue
        a = piece.coords[0]
        best = min(free, key=lambda c: math.dist(grid.frame.local_point(*c.start), a))
        free.remove(best)
        extra, survey = _cost(best, piece, grid)
        time_s = extra / best.speed_mps
        lat, lon = grid.frame.to_geodetic(*np.asarray(piece.coords).T)
        legs.append(
            NewLeg(
                ident=best.ident,
                points=[(round(float(p), 7), round(float(q), 7)) for p, q in zip(lat, lon, strict=True)],
                survey_m=round(survey, 1),
                extra_m=round(extra, 1),
                time_s=round(time_s, 1),
                energy_wh=round(best.power_w * time_s / 3600.0, 2),
                margin_wh=round(best.margin_wh, 2),
            )
        )
    return legs


def _division(route: LineString, drones: list[Candidate], grid: SeenGrid) -> list[NewLeg] | None:
    """The feasible division with the best :func:`_score` over 1..n drones (best margins first)."""
    best: list[NewLeg] | None = None
    ranked = sorted(drones, key=lambda c: -c.margin_wh)
    for k in range(1, len(ranked) + 1):
        chosen = ranked[:k]
        for weights in ([1.0] * k, [c.margin_wh for c in chosen]):
            legs = _assign(route, chosen, weights, grid)
            if not legs or any(leg.energy_wh > leg.margin_wh for leg in legs):
                continue
            if best is None or _score(legs) < _score(best):
                best = legs
    return best


def _score(legs: list[NewLeg]) -> float:
    """Makespan plus the fleet's total added time: another drone joins only when it saves more
    time than its way to the gap costs (three drones converging on a small gap is worse)."""
    times = [g.time_s for g in legs]
    return max(times) + sum(times)


def propose_retask(
    grid: SeenGrid,
    dropped: str,
    share: Sequence[LatLon],
    swath_m: float,
    candidates: Sequence[Candidate],
    min_gap_pct: float = MIN_GAP_PCT,
) -> RetaskProposal:
    """Re-task ``dropped``'s unseen share (its planned survey path ``share``) onto ``candidates``.

    ``grid`` is what the fleet has seen so far (:func:`gcs.planning.seen.seen_grid`).
    """
    share_mask, gap = share_gap(grid, share, swath_m)
    cell2 = grid.cell_m**2
    share_m2, gap_m2 = float(share_mask.sum()) * cell2, float(gap.sum()) * cell2
    unseen = SeenGrid(grid.frame, grid.x0, grid.y0, grid.cell_m, gap, np.zeros_like(gap)).unseen_geojson()

    def verdict(v: Verdict, reason: str, legs: list[NewLeg] | None = None) -> RetaskProposal:
        return RetaskProposal(v, reason, dropped, round(gap_m2, 1), round(share_m2, 1), legs or [], unseen)

    if share_m2 == 0 or gap_m2 <= share_m2 * min_gap_pct / 100.0:
        return verdict(
            "nothing_to_do", f"{dropped}'s share is seen ({gap_m2:.0f} of {share_m2:.0f} m2 unseen)"
        )
    route = gap_route(grid, share, gap, swath_m)
    assert route is not None  # the gap has cells, so the route has samples
    drones = [c for c in candidates if c.margin_wh > 0 and c.speed_mps > 0]
    if not drones:
        return verdict(
            "not_feasible", f"no drone left in the mission has energy to spare for {gap_m2:.0f} m2"
        )
    legs = _division(route, drones, grid)
    if legs is None:
        need = min((sum(g.energy_wh for g in _assign(route, [c], [1.0], grid)), c.ident) for c in drones)
        spare = sum(c.margin_wh for c in drones)
        return verdict(
            "not_feasible",
            f"{route.length:.0f} m of {dropped}'s share left unseen: no division fits the margins "
            f"(alone, {need[1]} would need {need[0]:.1f} Wh; {spare:.1f} Wh spare in all)",
        )
    who = ", ".join(f"{g.ident} {g.survey_m:.0f} m" for g in legs)
    return verdict("proposed", f"{gap_m2:.0f} m2 of {dropped}'s share unseen: {who}", legs)

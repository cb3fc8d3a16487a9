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
4. Scattered gaps: when the gap is several disjoint zones, they are also planned as RSA pieces
   (:mod:`gcs.planning.scattered`: a covering rectangle and channels per zone) and divided by
   region: the pieces in the share's flying order are cut into contiguous groups (in proportion
   to the same weights), each group to the nearest free drone, which chains its pieces from its
   start (nearest entry next). Whichever of the two plans scores better is proposed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np
import shapely
from scipy.spatial import cKDTree
from shapely.geometry import LineString
from shapely.ops import substring

from gcs.planning._rsa_channels import polyline_length
from gcs.planning.scattered import Piece, chain, gap_pieces
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
    pieces: int = 1  # the gap's zones flown as separate RSA pieces (1: one route along the share)

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


def _leg(c: Candidate, path: np.ndarray, survey_m: float, grid: SeenGrid) -> NewLeg:
    """``c`` flies ``path`` (local metres, ``survey_m`` of it surveying) before going home: the
    extra way it flies (to the path, along it, home from its end, minus the way home it had)."""
    sx, sy = grid.frame.local_point(*c.start)
    hx, hy = grid.frame.local_point(*c.home)
    (ax, ay), (bx, by) = path[0], path[-1]
    there, back, had = (
        math.hypot(ax - sx, ay - sy),
        math.hypot(hx - bx, hy - by),
        math.hypot(hx - sx, hy - sy),
    )
    extra = max(0.0, there + polyline_length(path) + back - had)
    time_s = extra / c.speed_mps
    lat, lon = grid.frame.to_geodetic(*np.asarray(path).T)
    return NewLeg(
        ident=c.ident,
        points=[(round(float(p), 7), round(float(q), 7)) for p, q in zip(lat, lon, strict=True)],
        survey_m=round(survey_m, 1),
        extra_m=round(extra, 1),
        time_s=round(time_s, 1),
        energy_wh=round(c.power_w * time_s / 3600.0, 2),
        margin_wh=round(c.margin_wh, 2),
    )


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
        legs.append(_leg(best, np.asarray(piece.coords), piece.length, grid))
    return legs


def _assign_pieces(
    pieces: Sequence[Piece], drones: Sequence[Candidate], weights: Sequence[float], grid: SeenGrid
) -> list[NewLeg]:
    """Region division of scattered pieces: contiguous groups (in the share's flying order) of about
    ``weights``' share of the surveyed length each, each group to the nearest free drone."""
    quotas = np.cumsum(weights) / sum(weights) * sum(p.length for p in pieces)
    groups: list[list[Piece]] = [[] for _ in weights]
    done, k = 0.0, 0
    for piece in pieces:
        if groups[k] and done + piece.length / 2.0 > quotas[k] and k + 1 < len(groups):
            k += 1
        groups[k].append(piece)
        done += piece.length
    free = list(drones)
    legs = []
    for group in (g for g in groups if g):
        best = min(
            free,
            key=lambda c: min(
                math.dist(grid.frame.local_point(*c.start), o[0]) for p in group for o in p.options
            ),
        )
        free.remove(best)
        path, survey = chain(grid.frame.local_point(*best.start), group)
        legs.append(_leg(best, path, survey, grid))
    return legs


Assign = Callable[[Sequence[Candidate], Sequence[float]], list[NewLeg]]


def _division(assign: Assign, drones: list[Candidate]) -> list[NewLeg] | None:
    """The feasible division with the best :func:`_score` over 1..n drones (best margins first)."""
    best: list[NewLeg] | None = None
    ranked = sorted(drones, key=lambda c: -c.margin_wh)
    for k in range(1, len(ranked) + 1):
        chosen = ranked[:k]
        for weights in ([1.0] * k, [c.margin_wh for c in chosen]):
            legs = assign(chosen, weights)
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

    def verdict(v: Verdict, reason: str, legs: list[NewLeg] | None = None, pieces: int = 1) -> RetaskProposal:
        return RetaskProposal(
            v, reason, dropped, round(gap_m2, 1), round(share_m2, 1), legs or [], unseen, pieces
        )

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
    legs = _division(lambda chosen, weights: _assign(route, chosen, weights, grid), drones)
    pieces = (
        gap_pieces(grid, gap, LineString(grid.frame.points_to_local(list(share))), swath_m)
        if len(share) > 1
        else []
    )
    if len(pieces) > 1:  # scattered: the RSA pieces by region division, if they score better
        scattered = _division(lambda chosen, weights: _assign_pieces(pieces, chosen, weights, grid), drones)
        if scattered is not None and (legs is None or _score(scattered) < _score(legs)):
            who = ", ".join(f"{g.ident} {g.survey_m:.0f} m" for g in scattered)
            return verdict(
                "proposed",
                f"{gap_m2:.0f} m2 of {dropped}'s share unseen in {len(pieces)} pieces: {who}",
                scattered,
                len(pieces),
            )
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

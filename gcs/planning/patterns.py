"""Traversal patterns over a convex area: zigzag, spiral, segmented and wind-curved zigzag.

Seed 000 Alg. 2 (zigzag) and seed 001 Algs. 1-3 (spiral, segmented, curved), with fixes:

* lines are spread evenly (``ceil(H / step)`` lines, spacing ``H / n`` <= step, first and last half
  a spacing inside) instead of a fixed step with a squeezed last line;
* each line spans the polygon's extent over its whole strip ``y +- spacing/2``, not just the chord
  at ``y``, so corners between lines are inside the footprint (a chord-only path misses a wedge at
  every vertex that is wider than the line's own chord);
* spiral rings are true inward offsets (constant distance from the boundary), not the paper's
  per-axis scaling, which bunches the rings along slanted edges and whose ``floor(i / n)`` factor
  is always 0.

Every pattern returns a :class:`Sweep` in local metres. Pure functions, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import shapely
from numpy.typing import ArrayLike
from shapely.geometry import LineString, Polygon, box
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient

from gcs.planning.geodesy import FloatArray
from gcs.planning.polygon import centroid, convex_hull, min_height_rotation, rotate

TURN_THRESHOLD_DEG = 10.0
GRID_TOL_M = 1e-6  # rounding allowance of line_grid's height (metres)
STRIP_TOL_M = 1e-6  # rounding allowance of strip_extent's strip borders (metres)


@dataclass(frozen=True)
class Sweep:
    """A coverage path and what it is made of.

    ``lines`` (L, 2, 2) are the straight survey legs in flight order; ``points`` is the full
    waypoint sequence (legs plus the turns and transits joining them). ``angle`` (rad) is the
    rotation that made the legs horizontal: legs run along direction ``-angle`` from east.
    """

    pattern: str
    points: FloatArray
    lines: FloatArray
    step: float
    spacing: float
    angle: float
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def length(self) -> float:
        """Total path length in metres (legs, turns and transits)."""
        return path_length(self.points)

    @property
    def turns(self) -> int:
        """Heading changes sharper than TURN_THRESHOLD_DEG (collinear break points do not count)."""
        return count_turns(self.points)

    def summary(self) -> dict[str, Any]:
        """JSON-friendly metadata (no waypoints)."""
        return {
            "pattern": self.pattern,
            "length_m": round(self.length, 3),
            "turns": self.turns,
            "lines": len(self.lines),
            "waypoints": len(self.points),
            "step_m": self.step,
            "spacing_m": self.spacing,
            "angle_deg": math.degrees(self.angle),
            **self.meta,
        }


def path_length(points: ArrayLike) -> float:
    """Polyline length."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(p) < 2:
        return 0.0
    return float(np.hypot(*np.diff(p, axis=0).T).sum())


def count_turns(points: ArrayLike, threshold_deg: float = TURN_THRESHOLD_DEG) -> int:
    """Number of interior waypoints where the heading changes by more than ``threshold_deg``."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    d = np.diff(p, axis=0)
    d = d[np.hypot(d[:, 0], d[:, 1]) > 1e-9]
    if len(d) < 2:
        return 0
    h = np.arctan2(d[:, 1], d[:, 0])
    dh = np.abs((np.diff(h) + math.pi) % (2 * math.pi) - math.pi)
    return int(np.count_nonzero(dh > math.radians(threshold_deg)))


def swept_footprint(points: ArrayLike, half_width: float) -> BaseGeometry:
    """Ground seen by a footprint of half width ``half_width`` swept along the polyline.

    Unions per-segment buffers: GEOS buffers a self-retracing LineString (out-and-back legs)
    wrongly, so the path is never buffered as one line.
    """
    p = dedupe(points)
    if len(p) == 1:
        return shapely.Point(p[0]).buffer(half_width)
    segs = shapely.linestrings(np.stack([p[:-1], p[1:]], axis=1))
    return shapely.union_all(shapely.buffer(segs, half_width))


def dedupe(points: ArrayLike, tol: float = 1e-9) -> FloatArray:
    """Drop consecutive duplicate waypoints."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(p) == 0:
        return p
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.hypot(*np.diff(p, axis=0).T) > tol
    return p[keep]


def line_grid(ymin: float, ymax: float, step: float) -> tuple[FloatArray, float]:
    """Evenly spaced line ordinates: n = ceil(H/step) lines, spacing H/n, half a spacing inside."""
    if step <= 0:
        raise ValueError("step must be positive")
    height = ymax - ymin
    # a height that is a multiple of the step up to rounding (a lat/lon round trip leaves ~1e-8 m)
    # must not add a line: GRID_TOL_M of overrun is far below any footprint
    n = max(1, math.ceil((height - GRID_TOL_M) / step))
    spacing = height / n if height > 0 else step
    ys: FloatArray = ymin + spacing * (np.arange(n, dtype=float) + 0.5)
    return ys, spacing


def strip_extent(poly: Polygon, y: float, half: float) -> tuple[float, float] | None:
    """x-range of the polygon within the strip [y - half, y + half] (None if it misses)."""
    minx, _, maxx, _ = poly.bounds
    # the strip is shrunk by STRIP_TOL_M: a neighbouring part of the polygon that only touches a
    # border line up to rounding (an L's inner edge) is the next leg's, not a reason to fly 180 m
    # outside the area
    eps = min(STRIP_TOL_M, half * 1e-3)
    piece = poly.intersection(box(minx - 1.0, y - half + eps, maxx + 1.0, y + half - eps))
    if piece.is_empty or piece.area <= 1e-12 * max(poly.area, 1.0):
        return None
    x0, _, x1, _ = piece.bounds
    return float(x0), float(x1)


def strip_extents(poly: Polygon, ys: ArrayLike, half: float) -> list[tuple[float, float] | None]:
    """:func:`strip_extent` for every ordinate in ``ys``, in one vectorised intersection."""
    y = np.asarray(ys, dtype=float).reshape(-1)
    minx, _, maxx, _ = poly.bounds
    eps = min(STRIP_TOL_M, half * 1e-3)
    pieces = shapely.intersection(poly, shapely.box(minx - 1.0, y - half + eps, maxx + 1.0, y + half - eps))
    ok = ~shapely.is_empty(pieces) & (shapely.area(pieces) > 1e-12 * max(poly.area, 1.0))
    b = shapely.bounds(pieces)
    return [(float(b[i, 0]), float(b[i, 2])) if ok[i] else None for i in range(len(y))]


def chord_extent(poly: Polygon, y: float) -> tuple[float, float] | None:
    """x-range of the line at ordinate ``y`` inside the polygon (the paper's PolygonLineIntersect)."""
    minx, _, maxx, _ = poly.bounds
    cut = poly.intersection(LineString([(minx - 1.0, y), (maxx + 1.0, y)]))
    if cut.is_empty or cut.length <= 0:
        return None
    x0, _, x1, _ = cut.bounds
    return float(x0), float(x1)


def _boustrophedon(segments: list[tuple[float, float, float]], reverse_first: bool = False) -> FloatArray:
    """(y, x0, x1) legs to an (L, 2, 2) array flown alternately left-right / right-left."""
    lines = np.empty((len(segments), 2, 2))
    for k, (y, x0, x1) in enumerate(segments):
        if (k % 2 == 1) != reverse_first:
            x0, x1 = x1, x0
        lines[k] = [[x0, y], [x1, y]]
    return lines


def zigzag(
    vertices: ArrayLike,
    step: float,
    angle: float | None = None,
    *,
    extent: str = "strip",
    start: ArrayLike | None = None,
    check: bool = True,
) -> Sweep:
    """Zigzag over the convex hull of ``vertices`` (seed 000 Alg. 2, corrected).

    ``angle`` defaults to the exact minimum-height rotation (fewest legs, fewest turns).
    ``extent="chord"`` reproduces the paper's leg ends (for comparison only: it leaves corners
    uncovered). ``start`` picks, among the four corners of the pattern, the one whose path plus
    trip from ``start`` is shortest (the nearest one when the corners' paths are equally long).
    Leg ends are cut back where the turns see the area (:mod:`gcs.planning.turn_trim`);
    ``check=False`` skips that module's coverage check (a length estimate for comparing angles).
    """
    hull = convex_hull(vertices)
    if angle is None:
        angle, _ = min_height_rotation(hull)
    c = centroid(hull)
    q = Polygon(rotate(hull, angle, c))
    _, ymin, _, ymax = q.bounds
    ys, spacing = line_grid(ymin, ymax, step)
    segs: list[tuple[float, float, float]] = []
    exts = strip_extents(q, ys, spacing / 2) if extent == "strip" else [chord_extent(q, float(y)) for y in ys]
    for y, ext in zip(ys, exts, strict=True):
        if ext is None:
            continue
        segs.append((float(y), ext[0], ext[1]))
    if not segs:
        raise ValueError("polygon too small or degenerate for a zigzag")
    trim_to = q if extent == "strip" else None
    lines = _choose_start(segs, angle, c, start, trim_to, spacing / 2, step / 2, check)
    pts = dedupe(lines.reshape(-1, 2))
    return Sweep("zigzag", pts, lines, step, spacing, angle, {"extent": extent})


def _choose_start(
    segs: list[tuple[float, float, float]],
    angle: float,
    c: tuple[float, float],
    start: ArrayLike | None,
    trim_to: Polygon | None = None,
    half: float = 0.0,
    reach: float = 0.0,
    check: bool = True,
) -> FloatArray:
    """Lines in world coordinates from the corner whose path plus trip from ``start`` is shortest; with
    ``trim_to`` (the rotated polygon) leg ends next to a turn are cut back where the turn sees the
    area (:func:`gcs.planning.turn_trim.trim_at_turns`), which depends on the corner."""
    from gcs.planning.turn_trim import half_strip_extents, trim_at_turns

    options = []
    for bottom_up in (True, False):
        ordered = segs if bottom_up else segs[::-1]
        for rev in (False, True):
            options.append((ordered, rev))
    ys = [y for y, _, _ in segs]
    halves = None if trim_to is None else half_strip_extents(trim_to, ys, ys, half)

    def flown(i: int, checked: bool) -> FloatArray:
        ordered, rev = options[i]
        if trim_to is None or halves is None:
            return _boustrophedon(ordered, rev)
        hv = halves if i < 2 else halves[::-1]
        legs = [[leg] for leg in ordered]
        oys = ys if i < 2 else ys[::-1]
        return trim_at_turns(trim_to, legs, oys, half, not rev, reach, check=checked, halves=hv)

    # trimming depends on which ends turn: the corners give two path lengths (each flown both ways);
    # keep the shortest path plus the trip from ``start`` to its first point (first corner on ties)
    s = None if start is None else rotate(np.asarray(start, dtype=float).reshape(1, 2), angle, c)[0]
    costs = []
    for i in range(len(options) if s is not None else 2):  # without a start, reversing changes nothing
        lines = flown(i, False)
        trip = 0.0 if s is None else float(np.hypot(*(lines[0, 0] - s)))
        costs.append(trip + path_length(dedupe(lines.reshape(-1, 2))))
    k = next(i for i, v in enumerate(costs) if v <= min(costs) * (1.0 + 1e-9))
    lines = flown(k, check)
    return rotate(lines.reshape(-1, 2), -angle, c).reshape(-1, 2, 2)


def _inward_bisector_excursions(
    hull: FloatArray, ring: FloatArray, off: float, max_angle_deg: float
) -> FloatArray:
    """Ring 0 with out-and-back detours toward sharp hull corners, so the corners are seen.

    A ring ``off`` inside the boundary passes a corner of interior angle a at ``off / sin(a/2)``
    from it, more than the footprint's half width; flying to ``off`` from the corner along the
    bisector (to the corner itself below 60 degrees) brings the corner wedge inside the footprint.
    When the offset swallowed the corner's edge the detour starts at the ring vertex nearest to it.
    """
    n = len(hull)
    out = [p for p in ring]
    inserts: list[tuple[int, FloatArray]] = []
    for i in range(n):
        v, prv, nxt = hull[i], hull[i - 1], hull[(i + 1) % n]
        a = prv - v
        b = nxt - v
        a /= np.hypot(*a)
        b /= np.hypot(*b)
        alpha = math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0)))
        if math.degrees(alpha) >= max_angle_deg:
            continue
        u = a + b
        u /= np.hypot(*u)
        w = v + u * off / math.sin(alpha / 2)
        # the ring vertex of this corner; if the offset swallowed it, the ring vertex nearest to it
        j = int(np.argmin(np.hypot(*(ring - w).T)))
        e = v if alpha < math.radians(60.0) else v + u * off
        inserts.append((j, e))
    for j, e in sorted(inserts, key=lambda t: -t[0]):
        out[j + 1 : j + 1] = [e, ring[j].copy()]
    return np.asarray(out)


def spiral(
    vertices: ArrayLike, step: float, *, start: ArrayLike | None = None, corner_deg: float = 173.0
) -> Sweep:
    """Inward spiral over the convex hull (seed 001 Alg. 1, corrected).

    Ring k is the mitred inward offset at (k + 1/2) step, i.e. half a step inside the offset
    B_k at k step; every point shallower than B_k is within half a step of ring k-1, so only
    B_k's corners need care: a ring passes a corner of angle a at half a step / sin(a/2), so
    every corner leaves an unseen wedge; corners sharper than ``corner_deg`` (173 deg: wedges
    deeper than 0.1 % of a step) get an out-and-back detour (see
    :func:`_inward_bisector_excursions`). Each ring is flown counter-clockwise from the
    vertex nearest the previous ring's end. The core deeper than the last ring plus step/2
    (narrower than one step) is flown as one leg along its long axis, ending near the centre.
    """
    hull = convex_hull(vertices)
    poly = orient(Polygon(hull), 1.0)
    if step <= 0:
        raise ValueError("step must be positive")
    rings: list[FloatArray] = []
    outer = poly
    while True:
        inner = outer.buffer(-step / 2, join_style="mitre", mitre_limit=1e6)
        if inner.is_empty or inner.area <= 1e-9 * poly.area or inner.geom_type != "Polygon":
            break
        ring = np.asarray(orient(inner, 1.0).exterior.coords)[:-1]
        bverts = np.asarray(orient(outer, 1.0).exterior.coords)[:-1]
        rings.append(_inward_bisector_excursions(bverts, ring, step / 2, corner_deg))
        outer = outer.buffer(-step, join_style="mitre", mitre_limit=1e6)
        if outer.is_empty or outer.geom_type != "Polygon":
            break
    pts: list[FloatArray] = []
    cur = np.asarray(start, dtype=float).reshape(2) if start is not None else None
    for ring in rings:
        k = 0 if cur is None else int(np.argmin(np.hypot(*(ring - cur).T)))
        loop = np.vstack([ring[k:], ring[: k + 1]])
        pts.append(loop)
        cur = loop[-1]
    core = outer
    if not core.is_empty and core.area > 1e-9 * poly.area:
        parts = list(getattr(core, "geoms", [core]))
        for part in parts:
            leg = zigzag(np.asarray(part.exterior.coords)[:-1], step, start=cur).points
            pts.append(leg)
            cur = leg[-1]
    elif len(pts) == 0:
        cx, cy = centroid(hull)
        pts.append(np.array([[cx, cy]]))
    # patch pass: where an offset swallowed an edge (areas barely wider than one step) fly a leg
    # over each missed piece bigger than a hundredth of a step squared
    patches = 0
    seen = swept_footprint(np.vstack(pts), step / 2 * (1 + 1e-9))
    missed = poly.difference(seen)
    for piece in sorted(getattr(missed, "geoms", [missed]), key=lambda g: -g.area):
        if piece.is_empty or piece.area < 0.01 * step * step or piece.geom_type != "Polygon":
            continue
        leg = zigzag(np.asarray(piece.exterior.coords)[:-1], step, start=cur).points
        pts.append(leg)
        cur = leg[-1]
        patches += 1
    points = dedupe(np.vstack(pts))
    lines = np.stack([points[:-1], points[1:]], axis=1) if len(points) > 1 else np.empty((0, 2, 2))
    return Sweep("spiral", points, lines, step, step, 0.0, {"rings": len(rings), "patch_legs": patches})


def segmented(sweep: Sweep, segments: int) -> Sweep:
    """Seed 001 Alg. 2: split every leg into ``segments`` equal parts (S - 1 extra waypoints).

    Short legs between waypoints keep the autopilot near the line at speed (seed 000 §VI-A).
    """
    if segments < 1:
        raise ValueError("segments must be >= 1")
    pts: list[FloatArray] = []
    t = np.linspace(0.0, 1.0, segments + 1)[:, None]
    for a, b in sweep.lines:
        pts.append(a + t * (b - a))
    points = dedupe(np.vstack(pts))
    meta = {**sweep.meta, "segments": segments}
    return replace(sweep, pattern=f"segmented-{sweep.pattern}", points=points, meta=meta)


def curved(sweep: Sweep, shift: float, wind_from_deg: float | None = None, max_shift: float = 0.5) -> Sweep:
    """Seed 001 Alg. 3: bend every leg so its midpoint sits ``shift x spacing`` sideways, into the wind.

    As in the paper (q_y + S x Step in the rotated frame) every leg bends the same way: along the
    pattern's cross-track axis without wind, or upwind with ``wind_from_deg`` (meteorological:
    the direction the wind blows FROM, clockwise from north), scaled by how square the wind is
    to the legs. The bend is centred on the leg's line: its ends move back by half the offset
    and its midpoint forward by half, so the family of legs stays inside its strip. The paper
    allows |S| <= 2, which puts a midpoint on or past the next leg; we refuse |S| > ``max_shift``
    (default 0.5: at most half a spacing). Bending alone can open gaps where neighbouring legs
    differ in length; :func:`curved_cover` picks the line spacing that closes them.
    """
    if abs(shift) > max_shift:
        raise ValueError(f"|shift| = {abs(shift)} exceeds {max_shift} x step; curved legs would cross")
    if sweep.pattern.endswith("spiral"):
        raise ValueError("curved paths apply to zigzag legs, not to a spiral")
    # the rotated frame's +y axis in world coordinates: one side for every leg
    across = np.array([math.sin(sweep.angle), math.cos(sweep.angle)])
    if wind_from_deg is None:
        off = shift * sweep.spacing * across
    else:
        th = math.radians(wind_from_deg)
        up = np.array([math.sin(th), math.cos(th)])  # unit vector pointing to where the wind comes from
        off = abs(shift) * sweep.spacing * float(np.dot(up, across)) * across
    pts: list[FloatArray] = []
    for a, b in sweep.lines:
        if float(np.hypot(*(b - a))) < 1e-9:
            pts.append(np.array([a]))
            continue
        pts.append(np.array([a - off / 2, 0.5 * (a + b) + off / 2, b - off / 2]))
    points = dedupe(np.vstack(pts))
    meta = {**sweep.meta, "shift": shift, "wind_from_deg": wind_from_deg}
    return replace(sweep, pattern=f"curved-{sweep.pattern}", points=points, meta=meta)


BaseSweep = Callable[[FloatArray, float, float | None, FloatArray | None], Sweep]


def uncovered_area(vertices: ArrayLike, points: ArrayLike, half_width: float) -> float:
    """Area (m^2) of the polygon that a footprint of ``half_width`` swept along ``points`` misses."""
    poly = Polygon(np.asarray(vertices, dtype=float).reshape(-1, 2))
    if not poly.is_valid:
        poly = poly.buffer(0)
    seen = swept_footprint(points, half_width * (1 + 1e-9))
    return float(poly.difference(seen).area)


def curved_cover(
    vertices: ArrayLike,
    step: float,
    shift: float,
    wind_from_deg: float | None = None,
    *,
    angle: float | None = None,
    start: ArrayLike | None = None,
    base: BaseSweep | None = None,
    tries: int = 6,
) -> Sweep:
    """A curved zigzag whose legs, bent by ``shift``, still leave no point farther than step/2.

    Bending moves each leg's middle by up to ``|shift| x spacing`` relative to its neighbours
    when their lengths differ, so straight-line spacing is not enough. Lines ``step / (1 + |shift|)``
    apart always suffice (neighbours then lie at most ``step`` apart at every abscissa, and the
    outer legs within ``step / 2`` of the edges); wider spacings, from ``step`` down to that bound,
    are tried first and the first one whose plan covers the polygon is kept (checked with the
    swept footprint). ``base`` builds the straight legs (default :func:`zigzag`; concave areas
    pass the cell decomposition).
    """
    v = np.asarray(vertices, dtype=float).reshape(-1, 2)
    s = np.asarray(start, dtype=float).reshape(2) if start is not None else None

    def straight(vs: FloatArray, line_step: float, ang: float | None, st: FloatArray | None) -> Sweep:
        return zigzag(vs, line_step, ang, start=st)

    build = base or straight
    tol = 1e-8 * max(Polygon(v).area, 1.0)
    best: Sweep | None = None
    for i in range(max(tries, 1) + 1):
        line_step = step / (1.0 + abs(shift) * i / max(tries, 1))
        sweep = curved(build(v, line_step, angle, s), shift, wind_from_deg)
        best = sweep
        if abs(shift) < 1e-12 or uncovered_area(v, sweep.points, step / 2) <= tol:
            break
    assert best is not None
    return replace(best, step=step, meta={**best.meta, "line_step_m": round(best.spacing, 4)})

"""Rectangle-based Scheduling Algorithm (RSA, seed 002): re-search the missed zones of a grid map.

Steps: (1) label the 8-connected missed zones (scipy.ndimage.label does the paper's two-pass
relabelling exactly); (2) cover each zone with its exact minimum-area rotated rectangle, merging
zones whose rectangles touch; (3) channel sets per rectangle (``_rsa_channels``), chained by
nearest neighbour under the flight-distance budget ``d_flt``, which decides the number of drones;
(4) separated entry/exit lanes from the accessible side, at least ``d_sfty`` apart. Pure
functions in the map's metric frame (x along columns, y along rows northward).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import shapely
from numpy.typing import NDArray
from scipy import ndimage
from shapely.geometry import MultiPoint, Polygon

from gcs.planning._rsa_channels import FloatArray, channel_sets, polyline_length

Side = Literal["west", "east", "south", "north"]
EIGHT = np.ones((3, 3), dtype=bool)


class RsaError(ValueError):
    """The map cannot be scheduled under the given budget (the paper's assumption 4 fails)."""


@dataclass(frozen=True)
class MissedMap:
    """Grid of 1 (detected) / 0 (missed) cells; row 0 is the northernmost row.

    Cell (r, c) covers x in [c, c+1] * cell and y in [rows-1-r, rows-r] * cell of the map frame;
    ``origin_lat/lon`` is the map frame's (0, 0) (south-west corner) and ``rotation_deg`` turns
    the map's x axis counter-clockwise from east.
    """

    grid: NDArray[np.uint8]
    cell_size: float
    origin_lat: float = 0.0
    origin_lon: float = 0.0
    rotation_deg: float = 0.0

    @property
    def extent(self) -> tuple[float, float]:
        """Width (x) and height (y) of the map in metres."""
        return self.grid.shape[1] * self.cell_size, self.grid.shape[0] * self.cell_size

    def cell_centres(self, mask: NDArray[np.bool_]) -> FloatArray:
        """Map-frame centres of the cells where ``mask`` is true."""
        r, c = np.nonzero(mask)
        return np.column_stack([(c + 0.5) * self.cell_size, (self.grid.shape[0] - r - 0.5) * self.cell_size])

    def to_east_north(self, xy: FloatArray) -> FloatArray:
        """Map frame -> east/north metres from the origin (rotation applied)."""
        a = np.radians(self.rotation_deg)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        return np.asarray(xy, dtype=float) @ rot.T


@dataclass(frozen=True)
class Zone:
    """A (possibly merged) missed zone and its covering rectangle (4 vertices x1..x4)."""

    labels: tuple[int, ...]
    cells: int
    rectangle: FloatArray


@dataclass(frozen=True)
class RsaDrone:
    """One drone's schedule: full path (take-off spot ... landing spot) and its parts."""

    path: FloatArray
    zones: tuple[int, ...]
    entry_lane: FloatArray  # take-off spot -> lane end (on the entry channel)
    exit_lane: FloatArray  # lane start -> landing spot

    @property
    def length(self) -> float:
        return polyline_length(self.path)


@dataclass(frozen=True)
class RsaPlan:
    """Zones, rectangles and per-drone schedules; ``len(drones)`` is the number of UAVs needed."""

    zones: tuple[Zone, ...]
    drones: tuple[RsaDrone, ...]
    zone_count_before_merge: int


def label_zones(grid: NDArray[np.integer]) -> tuple[NDArray[np.int32], int]:
    """Step 1: 8-connected labels of the missed (0) cells; 0 means detected."""
    labels, n = ndimage.label(np.asarray(grid) == 0, structure=EIGHT)
    return labels.astype(np.int32), int(n)


def _hull_points(mask: NDArray[np.bool_], r0: int, c0: int, rows: int, cell: float) -> FloatArray:
    """Corners of each row's leftmost and rightmost cell: enough for the zone's convex hull."""
    rr = np.flatnonzero(mask.any(axis=1))
    sub = mask[rr]
    left = np.argmax(sub, axis=1)
    right = sub.shape[1] - 1 - np.argmax(sub[:, ::-1], axis=1)
    r = rr + r0
    y_top = (rows - r) * cell
    y_bot = y_top - cell
    xl = (left + c0) * cell
    xr = (right + c0 + 1) * cell
    return np.concatenate(
        [
            np.column_stack([xl, y_top]),
            np.column_stack([xl, y_bot]),
            np.column_stack([xr, y_top]),
            np.column_stack([xr, y_bot]),
        ]
    )


def _rectangle(points: FloatArray) -> FloatArray:
    """Exact minimum-area rotated rectangle (rotating calipers in shapely), as x1..x4."""
    rect = shapely.minimum_rotated_rectangle(MultiPoint(points))
    coords = np.asarray(rect.exterior.coords)[:4] if isinstance(rect, Polygon) else None
    if coords is None or len(coords) < 4:
        raise RsaError("a zone degenerated to a line; cells have positive size so this is a bug")
    return coords


def zone_rectangles(missed: MissedMap) -> tuple[list[Zone], int]:
    """Step 2: rectangle per zone; zones whose rectangles touch are merged and re-covered."""
    labels, n = label_zones(missed.grid)
    rows = missed.grid.shape[0]
    hulls: dict[int, FloatArray] = {}
    counts = np.bincount(labels.ravel(), minlength=n + 1)
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        mask = labels[sl] == lab
        pts = _hull_points(mask, sl[0].start, sl[1].start, rows, missed.cell_size)
        hulls[lab] = np.asarray(MultiPoint(pts).convex_hull.exterior.coords)[:-1]
    groups: list[tuple[tuple[int, ...], FloatArray, int]] = [
        ((lab,), hulls[lab], int(counts[lab])) for lab in sorted(hulls)
    ]
    rects = [_rectangle(h) for _, h, _ in groups]
    merged = True
    while merged and len(groups) > 1:
        merged = False
        polys = [Polygon(r) for r in rects]
        tree = shapely.STRtree(polys)
        for i, poly in enumerate(polys):
            hits = [int(j) for j in tree.query(poly, predicate="intersects") if j > i]
            if hits:
                j = hits[0]
                labs = groups[i][0] + groups[j][0]
                pts = np.vstack([groups[i][1], groups[j][1]])
                groups[i] = (labs, pts, groups[i][2] + groups[j][2])
                rects[i] = _rectangle(pts)
                del groups[j], rects[j]
                merged = True
                break
    zones = [Zone(labels=g[0], cells=g[2], rectangle=r) for g, r in zip(groups, rects, strict=True)]
    return zones, n


# --- accessible-side frame: u = distance from the side into the field, v = along the side ---


def _to_side(xy: FloatArray, side: Side, extent: tuple[float, float]) -> FloatArray:
    x, y = xy[..., 0], xy[..., 1]
    width, height = extent
    u, v = {"west": (x, y), "east": (width - x, y), "south": (y, x), "north": (height - y, x)}[side]
    return np.stack([u, v], axis=-1)


def _from_side(uv: FloatArray, side: Side, extent: tuple[float, float]) -> FloatArray:
    u, v = uv[..., 0], uv[..., 1]
    width, height = extent
    x, y = {"west": (u, v), "east": (width - u, v), "south": (v, u), "north": (v, height - u)}[side]
    return np.stack([x, y], axis=-1)


@dataclass(frozen=True)
class _Option:
    zone: int
    path: FloatArray  # side frame, in flying order
    length: float


def _options(zones: list[Zone], d_nbh: float, side: Side, extent: tuple[float, float]) -> list[_Option]:
    out = []
    for k, zone in enumerate(zones):
        for path in channel_sets(zone.rectangle, d_nbh):
            uv = _to_side(path, side, extent)
            for p in (uv, uv[::-1]):  # the paper's direction index h
                out.append(_Option(k, p, polyline_length(p)))
    return out


def chain(options: list[_Option], budget: float) -> list[list[_Option]]:
    """Step 3b (eqs. 13-18): per drone, nearest start to the side, then nearest neighbours in budget.

    A set is taken only when the flight so far, the hop, the set and the way back to the side
    (its end's distance u) all fit in ``budget``; the paper's eq. 17 checks the hop alone first.
    """
    left = {o.zone for o in options}
    for zone in left:
        if min(o.path[0, 0] + o.length + o.path[-1, 0] for o in options if o.zone == zone) > budget + 1e-9:
            raise RsaError(f"zone {zone} alone needs more than the flight budget {budget:.1f} m")
    drones: list[list[_Option]] = []
    while left:
        cands = [
            o for o in options if o.zone in left and o.path[0, 0] + o.length + o.path[-1, 0] <= budget + 1e-9
        ]
        first = min(cands, key=lambda o: o.path[0, 0])
        route, used = [first], first.path[0, 0] + first.length
        left.discard(first.zone)
        while left:
            here = route[-1].path[-1]
            best, best_d = None, np.inf
            for o in options:
                if o.zone not in left:
                    continue
                d = float(np.hypot(*(o.path[0] - here)))
                if d < best_d and used + d + o.length + o.path[-1, 0] <= budget + 1e-9:
                    best, best_d = o, d
            if best is None:
                break
            route.append(best)
            used += best_d + best.length
            left.discard(best.zone)
        drones.append(route)
    return drones


def separate_lanes(v: FloatArray, d_sfty: float) -> FloatArray:
    """Lane positions closest (least squares) to ``v`` with neighbours at least ``d_sfty`` apart.

    Isotonic regression (pool adjacent violators) of v_k - k d on the sorted order; this is the
    exact optimum of the paper's pairwise broadening of eqs. 20-21, for any number of clashes.
    """
    order = np.argsort(v, kind="stable")
    q = np.asarray(v, dtype=float)[order] - d_sfty * np.arange(len(v))
    blocks: list[list[float]] = []  # [sum, count]
    for x in q:
        blocks.append([x, 1.0])
        while len(blocks) > 1 and blocks[-2][0] / blocks[-2][1] > blocks[-1][0] / blocks[-1][1]:
            s, c = blocks.pop()
            blocks[-1][0] += s
            blocks[-1][1] += c
    fit = np.concatenate([[s / c] * int(c) for s, c in blocks])
    out = np.empty(len(v))
    out[order] = fit + d_sfty * np.arange(len(v))
    return out


def _assemble(
    routes: list[list[_Option]], d_sfty: float, standoff: float
) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
    """Step 4: take-off spot -> entry lane -> search sets -> exit lane -> landing spot (side frame)."""
    starts = np.array([r[0].path[0] for r in routes])
    ends = np.array([r[-1].path[-1] for r in routes])
    lane_in = separate_lanes(starts[:, 1], d_sfty)
    lane_out = separate_lanes(ends[:, 1], d_sfty)
    out = []
    for k, route in enumerate(routes):
        entry = np.array([[-standoff, lane_in[k]], [starts[k, 0], lane_in[k]]])
        exit_ = np.array([[ends[k, 0], lane_out[k]], [-standoff, lane_out[k]]])
        body = np.vstack([o.path for o in route])
        path = np.vstack([entry, body, exit_])
        keep = np.concatenate([[True], np.any(np.abs(np.diff(path, axis=0)) > 1e-9, axis=1)])
        out.append((path[keep], entry, exit_))
    return out


def plan_rsa(
    missed: MissedMap,
    d_nbh: float,
    d_flt: float,
    side: Side = "west",
    d_sfty: float = 5.0,
    standoff: float = 5.0,
) -> RsaPlan:
    """Schedule the re-search of every missed zone; the number of drones follows from ``d_flt``."""
    if d_nbh <= 0 or d_flt <= 0 or d_sfty < 0 or standoff < 0:
        raise RsaError("d_nbh and d_flt must be positive, d_sfty and standoff non-negative")
    zones, n_labels = zone_rectangles(missed)
    if not zones:
        return RsaPlan(zones=(), drones=(), zone_count_before_merge=0)
    extent = missed.extent
    options = _options(zones, d_nbh, side, extent)
    reserve = 2.0 * standoff
    for _ in range(30):  # lanes shifted for safety make paths longer: shrink the budget and redo
        routes = chain(options, d_flt - reserve)
        assembled = _assemble(routes, d_sfty, standoff)
        over = max(polyline_length(p) for p, _, _ in assembled) - d_flt
        if over <= 1e-6:
            break
        reserve += over
    else:
        raise RsaError("could not fit the safety lanes inside the flight budget")
    drones = tuple(
        RsaDrone(
            path=_from_side(p, side, extent),
            zones=tuple(o.zone for o in route),
            entry_lane=_from_side(e, side, extent),
            exit_lane=_from_side(x, side, extent),
        )
        for (p, e, x), route in zip(assembled, routes, strict=True)
    )
    return RsaPlan(zones=tuple(zones), drones=drones, zone_count_before_merge=n_labels)


def missed_map_from_coverage(
    area: Polygon, flown: list[FloatArray], swath: float, cell_size: float
) -> MissedMap:
    """Grid of a flown search's gaps: cells of ``area`` farther than swath/2 from every flown line.

    Map frame = the area's bounding box from its south-west corner; outside cells count as detected.
    """
    minx, miny, maxx, maxy = area.bounds
    cols = max(1, int(np.ceil((maxx - minx) / cell_size)))
    rows = max(1, int(np.ceil((maxy - miny) / cell_size)))
    xs = minx + (np.arange(cols) + 0.5) * cell_size
    ys = maxy - (np.arange(rows) + 0.5) * cell_size
    gx, gy = np.meshgrid(xs, ys)
    inside = shapely.contains_xy(area, gx, gy)
    seen = shapely.union_all([shapely.linestrings(p).buffer(swath / 2.0) for p in flown if len(p) > 1])
    covered = shapely.contains_xy(seen, gx, gy) if not seen.is_empty else np.zeros_like(inside)
    grid = np.where(inside & ~covered, 0, 1).astype(np.uint8)
    return MissedMap(grid=grid, cell_size=cell_size)

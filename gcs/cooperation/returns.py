"""Deconflicted returns and landings (pure): altitude layers and a landing order.

RTL-all on an autopilot flies every drone home at one altitude (ArduCopter: RTL_ALT), so drones
whose homes are a few metres apart cross and meet. Here each drone gets a *layer*: two drones
whose return legs (position -> home, horizontally) come within ``spacing`` of each other fly at
altitudes at least ``layer_step`` apart (greedy colouring of the conflict graph, nearest-home
drones lowest). At home a drone waits in its layer until it is *cleared to descend*: no other
airborne drone below it is within the horizontal margin of its descent column. The lowest waiting
drone is always cleared (nobody is below it), so the sequence always drains.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Point2 = tuple[float, float]
RETURN_PREFIX = "return-"
"""Mission ids of return programs: their sync points are the coordinator's, not a mission's."""


@dataclass(frozen=True)
class Returner:
    """One drone at the moment the return starts (local metres, altitude above its home)."""

    ident: str
    position: Point2
    alt: float
    home: Point2


@dataclass(frozen=True)
class ReturnPlan:
    ident: str
    layer: int
    alt: float  # transit altitude above home, metres


def segment_distance(a0: Point2, a1: Point2, b0: Point2, b1: Point2) -> float:
    """Smallest horizontal distance between segments a0-a1 and b0-b1."""
    if _segments_cross(a0, a1, b0, b1):
        return 0.0
    return min(
        _point_segment(a0, b0, b1),
        _point_segment(a1, b0, b1),
        _point_segment(b0, a0, a1),
        _point_segment(b1, a0, a1),
    )


def _point_segment(p: Point2, s0: Point2, s1: Point2) -> float:
    sx, sy = s1[0] - s0[0], s1[1] - s0[1]
    length2 = sx * sx + sy * sy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((p[0] - s0[0]) * sx + (p[1] - s0[1]) * sy) / length2))
    return math.hypot(p[0] - (s0[0] + t * sx), p[1] - (s0[1] + t * sy))


def _segments_cross(a0: Point2, a1: Point2, b0: Point2, b1: Point2) -> bool:
    def orient(p: Point2, q: Point2, r: Point2) -> float:
        return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])

    d1, d2 = orient(b0, b1, a0), orient(b0, b1, a1)
    d3, d4 = orient(a0, a1, b0), orient(a0, a1, b1)
    return (d1 * d2 < 0) and (d3 * d4 < 0)


def assign_layers(
    drones: list[Returner], spacing: float, base_alt: float, layer_step: float
) -> list[ReturnPlan]:
    """Transit altitudes: conflicting return legs get distinct layers (greedy graph colouring).

    The base layer is ``base_alt`` (or higher, so a drone never descends to return); drones
    nearest their home are coloured first and so get the lowest layers: they land first.
    Only legs whose bounding boxes come within ``spacing`` are compared (found for the whole
    fleet in a few vectorised passes): a fleet RTL of 2,000 drones is not two million leg
    pairs compared in Python on the event loop.
    """
    order = sorted(drones, key=lambda d: math.dist(d.position, d.home))
    earlier = _earlier_near(_leg_boxes(order, spacing))
    layers: list[int] = []
    for index, drone in enumerate(order):
        taken = {
            layers[other]
            for other in earlier[index]
            if segment_distance(drone.position, drone.home, order[other].position, order[other].home)
            < spacing
        }
        layers.append(next(k for k in range(len(drones) + 1) if k not in taken))
    by_ident = {drone.ident: layer for drone, layer in zip(order, layers, strict=True)}
    floor = max([base_alt, 0.0])
    return [ReturnPlan(d.ident, by_ident[d.ident], floor + by_ident[d.ident] * layer_step) for d in drones]


def _leg_boxes(drones: list[Returner], spacing: float) -> np.ndarray:
    """Each leg's bounding box grown by ``spacing`` (and a hair, against rounding): rows min x,
    max x, min y, max y. Two legs closer than ``spacing`` have overlapping grown boxes."""
    if not drones:
        return np.zeros((4, 0))
    legs = np.array([(*d.position, *d.home) for d in drones], dtype=float).reshape(-1, 4)
    grow = spacing + 1e-6 * (1.0 + float(np.abs(legs).max()))
    xs, ys = legs[:, 0::2], legs[:, 1::2]
    return np.stack(
        [xs.min(axis=1) - grow, xs.max(axis=1) + grow, ys.min(axis=1) - grow, ys.max(axis=1) + grow]
    )


def _earlier_near(boxes: np.ndarray, block: int = 512) -> list[list[int]]:
    """For each box, the earlier boxes (lower index, in index order) it overlaps."""
    count = boxes.shape[1]
    near: list[list[int]] = [[] for _ in range(count)]
    lo_x, hi_x, lo_y, hi_y = boxes
    index = np.arange(count)
    for start in range(0, count, block):
        stop = min(count, start + block)
        rows, cols = slice(start, stop), slice(0, stop - 1)  # only earlier boxes: a triangle
        hits = (
            (lo_x[None, cols] <= hi_x[rows, None])
            & (hi_x[None, cols] >= lo_x[rows, None])
            & (lo_y[None, cols] <= hi_y[rows, None])
            & (hi_y[None, cols] >= lo_y[rows, None])
            & (index[None, cols] < index[rows, None])
        )
        found_rows, found_cols = np.nonzero(hits)  # row-major: each row's columns ascending
        for row, col in zip((found_rows + start).tolist(), found_cols.tolist(), strict=True):
            near[row].append(col)
    return near


def spread_landing_spots(drones: list[Returner], plans: list[ReturnPlan], margin: float) -> dict[str, Point2]:
    """Where each drone lands when it lands where it is: no two spots within ``margin``.

    Lowest layer first keeps its spot; a later drone whose spot is too close to one already
    taken moves straight away from it (east if exactly above; points are local east/north metres)
    until clear: a drone stacked above another does not land on top of it. Spots taken are kept
    in a grid of ``margin`` cells, so each check looks at its 3x3 cells, not every spot (the first
    spot taken within ``margin`` is the one it moves away from, as a scan of every spot in order
    would find).
    """
    by_layer = sorted(zip(drones, plans, strict=True), key=lambda dp: (dp[1].alt, dp[0].ident))
    spots: dict[str, Point2] = {}
    grid: dict[tuple[int, int], list[tuple[int, Point2]]] = {}
    cell = margin if margin > 0 else 1.0
    for drone, _ in by_layer:
        spot = drone.position
        for _ in range(len(drones) * 4):  # bounded: each move clears one neighbour by the margin
            other = _first_near(grid, spot, margin, cell)
            if other is None:
                break
            dx, dy = spot[0] - other[0], spot[1] - other[1]
            norm = math.hypot(dx, dy)
            ux, uy = (dx / norm, dy / norm) if norm > 1e-6 else (1.0, 0.0)
            spot = (other[0] + ux * margin * 1.25, other[1] + uy * margin * 1.25)
        key = (math.floor(spot[0] / cell), math.floor(spot[1] / cell))
        grid.setdefault(key, []).append((len(spots), spot))
        spots[drone.ident] = spot
    return spots


def _first_near(
    grid: dict[tuple[int, int], list[tuple[int, Point2]]], spot: Point2, margin: float, cell: float
) -> Point2 | None:
    """The earliest-taken spot within ``margin`` of ``spot`` (None: clear)."""
    cx, cy = math.floor(spot[0] / cell), math.floor(spot[1] / cell)
    best: tuple[int, Point2] | None = None
    for gx in (cx - 1, cx, cx + 1):
        for gy in (cy - 1, cy, cy + 1):
            for order, taken in grid.get((gx, gy), ()):
                if (best is None or order < best[0]) and math.dist(taken, spot) < margin:
                    best = (order, taken)
    return best[1] if best is not None else None


@dataclass(frozen=True)
class Airborne:
    """A drone in the air during the return: where it is and where it is going (local metres)."""

    ident: str
    position: Point2
    alt: float  # above its home (homes are taken as one ground level)
    target: Point2


def cleared_to_descend(ident: str, column: Point2, alt: float, others: list[Airborne], margin: float) -> bool:
    """May the drone waiting at ``column`` (altitude ``alt``) descend now?

    Yes when no other airborne drone lower than it is, or will be on its way, within ``margin``
    of the column; drones above it do not matter (it moves away from them).
    """
    for other in others:
        if other.ident == ident or other.alt >= alt:
            continue
        if _point_segment(column, other.position, other.target) < margin:
            return False
    return True


def min_pairwise_distance(points: np.ndarray) -> float:
    """Smallest 3-D distance between any two rows of ``points`` (inf for fewer than two)."""
    if len(points) < 2:
        return math.inf
    diff = points[:, None, :] - points[None, :, :]
    dist = np.sqrt((diff**2).sum(axis=-1))
    dist[np.diag_indices(len(points))] = np.inf
    return float(dist.min())


__all__ = ["Airborne", "ReturnPlan", "Returner", "assign_layers", "cleared_to_descend", "segment_distance"]

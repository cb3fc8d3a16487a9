"""Scattered gaps of a dropped drone's share as RSA pieces (issue 27; RSA, seed 002).

When what is left unseen of a share is several disjoint pieces (the drone flew parts of it, or
the others saw parts), one route along the share from the first gap to the last flies every seen
stretch in between. Instead, as the Rectangle-based Scheduling Algorithm does for a missed map:

1. label the 8-connected gap cells (scipy.ndimage.label);
2. cover each zone with its minimum-area rotated rectangle (shapely), merging zones whose
   rectangles come within one swath of each other (flying across is cheaper than two entries);
3. each rectangle's RSA channel sets (:func:`gcs.planning._rsa_channels.channel_sets`, channels
   one swath apart, edge to edge, so every cell is within half a swath), both directions;
4. :func:`chain`: from a drone's start, the nearest channel set's entry next (nearest-neighbour
   chaining, RSA step 3), until its pieces are flown.

Pure: local metres of the seen grid's frame, no I/O. The division of the pieces among the drones
is in :mod:`gcs.planning.retask` (region division: contiguous groups in the share's flying order).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage
from shapely.geometry import LineString, MultiPoint, Polygon

from gcs.planning._rsa_channels import FloatArray, channel_sets, polyline_length
from gcs.planning.seen import SeenGrid

EIGHT = np.ones((3, 3), dtype=bool)
MAX_PIECES = 200  # more zones than this is noise over the whole share: one route serves it better


@dataclass(frozen=True)
class Piece:
    """One (possibly merged) gap zone: its covering rectangle and the channel paths that fly it."""

    rectangle: FloatArray  # 4 corners, local metres
    options: tuple[FloatArray, ...]  # channel polylines covering the rectangle, each way round
    cells: int
    order: float  # where along the dropped drone's share the zone lies (metres): its flying order

    @property
    def length(self) -> float:
        return min(polyline_length(o) for o in self.options)


def _corners(rows: np.ndarray, cols: np.ndarray, grid: SeenGrid) -> FloatArray:
    """Every corner of the given cells (local metres): their hull is the zone's hull."""
    x = grid.x0 + cols * grid.cell_m
    y = grid.y0 + rows * grid.cell_m
    c = grid.cell_m
    return np.concatenate(
        [
            np.column_stack([x, y]),
            np.column_stack([x + c, y]),
            np.column_stack([x, y + c]),
            np.column_stack([x + c, y + c]),
        ]
    )


def _rectangle(points: FloatArray) -> FloatArray:
    rect = shapely.minimum_rotated_rectangle(MultiPoint(points))
    assert isinstance(rect, Polygon), "cells have positive size, so their hull does"
    return np.asarray(rect.exterior.coords, dtype=float)[:4]


def gap_pieces(grid: SeenGrid, gap: np.ndarray, share: LineString, swath_m: float) -> list[Piece]:
    """The gap's zones as RSA pieces, in the share's flying order; [] when there are more than
    :data:`MAX_PIECES` zones (the caller flies one route then)."""
    labels, n = ndimage.label(gap, structure=EIGHT)
    if n == 0 or n > MAX_PIECES:
        return []
    groups: list[tuple[FloatArray, int]] = []
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        rows, cols = np.nonzero(labels[sl] == lab)
        pts = _corners(rows + sl[0].start, cols + sl[1].start, grid)
        groups.append((np.asarray(MultiPoint(pts).convex_hull.exterior.coords)[:-1], len(rows)))
    rects = [_rectangle(h) for h, _ in groups]
    for _ in range(len(groups)):  # each pass merges one pair or ends: at most n - 1 merges
        polys = [Polygon(r).buffer(swath_m / 2.0) for r in rects]
        tree = shapely.STRtree(polys)
        pair = next(
            (
                (i, int(j))
                for i, p in enumerate(polys)
                for j in tree.query(p, predicate="intersects")
                if j > i
            ),
            None,
        )
        if pair is None:
            break
        i, j = pair
        hull = np.vstack([groups[i][0], groups[j][0]])
        groups[i] = (hull, groups[i][1] + groups[j][1])
        rects[i] = _rectangle(hull)
        del groups[j], rects[j]
    pieces = []
    for (_, cells), rect in zip(groups, rects, strict=True):
        sets = channel_sets(rect, swath_m)
        options = tuple(p for s in sets for p in (s, s[::-1]))
        centre = shapely.Point(rect.mean(axis=0))
        pieces.append(Piece(rect, options, cells, float(share.project(centre))))
    return sorted(pieces, key=lambda p: p.order)


def chain(start: tuple[float, float], pieces: list[Piece]) -> tuple[FloatArray, float]:
    """Fly ``pieces`` from ``start``, always entering the nearest channel set next: (the path in
    local metres, its surveyed metres along the channels)."""
    here = np.asarray(start, dtype=float)
    left = list(range(len(pieces)))
    path: list[FloatArray] = []
    survey = 0.0
    for _ in range(len(pieces)):
        _, k, option = min(
            ((math.dist(here, o[0]), k, o) for k in left for o in pieces[k].options),
            key=lambda t: (t[0], t[1]),
        )
        path.append(option)
        survey += polyline_length(option)
        here = option[-1]
        left.remove(k)
    return np.vstack(path), survey

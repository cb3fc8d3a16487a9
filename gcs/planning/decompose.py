"""Concave areas without waste: boustrophedon cell decomposition (Choset), one zigzag per cell.

The papers fill the convex hull of a concave area, flying over everything the hull adds. Here the
actual polygon, rotated so sweep lines are horizontal, is cut at every vertex ordinate into
slab pieces (each meets any horizontal line in one interval); pieces joined one-to-one across
a slab boundary are merged into cells. All cells share one global line grid so adjacent cells'
legs line up; each leg spans its cell's extent over its strip, so every point of the area is
within half a spacing of a leg (same guarantee as :func:`gcs.planning.patterns.zigzag`).
Cells are visited greedily, nearest entry corner first; transits are straight (no-fly zones
are not modelled, so a transit may cross a notch outside the area).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import ArrayLike
from shapely.geometry import Point, Polygon, box
from shapely.geometry.base import BaseGeometry
from shapely.ops import unary_union

from gcs.planning.geodesy import FloatArray
from gcs.planning.patterns import (
    STRIP_TOL_M,
    Sweep,
    chord_extent,
    dedupe,
    line_grid,
    path_length,
    strip_extents,
    zigzag,
)
from gcs.planning.polygon import (
    PolygonType,
    centroid,
    classify,
    convex_hull,
    min_height_rotation,
    require_simple,
    rotate,
)
from gcs.planning.turn_trim import trim_at_turns

MAX_ANGLE_CANDIDATES = 8  # rotations tried by sweep_angle (the minimum-height one included)
ANGLE_VERTEX_BUDGET = 400  # candidates x vertices: 8 up to 50 vertices, 1 (minimum height) from 400
ANGLE_BIN_DEG = 1.0  # edge directions closer than this count as one candidate


def boustrophedon_cells(q: Polygon) -> list[Polygon]:
    """Cells of a simple polygon, in its own frame, each crossed by horizontal lines once."""
    minx, _, maxx, _ = q.bounds
    ys = np.unique(np.asarray(q.exterior.coords)[:, 1])
    pieces: list[list[Polygon]] = []
    for y0, y1 in itertools.pairwise(ys):
        cut = q.intersection(box(minx - 1, y0, maxx + 1, y1))
        parts = [g for g in getattr(cut, "geoms", [cut]) if g.geom_type == "Polygon" and g.area > 0]
        parts.sort(key=lambda g: g.bounds[0])
        pieces.append(parts)
    # union-find over (slab, index)
    ids = {(i, j): (i, j) for i, parts in enumerate(pieces) for j in range(len(parts))}

    def find(k: tuple[int, int]) -> tuple[int, int]:
        while ids[k] != k:
            ids[k] = ids[ids[k]]
            k = ids[k]
        return k

    for i in range(len(pieces) - 1):
        y = ys[i + 1]
        if not pieces[i] or not pieces[i + 1]:
            continue
        # (A, 2) x-ranges on the shared line
        tops = np.array([_edge_at(pa, y) for pa in pieces[i]])
        bots = np.array([_edge_at(pb, y) for pb in pieces[i + 1]])
        touch = np.minimum(tops[:, None, 1], bots[None, :, 1]) - np.maximum(
            tops[:, None, 0], bots[None, :, 0]
        )
        adj = touch > 1e-9
        ups, downs = adj.sum(axis=1), adj.sum(axis=0)
        for a in np.nonzero(ups == 1)[0]:
            b = int(np.argmax(adj[a]))
            if downs[b] == 1:
                ids[find((i + 1, b))] = find((i, int(a)))
    groups: dict[tuple[int, int], list[Polygon]] = {}
    for k in ids:
        groups.setdefault(find(k), []).append(pieces[k[0]][k[1]])
    cells: list[Polygon] = []
    for parts in groups.values():
        merged = unary_union(parts)
        cells.extend(g for g in getattr(merged, "geoms", [merged]) if g.geom_type == "Polygon")
    return cells


def _edge_at(piece: Polygon, y: float) -> tuple[float, float]:
    """x-range of the piece's boundary lying on the line ``y`` (its top or bottom edge)."""
    pts = np.asarray(piece.exterior.coords)
    on = pts[np.abs(pts[:, 1] - y) < 1e-9 * max(1.0, abs(y)), 0]
    if len(on) == 0:
        return (0.0, -1.0)
    return (float(on.min()), float(on.max()))


def cover_area(
    vertices: ArrayLike, step: float, angle: float | None = None, start: ArrayLike | None = None
) -> Sweep:
    """Zigzag every boustrophedon cell of the actual (possibly concave) area; meta compares to the hull.

    ``meta`` holds ``cells``, ``hull_length_m`` (the papers' hull zigzag) and ``area_m2`` /
    ``hull_area_m2``, so callers can report what decomposition saves.
    """
    p = require_simple(vertices)
    hull = convex_hull(p)
    if angle is None:
        angle = sweep_angle(p, step, concave=True)
    lines_w, spacing, n_cells = _cell_lines(p, step, angle, start)
    points = dedupe(lines_w.reshape(-1, 2))
    hull_sweep = zigzag(hull, step, angle)
    meta = {
        "cells": n_cells,
        "hull_length_m": round(hull_sweep.length, 3),
        "length_m_vs_hull": round(path_length(points) / hull_sweep.length, 4),
        "area_m2": round(Polygon(p).area, 3),
        "hull_area_m2": round(Polygon(hull).area, 3),
    }
    return Sweep("zigzag-cells", points, lines_w, step, spacing, angle, meta)


def candidate_angles(vertices: ArrayLike, limit: int = MAX_ANGLE_CANDIDATES) -> list[float]:
    """Sweep rotations worth trying: the hull's minimum-height one, then edge directions by total length.

    Legs along a long edge need no cut where that edge is (an L's arm), so the directions that carry
    the most boundary are the likely shortest; at most ``limit`` are returned, so planning time
    stays bounded on 1000-vertex areas.
    """
    p = np.asarray(vertices, dtype=float).reshape(-1, 2)
    first, _ = min_height_rotation(convex_hull(p))
    d = np.roll(p, -1, axis=0) - p
    lengths = np.hypot(d[:, 0], d[:, 1])
    ang = (-np.arctan2(d[:, 1], d[:, 0])) % math.pi  # rotation making each edge horizontal
    key = np.round(np.degrees(ang) / ANGLE_BIN_DEG).astype(int) % round(180 / ANGLE_BIN_DEG)
    totals = np.bincount(key, weights=lengths)
    out = [first]
    for k in np.argsort(-totals):
        if totals[k] <= 0 or len(out) >= limit:
            break
        members = key == k
        a = float(ang[members][np.argmax(lengths[members])])  # the longest edge's exact direction
        if all(
            abs((a - b + math.pi / 2) % math.pi - math.pi / 2) > math.radians(ANGLE_BIN_DEG / 2) for b in out
        ):
            out.append(a)
    return out


def sweep_angle(vertices: ArrayLike, step: float, *, concave: bool | None = None) -> float:
    """The candidate rotation whose legs, turns and cell transits are shortest when flown.

    The hull's minimum width gives the fewest legs over the hull, not the shortest path over a
    concave area (an L cut into three cells, 4,363 m, where legs along an arm fly one cell,
    3,160 m); ties keep the minimum-height angle (fewest turns).
    """
    p = require_simple(vertices)
    # each candidate costs a whole decomposition (quadratic in vertices): bound the total work
    cands = candidate_angles(p, max(1, min(MAX_ANGLE_CANDIDATES, ANGLE_VERTEX_BUDGET // len(p))))
    if len(cands) == 1:
        return cands[0]
    if concave is None:
        concave = classify(p) == PolygonType.CONCAVE

    def flown_length(a: float, check: bool) -> float:
        if concave:
            lines, _, _ = _cell_lines(p, step, a, None, check=check)
            return path_length(dedupe(lines.reshape(-1, 2)))
        return zigzag(p, step, a, check=check).length

    # compare by the trimmed length unchecked (cheap; a cut the check gives back only lengthens the
    # path, by the triangle inequality), then check in that order until no estimate is below the
    # best checked length, so the checked shortest is found (usually after one check)
    est = [flown_length(a, False) for a in cands]
    order = sorted(range(len(cands)), key=lambda i: (est[i], i))
    best, best_len = cands[order[0]], math.inf
    for i in order:
        if est[i] >= best_len * (1.0 - 1e-9):
            break
        length = flown_length(cands[i], True)
        if length < best_len * (1.0 - 1e-9):
            best, best_len = cands[i], length
    return best


Piece = tuple[float, float, float]  # (y, x0, x1): a straight part of a leg, x0 <= x1


def leg_pieces(cell: Polygon, y: float, strip_y: float, half: float, ext: tuple[float, float]) -> list[Piece]:
    """One leg as straight pieces, left to right: the chord at ``y``, then each end beyond the chord.

    The strip rule spans the cell's extent over ``strip_y +- half``; where that extent reaches past
    the chord at ``y`` only because the cell is wider higher or lower in the strip (an L's arm
    ending just inside the strip), flying on at ``y`` would be outside the area for the whole
    excess (180 m on an L-shaped field). Instead, what lies within ``half`` of the chord's end is
    already seen from it; the rest is flown at ``y`` clamped into that rest's ordinates: it lies
    in the strip on one side of ``y``, so every point of it stays within ``half`` of the piece.
    """
    chord = chord_extent(cell, y)
    if chord is None:
        return [(y, ext[0], ext[1])]
    # up to the turn margin (half a spacing) past the chord, the leg is flown straight
    lo = ext[0] if chord[0] - ext[0] <= half else chord[0]
    hi = ext[1] if ext[1] - chord[1] <= half else chord[1]
    left = None if lo == ext[0] else _excess(cell, y, strip_y, half, (ext[0], lo), lo)
    right = None if hi == ext[1] else _excess(cell, y, strip_y, half, (hi, ext[1]), hi)
    if left is not None and abs(left[0] - y) <= 1e-9:
        lo, left = left[1], None
    if right is not None and abs(right[0] - y) <= 1e-9:
        hi, right = right[2], None
    return [p for p in (left, (y, lo, hi), right) if p is not None]


def _excess(
    cell: Polygon, y: float, strip_y: float, half: float, span: tuple[float, float], end: float
) -> Piece | None:
    """The piece flying a leg's excess over ``span`` (None: all of it is seen from the chord's ``end``)."""
    eps = min(STRIP_TOL_M, half * 1e-3)
    part = cell.intersection(box(span[0], strip_y - half + eps, span[1], strip_y + half - eps))
    # the inscribed polygon of the disc is slightly smaller than the disc: never drops an unseen point
    rest = part.difference(Point(end, y).buffer(half, quad_segs=32))
    # rounding slivers (an edge tilted by a lat/lon round trip) would pin the ordinate to the strip's
    # border: keep the parts with an area
    parts = [g for g in getattr(rest, "geoms", [rest]) if g.area > 1e-6 * half * half]
    if not parts:
        return None
    rx0, ry0, rx1, ry1 = unary_union(parts).bounds
    yy = float(np.clip(y, ry0, ry1))
    return (yy, min(end, rx0), end) if end > span[0] else (yy, end, max(end, rx1))


def _cell_lines(
    p: FloatArray, step: float, angle: float, start: ArrayLike | None, *, check: bool = True
) -> tuple[FloatArray, float, int]:
    """World-frame legs (L, 2, 2) of every cell in visiting order, the line spacing, the cell count
    (``check=False``: leg ends trimmed unchecked, to compare angles; see :func:`trim_at_turns`)."""
    c = centroid(p)
    q = Polygon(rotate(p, angle, c))
    if not q.is_valid:
        q = q.buffer(0)
    _, ymin, _, ymax = q.bounds
    grid, spacing = line_grid(ymin, ymax, step)
    cells = boustrophedon_cells(q)
    cell_legs: list[list[list[Piece]]] = []
    cell_info: list[tuple[Polygon, list[float], list[float]]] = []  # cell, strip and leg ordinates
    for cell in cells:
        cy0, cy1 = cell.bounds[1], cell.bounds[3]
        legs: list[list[Piece]] = []
        strip_ys: list[float] = []
        leg_ys: list[float] = []
        ys = grid[(grid + spacing / 2 > cy0) & (grid - spacing / 2 < cy1)]
        for y, ext in zip(ys, strip_extents(cell, ys, spacing / 2), strict=True):
            if ext is None:
                continue
            legs.append(leg_pieces(cell, float(np.clip(y, cy0, cy1)), float(y), spacing / 2, ext))
            strip_ys.append(float(y))
            leg_ys.append(float(np.clip(y, cy0, cy1)))
        if legs:
            cell_legs.append(legs)
            cell_info.append((cell, strip_ys, leg_ys))
    cur = None if start is None else rotate(np.asarray(start, dtype=float).reshape(1, 2), angle, c)[0]
    # greedy: enter next the cell whose entry corner is nearest (vectorised over cells x 4 corners)
    k_n = len(cell_legs)
    starts = np.empty((k_n, 4, 2))
    for k, cl in enumerate(cell_legs):
        first, last = cl[0], cl[-1]
        starts[k] = [
            [first[0][1], first[0][0]],
            [first[-1][2], first[-1][0]],
            [last[0][1], last[0][0]],
            [last[-1][2], last[-1][0]],
        ]
    todo = np.ones(k_n, dtype=bool)
    ordered: list[FloatArray] = []
    for _ in range(k_n):
        if cur is None:
            k, opt = int(np.argmax(todo)), 0
        else:
            d = np.hypot(starts[..., 0] - cur[0], starts[..., 1] - cur[1])
            d[~todo] = np.inf
            k, opt = divmod(int(np.argmin(d)), 4)
        seq = cell_legs[k] if opt < 2 else cell_legs[k][::-1]
        cell, sys_, lys = cell_info[k]  # leg ends cut back where the turns see the area
        fwd = opt < 2
        lines = trim_at_turns(
            cell,
            seq,
            sys_ if fwd else sys_[::-1],
            spacing / 2,
            opt % 2 == 0,
            reach=step / 2,
            check=check,
            leg_ys=lys if fwd else lys[::-1],
        )
        ordered.append(lines)
        cur = lines[-1, 1]
        todo[k] = False
    if not ordered:
        raise ValueError("area too small or degenerate to cover")
    lines_r = np.concatenate(ordered)
    return rotate(lines_r.reshape(-1, 2), -angle, c).reshape(-1, 2, 2), spacing, len(cell_legs)


def to_world(cells: list[Polygon], angle: float, about: tuple[float, float]) -> list[BaseGeometry]:
    """Rotate cell polygons from the sweep frame back to east/north."""
    return [Polygon(rotate(np.asarray(c.exterior.coords), -angle, about)) for c in cells]

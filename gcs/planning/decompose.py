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

import numpy as np
from numpy.typing import ArrayLike
from shapely.geometry import Polygon, box
from shapely.geometry.base import BaseGeometry
from shapely.ops import unary_union

from gcs.planning.geodesy import FloatArray
from gcs.planning.patterns import Sweep, _boustrophedon, dedupe, line_grid, path_length, strip_extent, zigzag
from gcs.planning.polygon import centroid, convex_hull, min_height_rotation, require_simple, rotate


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
        angle, _ = min_height_rotation(hull)
    c = centroid(p)
    q = Polygon(rotate(p, angle, c))
    if not q.is_valid:
        q = q.buffer(0)
    _, ymin, _, ymax = q.bounds
    grid, spacing = line_grid(ymin, ymax, step)
    cells = boustrophedon_cells(q)
    cell_legs: list[list[tuple[float, float, float]]] = []
    for cell in cells:
        cy0, cy1 = cell.bounds[1], cell.bounds[3]
        legs = []
        for y in grid:
            if y + spacing / 2 <= cy0 or y - spacing / 2 >= cy1:
                continue
            ext = strip_extent(cell, float(y), spacing / 2)
            if ext is None:
                continue
            legs.append((float(np.clip(y, cy0, cy1)), ext[0], ext[1]))
        if legs:
            cell_legs.append(legs)
    cur = None if start is None else rotate(np.asarray(start, dtype=float).reshape(1, 2), angle, c)[0]
    # greedy: enter next the cell whose entry corner is nearest (vectorised over cells x 4 corners)
    k_n = len(cell_legs)
    starts = np.empty((k_n, 4, 2))
    for k, legs in enumerate(cell_legs):
        (y0, a0, b0), (y1, a1, b1) = legs[0], legs[-1]
        starts[k] = [[a0, y0], [b0, y0], [a1, y1], [b1, y1]]
    todo = np.ones(k_n, dtype=bool)
    ordered: list[FloatArray] = []
    for _ in range(k_n):
        if cur is None:
            k, opt = int(np.argmax(todo)), 0
        else:
            d = np.hypot(starts[..., 0] - cur[0], starts[..., 1] - cur[1])
            d[~todo] = np.inf
            k, opt = divmod(int(np.argmin(d)), 4)
        legs = cell_legs[k] if opt < 2 else cell_legs[k][::-1]
        lines = _boustrophedon(legs, opt % 2 == 1)
        ordered.append(lines)
        cur = lines[-1, 1]
        todo[k] = False
    if not ordered:
        raise ValueError("area too small or degenerate to cover")
    lines_r = np.concatenate(ordered)
    lines_w = rotate(lines_r.reshape(-1, 2), -angle, c).reshape(-1, 2, 2)
    points = dedupe(lines_w.reshape(-1, 2))
    hull_sweep = zigzag(hull, step, angle)
    meta = {
        "cells": len(cell_legs),
        "hull_length_m": round(hull_sweep.length, 3),
        "length_m_vs_hull": round(path_length(points) / hull_sweep.length, 4),
        "area_m2": round(Polygon(p).area, 3),
        "hull_area_m2": round(Polygon(hull).area, 3),
    }
    return Sweep("zigzag-cells", points, lines_w, step, spacing, angle, meta)


def to_world(cells: list[Polygon], angle: float, about: tuple[float, float]) -> list[BaseGeometry]:
    """Rotate cell polygons from the sweep frame back to east/north."""
    return [Polygon(rotate(np.asarray(c.exterior.coords), -angle, about)) for c in cells]

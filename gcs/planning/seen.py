"""What the fleet has actually seen: flown track samples rasterised over the search area (NumPy).

Each sample is (lat, lon, alt_rel). The ground seen across track is the camera footprint of seeds
000/001, eq. 5: ``w = 2 h tan(fov/2)`` at the sample's height ``h`` (a lower drone sees a narrower
band). Between two consecutive samples of one drone the footprint is swept as a capsule of the
smaller of the two half widths, so a climb or descent never claims ground it did not see. Cells
of the area's local grid whose centre is inside such a capsule are seen; coverage is the seen
share of the cells inside the area. Pure: no I/O, no clock; the daemon calls it per request.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gcs.planning.geodesy import FloatArray, LocalFrame

MAX_CELLS_PER_SIDE = 400  # grid resolution cap: 160k cells, a few ms per thousand samples
MIN_ALT_M = 0.5  # samples below this height (on the ground, taking off) see nothing


@dataclass(frozen=True)
class SeenGrid:
    """The seen/unseen raster of one area: ``inside`` and ``seen`` are (rows, cols), row 0 south."""

    frame: LocalFrame
    x0: float
    y0: float
    cell_m: float
    inside: np.ndarray
    seen: np.ndarray

    @property
    def area_m2(self) -> float:
        return float(self.inside.sum()) * self.cell_m**2

    @property
    def seen_m2(self) -> float:
        return float((self.inside & self.seen).sum()) * self.cell_m**2

    @property
    def covered_pct(self) -> float:
        cells = int(self.inside.sum())
        return 0.0 if cells == 0 else round(100.0 * float((self.inside & self.seen).sum()) / cells, 2)

    def rows(self) -> list[str]:
        """The grid as text rows, north first: ``#`` seen, ``.`` unseen, space outside the area."""
        chars = np.where(self.inside, np.where(self.seen, "#", "."), " ")
        return ["".join(r) for r in chars[::-1]]

    def unseen_geojson(self) -> dict[str, Any]:
        """Unseen cells inside the area as one GeoJSON MultiPolygon (a row's run of cells = one box)."""
        polys = []
        todo = self.inside & ~self.seen
        for r in range(todo.shape[0]):
            row = np.concatenate([[False], todo[r], [False]])
            edges = np.flatnonzero(np.diff(row.astype(np.int8)))
            for a, b in zip(edges[0::2], edges[1::2], strict=True):
                x_a, x_b = self.x0 + a * self.cell_m, self.x0 + b * self.cell_m
                y_a, y_b = self.y0 + r * self.cell_m, self.y0 + (r + 1) * self.cell_m
                ring = np.array([(x_a, y_a), (x_b, y_a), (x_b, y_b), (x_a, y_b), (x_a, y_a)])
                lat, lon = self.frame.to_geodetic(ring[:, 0], ring[:, 1])
                polys.append(
                    [[[round(float(o), 7), round(float(a_), 7)] for a_, o in zip(lat, lon, strict=True)]]
                )
        return {"type": "MultiPolygon", "coordinates": polys}


def footprint_half_widths(alts: FloatArray, swath_m: float, altitude_m: float | None) -> FloatArray:
    """Half the ground width seen at each height: eq. 5 with the camera implied by swath at altitude.

    Without a planned altitude the swath is taken as fixed (a sensor whose footprint is known).
    """
    a = np.asarray(alts, dtype=float)
    if altitude_m is None or altitude_m <= 0:
        half = np.full(a.shape, swath_m / 2.0)
    else:
        half = a * (swath_m / (2.0 * altitude_m))  # tan(fov/2) = swath / (2 h_planned)
    half[~np.isfinite(a) | (a < MIN_ALT_M)] = 0.0
    return half


def inside_mask(poly: FloatArray, xs: FloatArray, ys: FloatArray) -> np.ndarray:
    """Even-odd point-in-polygon for every (xs[j], ys[i]) grid centre, vectorised over the grid."""
    gx, gy = np.meshgrid(xs, ys)
    inside = np.zeros(gx.shape, dtype=bool)
    n = len(poly)
    for k in range(n):
        (x1, y1), (x2, y2) = poly[k], poly[(k + 1) % n]
        if y1 == y2:
            continue
        crosses = (y1 > gy) != (y2 > gy)
        x_at = x1 + (gy - y1) * (x2 - x1) / (y2 - y1)
        inside ^= crosses & (gx < x_at)
    return inside


def seen_grid(
    area_latlon: Sequence[tuple[float, float]],
    tracks: Sequence[Sequence[tuple[float, float, float]]],
    swath_m: float,
    altitude_m: float | None = None,
    cell_m: float | None = None,
) -> SeenGrid:
    """Rasterise the tracks' footprints over the area; ``cell_m`` defaults to swath/4 (capped grid)."""
    if swath_m <= 0:
        raise ValueError("swath must be positive")
    if len(area_latlon) < 3:
        raise ValueError("an area needs at least three vertices")
    arr = np.asarray(area_latlon, dtype=float)
    frame = LocalFrame.centred_on(arr[:, 0], arr[:, 1])
    poly = frame.points_to_local([(float(a), float(b)) for a, b in arr])
    (xmin, ymin), (xmax, ymax) = poly.min(axis=0), poly.max(axis=0)
    extent = max(xmax - xmin, ymax - ymin, 1e-6)
    cell = max(cell_m or swath_m / 4.0, extent / MAX_CELLS_PER_SIDE)
    cols, rows = max(1, math.ceil((xmax - xmin) / cell)), max(1, math.ceil((ymax - ymin) / cell))
    xs = xmin + (np.arange(cols) + 0.5) * cell
    ys = ymin + (np.arange(rows) + 0.5) * cell
    seen = np.zeros((rows, cols), dtype=bool)
    for track in tracks:
        if len(track) == 0:
            continue
        t = np.asarray(track, dtype=float).reshape(-1, 3)
        pts = frame.points_to_local([(float(a), float(b)) for a, b in t[:, :2]])
        half = footprint_half_widths(t[:, 2], swath_m, altitude_m)
        sweep(seen, pts, half, xmin, ymin, cell)
    return SeenGrid(frame, float(xmin), float(ymin), cell, inside_mask(poly, xs, ys), seen)


def sweep(seen: np.ndarray, pts: FloatArray, half: FloatArray, x0: float, y0: float, cell: float) -> None:
    """Mark the cells within each segment's capsule (one sample alone: its disc); re-tasking
    sweeps a planned path with it to find the share a drone was to see (gcs/planning/retask.py)."""
    rows, cols = seen.shape
    a_pts = pts if len(pts) > 1 else np.vstack([pts, pts])
    a_half = half if len(half) > 1 else np.concatenate([half, half])
    for k in range(len(a_pts) - 1):
        r = float(min(a_half[k], a_half[k + 1]))
        if r <= 0:
            continue
        (ax, ay), (bx, by) = a_pts[k], a_pts[k + 1]
        c0 = max(0, int((min(ax, bx) - r - x0) / cell))
        c1 = min(cols, int((max(ax, bx) + r - x0) / cell) + 1)
        r0 = max(0, int((min(ay, by) - r - y0) / cell))
        r1 = min(rows, int((max(ay, by) + r - y0) / cell) + 1)
        if c0 >= c1 or r0 >= r1:
            continue
        gx = x0 + (np.arange(c0, c1) + 0.5) * cell
        gy = y0 + (np.arange(r0, r1) + 0.5) * cell
        dx, dy = bx - ax, by - ay
        seg2 = dx * dx + dy * dy
        px, py = gx[None, :] - ax, gy[:, None] - ay
        t = np.clip((px * dx + py * dy) / seg2, 0.0, 1.0) if seg2 > 0 else np.zeros_like(px * py)
        d2 = (px - t * dx) ** 2 + (py - t * dy) ** 2
        seen[r0:r1, c0:c1] |= d2 <= r * r

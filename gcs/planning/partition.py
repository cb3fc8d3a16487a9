"""Capability-proportional area partition (seed 003): divide protocol, one-to-one and block sharing.

* :func:`divide_polygon` - the ``divide`` protocol on an exact shapely area: vertical cuts by
  column capability sums, then horizontal cuts by row within each column. With one block over
  the whole grid it is the converged partition; the search planner consumes it.
* :func:`simulate` - discrete-event simulation of UAVs on an m x n grid meeting neighbours at
  link positions (one meeting per neighbour pair per period), dividing either at every meeting
  (one-to-one) or once they know their whole (g, h) block (block sharing). Areas are rasters
  (pixels of the irregular area with holes) so a division is a numpy cut, not a polygon clip.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import MultiPolygon, Polygon, box

FloatArray = NDArray[np.float64]
Strategy = Literal["one-to-one", "block"]


def capability(coverage_range: FloatArray | float, speed: FloatArray | float) -> FloatArray:
    """Maximum coverage speed a_i = 2 c_i v_i (m^2/s), eq. 1."""
    return np.asarray(2.0 * np.asarray(coverage_range) * np.asarray(speed), dtype=float)


def target_areas(total: float, a: FloatArray) -> FloatArray:
    """Eq. 2: A_i = a_i A / sum a_j."""
    a = np.asarray(a, dtype=float)
    return np.asarray(total * a / a.sum(), dtype=float)


# ---------------------------------------------------------------- exact divide (planner side)


def _cut(geom: Polygon | MultiPolygon, frac: float, axis: int) -> float:
    """Coordinate c with area(geom below c along axis) = frac * area, by bisection (exact to 1e-9)."""
    minx, miny, maxx, maxy = geom.bounds
    lo, hi = (minx, maxx) if axis == 0 else (miny, maxy)
    want = frac * geom.area
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        part = geom.intersection(
            box(minx - 1, miny - 1, mid, maxy + 1) if axis == 0 else box(minx - 1, miny - 1, maxx + 1, mid)
        )
        if part.area < want:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _strips(
    geom: Polygon | MultiPolygon, weights: Sequence[float] | FloatArray, axis: int
) -> list[Polygon | MultiPolygon]:
    """Cut into parallel strips with areas proportional to ``weights`` (axis 0: left to right)."""
    w = np.asarray(weights, dtype=float)
    cum = np.cumsum(w)[:-1] / w.sum()
    minx, miny, maxx, maxy = geom.bounds
    cuts = (
        [minx - 1 if axis == 0 else miny - 1]
        + [_cut(geom, f, axis) for f in cum]
        + [maxx + 1 if axis == 0 else maxy + 1]
    )
    out = []
    for a, b in itertools.pairwise(cuts):
        clip = box(a, miny - 1, b, maxy + 1) if axis == 0 else box(minx - 1, a, maxx + 1, b)
        out.append(geom.intersection(clip))
    return out


def divide_polygon(
    area: Polygon | MultiPolygon, capabilities: FloatArray
) -> list[list[Polygon | MultiPolygon]]:
    """The divide protocol on an (rows x cols) capability grid; returns sub-areas [row][col].

    Row 0 is the northern row (the paper's "above"), column 0 the western one.
    """
    cap = np.atleast_2d(np.asarray(capabilities, dtype=float))
    if np.any(cap <= 0):
        raise ValueError("every capability must be positive")
    columns = _strips(area, cap.sum(axis=0), axis=0)
    cells: list[list[Polygon | MultiPolygon]] = [[Polygon()] * cap.shape[1] for _ in range(cap.shape[0])]
    for c, strip in enumerate(columns):
        rows = _strips(strip, cap[::-1, c], axis=1)[::-1]  # horizontal cuts go bottom-up
        for r, part in enumerate(rows):
            cells[r][c] = part
    return cells


def partition_for_search(
    area: Polygon, capabilities: Sequence[float], rows: int | None = None
) -> list[Polygon | MultiPolygon]:
    """Pure function for the search planner: one sub-area per drone, areas proportional to a_i.

    Drones are laid on a near-square grid (``rows`` x ceil(N / rows)); grid slots beyond N get
    no area. Each returned sub-area can be zig-zagged by the coverage planner.
    """
    caps = np.asarray(capabilities, dtype=float)
    n = len(caps)
    r = rows or max(1, int(np.floor(np.sqrt(n))))
    c = int(np.ceil(n / r))
    # put the N drones in the first N slots of the grid; unused slots are dropped from their column
    out: list[Polygon | MultiPolygon] = [Polygon()] * n
    col_members = [list(range(k, n, c)) for k in range(c)]
    col_members = [m for m in col_members if m]
    strips = _strips(area, [caps[m].sum() for m in col_members], axis=0)
    for members, strip in zip(col_members, strips, strict=True):
        parts = _strips(strip, caps[members][::-1], axis=1)[::-1]
        for i, part in zip(members, parts, strict=True):
            out[i] = part
    return out


# ---------------------------------------------------------------- raster simulation


@dataclass(frozen=True)
class Raster:
    """Pixels of the area: ``inside`` mask (row 0 = north), pixel size in metres and origin (SW)."""

    inside: NDArray[np.bool_]
    pixel: float
    origin: tuple[float, float]

    @classmethod
    def from_polygon(cls, area: Polygon | MultiPolygon, pixel: float) -> Raster:
        minx, miny, maxx, maxy = area.bounds
        cols = int(np.ceil((maxx - minx) / pixel))
        rows = int(np.ceil((maxy - miny) / pixel))
        gx, gy = np.meshgrid(minx + (np.arange(cols) + 0.5) * pixel, maxy - (np.arange(rows) + 0.5) * pixel)
        return cls(inside=shapely.contains_xy(area, gx, gy), pixel=pixel, origin=(minx, maxy - rows * pixel))

    def polygon(self, mask: NDArray[np.bool_]) -> Polygon | MultiPolygon:
        """Union of the pixel runs of ``mask`` (staircase boundary at pixel resolution)."""
        boxes = []
        x0, y0 = self.origin
        rows = mask.shape[0]
        for r in range(rows):
            line = np.concatenate([[False], mask[r], [False]]).astype(np.int8)
            edges = np.flatnonzero(np.diff(line))
            top = y0 + (rows - r) * self.pixel
            for a, b in zip(edges[::2], edges[1::2], strict=True):
                boxes.append(box(x0 + a * self.pixel, top - self.pixel, x0 + b * self.pixel, top))
        return shapely.union_all(boxes) if boxes else Polygon()


def _split_mask(mask: NDArray[np.bool_], weights: FloatArray, axis: int) -> list[NDArray[np.bool_]]:
    """Straight cuts of a pixel set: order pixels along ``axis`` (0: by column then row, left to
    right; 1: by row then column, north to south) and cut the sequence at the weight shares."""
    r, c = np.nonzero(mask)
    order = np.lexsort((r, c)) if axis == 0 else np.lexsort((c, r))
    cum = np.rint(np.cumsum(weights) / np.sum(weights) * len(order)).astype(int)
    parts, start = [], 0
    for end in cum:
        m = np.zeros_like(mask)
        sel = order[start:end]
        m[r[sel], c[sel]] = True
        parts.append(m)
        start = end
    return parts


def divide_block(
    union: NDArray[np.bool_], members: list[tuple[int, int]], a: FloatArray
) -> dict[tuple[int, int], NDArray[np.bool_]]:
    """The divide protocol (eqs. 3-8) for a block: columns by capability sums, then rows."""
    cols = sorted({c for _, c in members})
    col_masks = _split_mask(union, np.array([sum(a[r, c] for r, cc in members if cc == c) for c in cols]), 0)
    out = {}
    for c, cm in zip(cols, col_masks, strict=True):
        rows = sorted(r for r, cc in members if cc == c)
        for r, m in zip(rows, _split_mask(cm, np.array([a[r, c] for r in rows]), 1), strict=True):
            out[(r, c)] = m
    return out


def _blocks(
    rows: int, cols: int, g: int, h: int, phase: int
) -> dict[tuple[int, int], tuple[tuple[int, int], ...]]:
    """(g, h) blocks tiling the grid; phase 1 shifts the tiling by (g/2, h/2) (the paper's b = -1)."""
    sr, sc = (g // 2, h // 2) if phase else (0, 0)
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for r in range(rows):
        for c in range(cols):
            groups.setdefault(
                ((r + g - sr) // g if sr else r // g, (c + h - sc) // h if sc else c // h), []
            ).append((r, c))
    return {cell: tuple(members) for members in groups.values() for cell in members}


def meeting_schedule(rows: int, cols: int) -> list[list[tuple[tuple[int, int], tuple[int, int]]]]:
    """Neighbour pairs meeting in each quarter period at their shared link position.

    Chessboard start (even cells at link 1 = top, odd at link 3 = bottom), all turning through
    the four links, so each pair meets exactly once per period and nobody meets two at once.
    """
    q: list[list[tuple[tuple[int, int], tuple[int, int]]]] = [[], [], [], []]
    for r in range(rows):
        for c in range(cols):
            even = (r + c) % 2 == 0
            if r + 1 < rows:
                q[2 if even else 0].append(((r, c), (r + 1, c)))
            if c + 1 < cols:
                q[3 if even else 1].append(((r, c), (r, c + 1)))
    return q


@dataclass
class SimResult:
    """Max relative area error (vs eq. 2) after each quarter period, and the final partition."""

    errors: list[float]
    areas: list[FloatArray]
    masks: dict[tuple[int, int], NDArray[np.bool_]] = field(repr=False)
    divisions: int = 0
    division_times: dict[tuple[int, int], list[float]] = field(default_factory=dict, repr=False)
    """Per UAV, when (periods) it took each new sub-area from a block division."""

    def periods_to(self, tol: float) -> float | None:
        """First time (periods, quarter resolution) the error is <= ``tol`` and stays so."""
        e = np.asarray(self.errors)
        bad = np.flatnonzero(e > tol)
        if len(bad) and bad[-1] == len(e) - 1:
            return None
        return (int(bad[-1]) + 1 if len(bad) else 0) / 4.0


def initial_grid(raster: Raster, rows: int, cols: int) -> dict[tuple[int, int], NDArray[np.bool_]]:
    """The unsuitable starting partition: equal slices of the bounding box, clipped to the area."""
    h, w = raster.inside.shape
    rr = np.minimum(np.arange(h) * rows // h, rows - 1)
    cc = np.minimum(np.arange(w) * cols // w, cols - 1)
    return {
        (r, c): raster.inside & (rr[:, None] == r) & (cc[None, :] == c)
        for r in range(rows)
        for c in range(cols)
    }


def simulate(
    raster: Raster,
    a: FloatArray,
    strategy: Strategy,
    block: tuple[int, int] = (2, 2),
    max_periods: int = 60,
    tol: float | None = 0.01,
    start: dict[tuple[int, int], NDArray[np.bool_]] | None = None,
) -> SimResult:
    """Run the meetings period by period; stop after ``max_periods`` or once the error <= ``tol``."""
    rows, cols = a.shape
    masks = {k: v.copy() for k, v in (start or initial_grid(raster, rows, cols)).items()}
    want = target_areas(float(raster.inside.sum()), a).reshape(rows, cols)
    schedule = meeting_schedule(rows, cols)
    epoch = {k: 0 for k in masks}
    snap: dict[tuple[tuple[int, int], int], NDArray[np.bool_]] = {(k, 0): m for k, m in masks.items()}
    known: dict[tuple[int, int], set[tuple[int, int]]] = {k: {k} for k in masks}
    tilings = [_blocks(rows, cols, *block, p) for p in (0, 1)]
    result = SimResult(errors=[], areas=[], masks=masks)

    def block_of(k: tuple[int, int], e: int) -> tuple[tuple[int, int], ...]:
        return tilings[e % 2][k]

    def try_divide(k: tuple[int, int]) -> None:
        while set(block_of(k, epoch[k])) <= known[k]:
            members = list(block_of(k, epoch[k]))
            union = np.zeros_like(raster.inside)
            for u in members:
                union |= snap[(u, epoch[u] if u == k else epoch[k])]
            masks[k] = divide_block(union, members, a)[k]
            result.divisions += 1
            result.division_times.setdefault(k, []).append(clock[0])
            epoch[k] += 1
            snap[(k, epoch[k])] = masks[k]
            known[k] = {k}

    clock = [0.0]  # periods elapsed, at quarter resolution
    if strategy == "block":
        for k in masks:
            try_divide(k)
    for period in range(max_periods):
        for q_index, quarter in enumerate(schedule):
            clock[0] = period + (q_index + 1) / 4.0
            for i, j in quarter:
                if strategy == "one-to-one":
                    axis = 0 if i[0] == j[0] else 1  # side by side: vertical cut; stacked: horizontal
                    union = masks[i] | masks[j]
                    parts = _split_mask(union, np.array([a[i], a[j]]), axis)
                    masks[i], masks[j] = parts
                    result.divisions += 2
                    continue
                # One contact: share, divide what is complete, and share again what the division
                # (or the block learnt from the other) changed. The paper's timing: the contact that
                # completes a division is also the first exchange for the next block, so a (1, 4)
                # or (2, 2) block divides once per period after the first (seed 003, Sec. III).
                for _ in range(4):  # bounded: each round can only raise the pair's epochs
                    before = (epoch[i], epoch[j])
                    for x, y in ((i, j), (j, i)):
                        if y in block_of(x, epoch[x]):
                            if epoch[y] == epoch[x]:
                                known[x] |= known[y]
                            elif epoch[y] > epoch[x]:  # y already divided this block: x learns it all
                                known[x] = set(block_of(x, epoch[x]))
                    for u in (i, j):
                        try_divide(u)
                    if (epoch[i], epoch[j]) == before:
                        break
            areas = np.array([[masks[(r, c)].sum() for c in range(cols)] for r in range(rows)], dtype=float)
            result.errors.append(float(np.max(np.abs(areas - want) / want)))
            result.areas.append(areas)
        if tol is not None and result.periods_to(tol) is not None and result.errors[-1] <= tol:
            break
    return result

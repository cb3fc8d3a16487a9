"""Polygon analysis for coverage planning (seed 000 §V-A/B): type, hull, regularity, sweep direction.

All functions take an (N, 2) array of local east/north metres (ring not closed) and are pure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import ConvexHull
from shapely.geometry import Polygon

from gcs.planning.geodesy import FloatArray

_EPS = 1e-9


class PolygonType(StrEnum):
    CONVEX = "convex"
    CONCAVE = "concave"
    SELF_INTERSECTING = "self-intersecting"


@dataclass(frozen=True)
class EdgeCrossing:
    """Two non-adjacent edges that cross: edge i joins vertex i to vertex i+1 (mod n)."""

    edge_a: int
    edge_b: int
    point: tuple[float, float]


class SelfIntersectionError(ValueError):
    """The area's boundary crosses itself; there is no inside to search, so we refuse it."""

    def __init__(self, crossings: list[EdgeCrossing], vertices: FloatArray | None = None) -> None:
        self.crossings = crossings
        parts = []
        for c in crossings[:5]:
            desc = f"edge {c.edge_a} crosses edge {c.edge_b} at ({c.point[0]:.2f}, {c.point[1]:.2f})"
            if vertices is not None:
                n = len(vertices)
                a0, a1 = vertices[c.edge_a], vertices[(c.edge_a + 1) % n]
                b0, b1 = vertices[c.edge_b], vertices[(c.edge_b + 1) % n]
                desc += (
                    f" [edge {c.edge_a}: ({a0[0]:.2f}, {a0[1]:.2f})->({a1[0]:.2f}, {a1[1]:.2f}); "
                    f"edge {c.edge_b}: ({b0[0]:.2f}, {b0[1]:.2f})->({b1[0]:.2f}, {b1[1]:.2f})]"
                )
            parts.append(desc)
        more = f" and {len(crossings) - 5} more" if len(crossings) > 5 else ""
        super().__init__("self-intersecting area: " + "; ".join(parts) + more)


def as_ring(points: ArrayLike) -> FloatArray:
    """(N, 2) float array with a repeated closing vertex and consecutive duplicates removed."""
    arr = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(arr) > 1 and np.allclose(arr[0], arr[-1]):
        arr = arr[:-1]
    keep = np.ones(len(arr), dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(arr, axis=0)) > _EPS, axis=1)
    arr = arr[keep]
    if len(arr) < 3:
        raise ValueError("a polygon needs at least three distinct vertices")
    return arr


def signed_area(points: ArrayLike) -> float:
    """Shoelace area, positive counter-clockwise (seed 000 eq. 3, with its typo corrected)."""
    p = as_ring(points)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def centroid(points: ArrayLike) -> tuple[float, float]:
    """Centre of mass of the polygon's area (seed 000 eqs. 1-2); vertex mean if degenerate."""
    p = as_ring(points)
    x, y = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    a = 0.5 * float(cross.sum())
    if abs(a) < _EPS:
        return float(x.mean()), float(y.mean())
    return float(((x + x1) * cross).sum() / (6 * a)), float(((y + y1) * cross).sum() / (6 * a))


def find_crossings(points: ArrayLike) -> list[EdgeCrossing]:
    """All pairs of non-adjacent edges that touch or cross (O(n^2) vectorised per edge)."""
    p = as_ring(points)
    n = len(p)
    a, b = p, np.roll(p, -1, axis=0)
    d = b - a
    out: list[EdgeCrossing] = []
    for i in range(n - 2):
        js = np.arange(i + 2, n)
        if i == 0:
            js = js[js != n - 1]  # edge n-1 is adjacent to edge 0
        if js.size == 0:
            continue
        r = d[i]
        s = d[js]
        qp = a[js] - a[i]
        denom = r[0] * s[:, 1] - r[1] * s[:, 0]
        t_num = qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]
        u_num = qp[:, 0] * r[1] - qp[:, 1] * r[0]
        scale = max(float(np.abs(p).max()), 1.0)
        par = np.abs(denom) <= _EPS * scale * scale
        with np.errstate(divide="ignore", invalid="ignore"):
            t = t_num / denom
            u = u_num / denom
        hit = (~par) & (t >= -_EPS) & (t <= 1 + _EPS) & (u >= -_EPS) & (u <= 1 + _EPS)
        # collinear overlapping edges also make the ring invalid
        colin = par & (np.abs(t_num) <= _EPS * scale * scale)
        if colin.any():
            rr = float(np.dot(r, r))
            for k in np.nonzero(colin)[0]:
                t0 = float(np.dot(qp[k], r)) / rr
                t1 = float(np.dot(qp[k] + s[k], r)) / rr
                if max(t0, t1) >= -_EPS and min(t0, t1) <= 1 + _EPS:
                    tt = min(max(max(min(t0, t1), 0.0), 0.0), 1.0)
                    pt = a[i] + tt * r
                    out.append(EdgeCrossing(i, int(js[k]), (float(pt[0]), float(pt[1]))))
        for k in np.nonzero(hit)[0]:
            pt = a[i] + t[k] * r
            out.append(EdgeCrossing(i, int(js[k]), (float(pt[0]), float(pt[1]))))
    return out


def classify(points: ArrayLike) -> PolygonType:
    """Convex / concave / self-intersecting.

    The paper's test (drop each vertex, check if it falls inside the rest) misses crossings where
    no vertex is inside (a bow-tie); we test edge crossings directly, then turn directions.
    """
    p = as_ring(points)
    if find_crossings(p):
        return PolygonType.SELF_INTERSECTING
    d = np.roll(p, -1, axis=0) - p
    cross = d[:, 0] * np.roll(d[:, 1], -1) - d[:, 1] * np.roll(d[:, 0], -1)
    scale = float(np.abs(d).max()) ** 2
    sig = cross[np.abs(cross) > 1e-12 * scale]
    if sig.size == 0 or np.all(sig > 0) or np.all(sig < 0):
        return PolygonType.CONVEX
    return PolygonType.CONCAVE


def convex_hull(points: ArrayLike) -> FloatArray:
    """Counter-clockwise hull vertices, collinear points dropped (the paper's ConcaveToConvex)."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    hull = ConvexHull(p)
    return p[hull.vertices]


def require_simple(points: ArrayLike) -> FloatArray:
    """The ring, counter-clockwise; raises :class:`SelfIntersectionError` naming the crossing edges."""
    p = as_ring(points)
    crossings = find_crossings(p)
    if crossings:
        raise SelfIntersectionError(crossings, p)
    if signed_area(p) < 0:
        p = p[::-1].copy()
    return p


def interior_angles(points: ArrayLike) -> FloatArray:
    """Interior angle at each vertex in degrees (reflex angles > 180 for concave vertices)."""
    p = require_simple(points)
    prev = np.roll(p, 1, axis=0) - p
    nxt = np.roll(p, -1, axis=0) - p
    ang = np.degrees(np.arctan2(prev[:, 1], prev[:, 0]) - np.arctan2(nxt[:, 1], nxt[:, 0]))
    return np.mod(ang, 360.0)


def regularity(points: ArrayLike) -> float:
    """Seed 000 Alg. 1: 1.0 for a regular polygon, lower the more angles and edges vary.

    r_angle = 1 - mean(|theta_i - mean theta|) / 360; r_edge = 1 - mean(|l_i - mean l| / mean l);
    r = their average. (The paper calls the mean edge length the "average perimeter".)
    """
    p = require_simple(points)
    theta = interior_angles(p)
    lengths = np.hypot(*(p - np.roll(p, 1, axis=0)).T)
    r_angle = 1.0 - float(np.mean(np.abs(theta - theta.mean()) / 360.0))
    r_edge = 1.0 - float(np.mean(np.abs(lengths - lengths.mean()) / lengths.mean()))
    return 0.5 * (r_angle + r_edge)


def rotate(points: ArrayLike, angle_rad: float, about: tuple[float, float] = (0.0, 0.0)) -> FloatArray:
    """Rotate points counter-clockwise by ``angle_rad`` around ``about``."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    q = p - np.asarray(about)
    return np.column_stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]]) + np.asarray(about)


def height_at(points: ArrayLike, angle_rad: float) -> float:
    """Extent along y after rotating the points by ``angle_rad`` (the paper's "height")."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    y = math.sin(angle_rad) * p[:, 0] + math.cos(angle_rad) * p[:, 1]
    return float(y.max() - y.min())


def min_height_rotation(points: ArrayLike) -> tuple[float, float]:
    """Exact (angle, height): rotating by ``angle`` makes the y-extent minimal (rotating calipers).

    The minimum width of a convex set is attained with one support line flush with a hull edge, so
    checking the n hull-edge directions is exact; the paper's 0.1 degree scan can only be worse.
    The returned angle rotates that edge onto the x axis, in (-pi/2, pi/2].
    """
    hull = convex_hull(points)
    edges = np.roll(hull, -1, axis=0) - hull
    best = (0.0, math.inf)
    for ex, ey in edges:
        length = math.hypot(ex, ey)
        if length < _EPS:
            continue
        nx, ny = -ey / length, ex / length
        proj = hull[:, 0] * nx + hull[:, 1] * ny
        h = float(proj.max() - proj.min())
        if h < best[1] - 1e-12:
            ang = -math.atan2(ey, ex)
            ang = (ang + math.pi / 2) % math.pi - math.pi / 2
            if ang <= -math.pi / 2 + 1e-15:
                ang += math.pi
            best = (ang, h)
    return best


def scan_min_height(points: ArrayLike, step_deg: float = 0.1) -> tuple[float, float]:
    """The paper's method: try rotations 0..180 degrees in ``step_deg`` steps (for comparison)."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    angles = np.radians(np.arange(0.0, 180.0, step_deg))
    y = np.outer(np.sin(angles), p[:, 0]) + np.outer(np.cos(angles), p[:, 1])
    h = y.max(axis=1) - y.min(axis=1)
    k = int(np.argmin(h))
    return float(angles[k]), float(h[k])


def to_shapely(points: ArrayLike) -> Polygon:
    """Shapely polygon of a simple ring (validated)."""
    return Polygon(require_simple(points))

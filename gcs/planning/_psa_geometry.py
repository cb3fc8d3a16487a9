"""Convex-polygon helpers for PSA: hull, edge frames, ring membership, segment entry points.

Kept apart from the algorithm so each piece can be tested on hand-made polygons. Hulls are
counter-clockwise vertex arrays without repetition; a hull of two points is the degenerate
polygon a -> b -> a (two edges, perimeter 2|ab|), a hull of one point has no edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

EPS = 1e-9


def convex_hull(points: FloatArray, tol: float = 1e-9) -> FloatArray:
    """Andrew's monotone chain; CCW, collinear points dropped; (1,2) or (2,2) arrays when degenerate."""
    pts = np.unique(np.asarray(points, dtype=float).reshape(-1, 2), axis=0)
    if len(pts) <= 2:
        return pts

    def cross(o: FloatArray, a: FloatArray, b: FloatArray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    lower: list[FloatArray] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= tol:
            lower.pop()
        lower.append(p)
    upper: list[FloatArray] = []
    for p in pts[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= tol:
            upper.pop()
        upper.append(p)
    hull = np.array(lower[:-1] + upper[:-1])
    if len(hull) < 2:  # all points identical up to tol
        return pts[:1]
    return hull


@dataclass(frozen=True)
class EdgeFrame:
    """Per-edge start vertex, unit direction, outward unit normal and length of a CCW hull."""

    start: FloatArray  # (h, 2)
    direction: FloatArray  # (h, 2)
    normal: FloatArray  # (h, 2), outward
    length: FloatArray  # (h,)

    @property
    def perimeter(self) -> float:
        return float(self.length.sum())

    def point(self, edge: int, t: float) -> FloatArray:
        """The point ``t`` metres along ``edge``."""
        return np.asarray(self.start[edge] + t * self.direction[edge], dtype=float)


def edge_frame(hull: FloatArray) -> EdgeFrame:
    """Edges of a CCW hull with at least two vertices (outward normal = direction turned right)."""
    start = np.asarray(hull, dtype=float)
    end = np.roll(start, -1, axis=0)
    vec = end - start
    length = np.hypot(vec[:, 0], vec[:, 1])
    direction = vec / np.maximum(length, EPS)[:, None]
    normal = np.column_stack([direction[:, 1], -direction[:, 0]])
    return EdgeFrame(start=start, direction=direction, normal=normal, length=length)


def locate(frame: EdgeFrame, points: FloatArray) -> tuple[FloatArray, IntArray, FloatArray]:
    """Depth inside the hull, nearest edge and position along it for each point.

    For a point inside a convex polygon the distance to the boundary is the smallest distance to
    an edge's supporting line and its foot lies on that edge, so ``depth`` is exactly the
    distance to the boundary and the (edge, t) pair is where the formation's scan line passes it.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    rel = pts[:, None, :] - frame.start[None, :, :]  # (n, h, 2)
    signed = -np.einsum("nhk,hk->nh", rel, frame.normal)  # distance inside each edge's line
    edge = np.argmin(signed, axis=1).astype(np.int64)
    depth = np.maximum(signed[np.arange(len(pts)), edge], 0.0)
    t = np.einsum("nk,nk->n", rel[np.arange(len(pts)), edge], frame.direction[edge])
    t = np.clip(t, 0.0, frame.length[edge])
    return depth, edge, t


def entry_parameter(frame: EdgeFrame, a: FloatArray, b: FloatArray) -> float:
    """Smallest s in [0, 1] with a + s (b - a) inside the convex hull (Cyrus-Beck); b must be inside."""
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    f0 = np.einsum("hk,hk->h", np.asarray(a)[None, :] - frame.start, frame.normal)
    slope = frame.normal @ d
    s = 0.0
    for fa, sl in zip(f0, slope, strict=True):
        if sl < -EPS and fa > 0.0:
            s = max(s, -fa / sl)
    return min(s, 1.0)


def nearest_on_boundary(frame: EdgeFrame, point: FloatArray) -> tuple[FloatArray, int, float]:
    """Foot of ``point`` (inside the hull) on the nearest edge: (foot, edge, t)."""
    _, edge, t = locate(frame, np.asarray(point).reshape(1, 2))
    e = int(edge[0])
    return frame.point(e, float(t[0])), e, float(t[0])


def exterior_angle(n_from: FloatArray, n_to: FloatArray) -> float:
    """Unsigned angle between two unit normals (radians, 0..pi)."""
    c = float(np.clip(np.dot(n_from, n_to), -1.0, 1.0))
    return float(np.arccos(c))

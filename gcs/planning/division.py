"""Dividing a search among drones by capability (seed 000 §V-D, Algs. 3 and 4).

Capability is a flying range: ``battery x endurance x speed x (1 - reserve)`` metres. Every
drone first pays its trip from home to the area and back (C_h); what is left (C' = C - C_h) is
what it can survey. Both divisions give each drone a share proportional to C'.

* Path division (Alg. 3) cuts one coverage path into consecutive pieces of those lengths.
* Region division (Alg. 4) cuts the area, in the sweep frame, by lines parallel to the legs
  into slices whose areas are in those proportions; each cut is found by bisection.

Where the paper silently leaves the tail of the path unflown (its Fig. 12b) we raise
:class:`InsufficientCapabilityError` with the shortfall, unless ``allow_partial`` is set.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from pydantic import BaseModel, Field
from shapely.geometry import Polygon, box
from shapely.geometry.base import BaseGeometry

from gcs.planning.geodesy import FloatArray
from gcs.planning.polygon import centroid, rotate


class InsufficientCapabilityError(ValueError):
    """The fleet cannot fly the whole search; ``shortfall_m`` says how much path is left over."""

    def __init__(self, message: str, shortfall_m: float = 0.0, shortfall_m2: float = 0.0) -> None:
        super().__init__(message)
        self.shortfall_m = shortfall_m
        self.shortfall_m2 = shortfall_m2


class DroneSpec(BaseModel):
    """What a drone can fly: battery fraction, full-charge endurance, cruise speed, reserve."""

    name: str = Field(min_length=1, max_length=64)
    battery: float = Field(default=1.0, gt=0.0, le=1.0)
    endurance_s: float = Field(default=1200.0, gt=0.0)
    speed_mps: float = Field(default=5.0, gt=0.0)
    reserve: float = Field(default=0.2, ge=0.0, lt=1.0)
    home: tuple[float, float] | None = Field(default=None, description="local east/north of home (m)")

    @property
    def range_m(self) -> float:
        """Distance it can fly before its reserve."""
        return self.battery * self.endurance_s * self.speed_mps * (1.0 - self.reserve)


def capability_fractions(ranges: ArrayLike) -> FloatArray:
    """c_i = d_i / sum(d): each drone's share of the fleet's range."""
    r = np.asarray(ranges, dtype=float)
    if np.any(r <= 0):
        raise ValueError("every drone needs a positive usable range")
    return r / r.sum()


def split_lengths(
    total: float, fractions: ArrayLike, limits: ArrayLike, allow_partial: bool = False
) -> FloatArray:
    """Lengths ``c_i x total`` capped at ``limits``; what a capped drone cannot take goes to the others.

    The paper stops at the cap (870 m path, c = 0.3, 300 m range: 261 m, fine; a 0.4 share would
    be cut to 300 m and the rest lost); we hand the excess to drones with spare range in
    proportion to their fractions, and raise only when the fleet as a whole is short.
    """
    c = np.asarray(fractions, dtype=float)
    lim = np.maximum(np.asarray(limits, dtype=float), 0.0)
    if c.shape != lim.shape or np.any(c <= 0):
        raise ValueError("one positive fraction and one limit per drone")
    c = c / c.sum()
    out = np.zeros_like(c)
    left = float(total)
    free = np.ones(len(c), dtype=bool)
    while left > 1e-9 and free.any():
        want = left * c * free / c[free].sum()
        room = lim - out
        capped = free & (want >= room - 1e-12)
        if not capped.any():
            out += want
            left = 0.0
            break
        left -= float(room[capped].sum())
        out[capped] = lim[capped]
        free &= ~capped
    if left > 1e-6 * max(total, 1.0) and not allow_partial:
        raise InsufficientCapabilityError(
            f"the fleet can survey {total - left:.1f} m of a {total:.1f} m path; "
            f"{left:.1f} m would be left unflown (add drones, charge batteries or shrink the area)",
            shortfall_m=left,
        )
    return out


def cut_path(points: ArrayLike, lengths: Sequence[float] | FloatArray) -> list[FloatArray]:
    """Consecutive pieces of the polyline with the given lengths (cut points interpolated)."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    seg = np.hypot(*np.diff(p, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = float(cum[-1])

    def at(s: float) -> FloatArray:
        s = min(max(s, 0.0), total)
        k = int(np.searchsorted(cum, s, side="right") - 1)
        k = min(k, len(seg) - 1)
        t = 0.0 if seg[k] == 0 else (s - cum[k]) / seg[k]
        return p[k] + t * (p[k + 1] - p[k])

    pieces = []
    s0 = 0.0
    for length in lengths:
        s1 = min(s0 + float(length), total)
        if s1 - s0 <= 1e-9:
            pieces.append(np.empty((0, 2)))
            continue
        inner = p[(cum > s0 + 1e-9) & (cum < s1 - 1e-9)]
        pieces.append(np.vstack([at(s0), inner, at(s1)]))
        s0 = s1
    return pieces


@dataclass(frozen=True)
class PathShare:
    """One drone's piece of a divided path and its budget."""

    drone: str
    points: FloatArray
    survey_m: float
    transit_m: float
    range_m: float

    @property
    def total_m(self) -> float:
        return self.survey_m + self.transit_m


def _homes(drones: Sequence[DroneSpec], home: ArrayLike | None) -> FloatArray:
    default = np.zeros(2) if home is None else np.asarray(home, dtype=float).reshape(2)
    return np.array([d.home if d.home is not None else default for d in drones], dtype=float)


class _Path:
    """A polyline with arc-length lookup (for cutting it and pricing the trips to its pieces)."""

    def __init__(self, points: FloatArray) -> None:
        self.p = points
        self.seg = np.hypot(*np.diff(points, axis=0).T) if len(points) > 1 else np.zeros(0)
        self.cum = np.concatenate([[0.0], np.cumsum(self.seg)])
        self.total = float(self.cum[-1])

    def at(self, s: float) -> FloatArray:
        if len(self.seg) == 0:
            return self.p[0]
        s = min(max(s, 0.0), self.total)
        k = min(int(np.searchsorted(self.cum, s, side="right") - 1), len(self.seg) - 1)
        t = 0.0 if self.seg[k] == 0 else (s - self.cum[k]) / self.seg[k]
        return self.p[k] + t * (self.p[k + 1] - self.p[k])

    def longest_from(self, start: float, home: FloatArray, budget: float) -> float:
        """The longest piece from ``start`` a drone with ``budget`` metres can fly, home to home.

        Its cost L + |p(start + L) - home| never decreases with L (the return leg shrinks at most
        as fast as the piece grows), so bisection finds the limit.
        """
        left = budget - float(np.hypot(*(self.at(start) - home)))
        rest = self.total - start

        def cost(length: float) -> float:
            return length + float(np.hypot(*(self.at(start + length) - home)))

        if left <= 0 or rest <= 0:
            return 0.0
        if cost(rest) <= left:
            return rest
        lo, hi = 0.0, rest
        if cost(0.0) > left:
            return 0.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if cost(mid) <= left:
                lo = mid
            else:
                hi = mid
        return lo


def path_division(
    points: ArrayLike,
    drones: Sequence[DroneSpec],
    home: ArrayLike | None = None,
    fractions: ArrayLike | None = None,
    allow_partial: bool = False,
) -> list[PathShare]:
    """Seed 000 Alg. 3: consecutive pieces of one path, sized by capability after the home trip.

    Each drone's share is proportional to C' = its range less its own trip (home to its piece's
    start, the piece's end back home), priced on the real pieces rather than on the paper's bound
    (twice the farthest waypoint), which refused paths the fleet can fly. Pieces are laid out in
    drone order; a drone whose share would not fit its range takes the longest piece it can fly
    and the rest moves on to the drones after it (the scale of the shares is bisected so the
    pieces add up to the path). When even every drone flying as far as it can leaves path over,
    the shortfall is exact: :class:`InsufficientCapabilityError`, or with ``allow_partial`` the
    plan that flies the most of the path.
    """
    path = _Path(np.asarray(points, dtype=float).reshape(-1, 2))
    homes = _homes(drones, home)
    ranges = np.array([d.range_m for d in drones])
    total = path.total
    n = len(drones)

    def lay_out(weights: FloatArray, scale: float) -> FloatArray:
        lengths = np.zeros(n)
        start = 0.0
        for i in range(n):
            want = min(scale * weights[i], total - start)
            lengths[i] = min(want, path.longest_from(start, homes[i], ranges[i]))
            start += lengths[i]
        return lengths

    def trips(lengths: FloatArray) -> FloatArray:
        starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        return np.array(
            [
                0.0 if ln <= 0 else float(np.hypot(*(path.at(s) - h)) + np.hypot(*(path.at(s + ln) - h)))
                for s, ln, h in zip(starts, lengths, homes, strict=True)
            ]
        )

    greedy = lay_out(np.ones(n), total)  # every drone as far as it can: the most the fleet can fly
    flown = float(greedy.sum())
    if flown < total - 1e-6 * max(total, 1.0):
        short = total - flown
        if flown <= 1e-9:
            raise InsufficientCapabilityError(
                "no drone can even reach the area and return", shortfall_m=total
            )
        if not allow_partial:
            raise InsufficientCapabilityError(
                f"the fleet can survey {flown:.1f} m of a {total:.1f} m path; "
                f"{short:.1f} m would be left unflown (add drones, charge batteries or shrink the area)",
                shortfall_m=short,
            )
        lengths = greedy
    else:
        if fractions is not None:
            weights = np.asarray(fractions, dtype=float).reshape(n)
            rounds = 1
        else:
            near = np.array([2 * float(np.hypot(*(path.p - h).T).min()) for h in homes])
            weights = np.maximum(ranges - near, 1e-9)
            rounds = 4
        lengths = greedy
        for _ in range(rounds):
            w = weights / weights.sum()
            lo, hi = 0.0, total / float(w.min())
            for _ in range(60):  # the pieces' sum grows with the scale; bisect to the whole path
                mid = 0.5 * (lo + hi)
                if lay_out(w, mid).sum() >= total - 1e-9 * max(total, 1.0):
                    hi = mid
                else:
                    lo = mid
            lengths = lay_out(w, hi)
            if fractions is not None:
                break
            weights = np.maximum(ranges - trips(lengths), 1e-9)  # C' on the real trips
        last = int(np.flatnonzero(lengths > 0)[-1])
        lengths[last] += total - float(lengths.sum())  # bisection leaves a hair of the path over
    pieces = cut_path(path.p, lengths)
    return [
        PathShare(d.name, pc, float(ln), _trip(pc, h), d.range_m)
        for d, pc, ln, h in zip(drones, pieces, lengths, homes, strict=True)
    ]


def _trip(piece: FloatArray, home: FloatArray) -> float:
    if len(piece) == 0:
        return 0.0
    return float(np.hypot(*(piece[0] - home)) + np.hypot(*(piece[-1] - home)))


def cut_by_area(q: BaseGeometry, fractions: ArrayLike, tol: float = 1e-6, max_iter: int = 100) -> list[float]:
    """Ordinates y_1 < ... < y_{n-1} splitting ``q`` bottom-up into slices with these area fractions.

    Bisection on each cut (area below y is monotone in y) until the slice area is within
    ``tol x total area`` of its target; the paper's Alg. 4 instead halves an area guess
    between recursive calls and stops within an unspecified +-Delta.
    """
    c = np.asarray(fractions, dtype=float)
    c = c / c.sum()
    minx, ymin, maxx, ymax = q.bounds
    total = q.area

    def below(y: float) -> float:
        return float(q.intersection(box(minx - 1, ymin - 1, maxx + 1, y)).area)

    cuts = []
    lo_bound = ymin
    for target in np.cumsum(c)[:-1] * total:
        lo, hi = lo_bound, ymax
        mid = 0.5 * (lo + hi)
        for _ in range(max_iter):
            mid = 0.5 * (lo + hi)
            a = below(mid)
            if abs(a - target) <= tol * total:
                break
            if a < target:
                lo = mid
            else:
                hi = mid
        cuts.append(mid)
        lo_bound = mid
    return cuts


@dataclass(frozen=True)
class RegionShare:
    """One drone's slice of the area (local east/north) and its share."""

    drone: str
    region: BaseGeometry
    fraction: float
    transit_bound_m: float
    usable_m: float


def region_division(
    vertices: ArrayLike,
    drones: Sequence[DroneSpec],
    angle: float,
    home: ArrayLike | None = None,
    fractions: ArrayLike | None = None,
    tol: float = 1e-6,
) -> list[RegionShare]:
    """Seed 000 Alg. 4: slices of the area across its minimum height, areas proportional to C'.

    C_h is twice the distance from home to the farthest vertex of the area (the paper's bound).
    ``angle`` is the sweep rotation (legs horizontal after rotating by it). Drone i gets the
    i-th slice from the bottom of the rotated area.
    """
    p = np.asarray(vertices, dtype=float).reshape(-1, 2)
    homes = _homes(drones, home)
    ranges = np.array([d.range_m for d in drones])
    far = np.array([2 * float(np.hypot(*(p - h).T).max()) for h in homes])
    usable = ranges - far
    bad = [d.name for d, u in zip(drones, usable, strict=True) if u <= 0]
    if bad:
        raise InsufficientCapabilityError(f"{', '.join(bad)} cannot reach the area and return home")
    frac = capability_fractions(usable) if fractions is None else np.asarray(fractions, float)
    frac = frac / frac.sum()
    c = centroid(p)
    poly = Polygon(p)
    q = Polygon(rotate(p, angle, c))
    if not q.is_valid:
        q = q.buffer(0)
    cuts = cut_by_area(q, frac, tol)
    minx, ymin, maxx, ymax = q.bounds
    edges = [ymin - 1.0, *cuts, ymax + 1.0]
    shares = []
    for i, d in enumerate(drones):
        sl = q.intersection(box(minx - 1, edges[i], maxx + 1, edges[i + 1]))
        world = _rotate_geom(sl, -angle, c)
        shares.append(RegionShare(d.name, world, float(sl.area / q.area), float(far[i]), float(usable[i])))
    assert math.isclose(sum(s.region.area for s in shares), poly.area, rel_tol=1e-6)
    return shares


def _rotate_geom(g: BaseGeometry, angle: float, about: tuple[float, float]) -> BaseGeometry:
    from shapely import affinity

    return affinity.rotate(g, angle, origin=about, use_radians=True)

"""Coverage of an area by flown (or planned) tracks, as in seed 001 Tables 2-3, plus track simulation.

Footprint model: a disc of radius swath/2 swept along the track (per-segment buffers, unioned).
Covered % = area seen / area; overlap % = area seen by two or more passes / area, where a pass
is a run of the track between turns sharper than 45 degrees, swept with flat ends (so that
consecutive passes meeting at a turn do not count as overlap); gaps are returned as polygons
(local metres) so a rescheduler can plan them again.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import ArrayLike
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from gcs.planning.geodesy import FloatArray
from gcs.planning.patterns import dedupe, swept_footprint

# seed 000 eq. 9 (fit over 0.5-5 m/s)
EQ9_A, EQ9_B, EQ9_C = 0.1356, -0.008092, 1.051
EQ9_RANGE = (0.5, 5.0)


def path_error_m(speed: float, extrapolate: bool = False) -> float:
    """Seed 000 eq. 9: mean deviation from the planned line (m) at a given speed (m/s).

    error = 0.1356 sin(v - pi) - 0.008092 (v - 10)^2 + 1.051. The fit comes from flights at
    0.5-5 m/s; its negative quadratic term makes it fall and go negative at high speed, so
    outside that range we refuse unless ``extrapolate`` (then clamp at zero).
    """
    if not extrapolate and not EQ9_RANGE[0] <= speed <= EQ9_RANGE[1]:
        raise ValueError(f"eq. 9 was fitted for {EQ9_RANGE[0]}-{EQ9_RANGE[1]} m/s, not {speed} m/s")
    err = EQ9_A * math.sin(speed - math.pi) + EQ9_B * (speed - 10.0) ** 2 + EQ9_C
    return max(err, 0.0)


@dataclass(frozen=True)
class CoverageReport:
    """Result of :func:`evaluate_coverage`; ``gaps`` are the unseen parts of the area."""

    area_m2: float
    covered_m2: float
    overlap_m2: float
    gaps: list[Polygon]

    @property
    def covered_pct(self) -> float:
        return 100.0 * self.covered_m2 / self.area_m2

    @property
    def overlap_pct(self) -> float:
        return 100.0 * self.overlap_m2 / self.area_m2

    @property
    def gap_m2(self) -> float:
        return self.area_m2 - self.covered_m2

    def summary(self) -> dict[str, float | int]:
        return {
            "covered_pct": round(self.covered_pct, 3),
            "overlap_pct": round(self.overlap_pct, 3),
            "gap_m2": round(self.gap_m2, 3),
            "gaps": len(self.gaps),
        }


def _flat_footprint(points: FloatArray, half: float) -> BaseGeometry:
    segs = shapely.linestrings(np.stack([points[:-1], points[1:]], axis=1))
    return shapely.union_all(shapely.buffer(segs, half, cap_style="flat"))


def split_passes(track: ArrayLike, turn_deg: float = 45.0) -> list[FloatArray]:
    """Cut a track at heading changes sharper than ``turn_deg`` (each piece is one pass)."""
    p = dedupe(track)
    if len(p) < 3:
        return [p]
    d = np.diff(p, axis=0)
    h = np.arctan2(d[:, 1], d[:, 0])
    dh = np.abs((np.diff(h) + math.pi) % (2 * math.pi) - math.pi)
    cuts = np.nonzero(dh > math.radians(turn_deg))[0] + 1
    out, k0 = [], 0
    for k in cuts:
        out.append(p[k0 : k + 1])
        k0 = int(k)
    out.append(p[k0:])
    return out


def evaluate_coverage(
    area: BaseGeometry | ArrayLike,
    tracks: Sequence[ArrayLike],
    swath: float,
    min_gap_m2: float = 0.0,
) -> CoverageReport:
    """Covered %, overlap % and gap polygons of ``area`` seen from ``tracks`` with footprint ``swath``."""
    poly = area if isinstance(area, BaseGeometry) else Polygon(np.asarray(area, dtype=float))
    half = swath / 2
    passes = [ps for t in tracks for ps in split_passes(t) if len(ps) >= 1]
    seen = swept_footprint(np.vstack([dedupe(t) for t in tracks]), half) if tracks else Polygon()
    if len(tracks) > 1:
        seen = shapely.union_all([swept_footprint(t, half) for t in tracks])
    seen = seen.intersection(poly)
    covered = float(seen.area)
    prints = [_flat_footprint(ps, half).intersection(poly) for ps in passes if len(ps) >= 2]
    # area seen by >= 2 passes: pairwise intersections of footprints that touch (STRtree)
    tree = shapely.STRtree(prints)
    doubles = []
    for i, fp in enumerate(prints):
        for j in tree.query(fp):
            if j > i:
                inter = fp.intersection(prints[j])
                if inter.area > 0:
                    doubles.append(inter)
    overlap = float(shapely.union_all(doubles).area) if doubles else 0.0
    missed = poly.difference(seen)
    gaps = [g for g in getattr(missed, "geoms", [missed]) if g.geom_type == "Polygon" and g.area > min_gap_m2]
    return CoverageReport(float(poly.area), covered, overlap, gaps)


def simulate_track(
    points: ArrayLike,
    speed: float,
    accel: float = 1.0,
    seed: int = 0,
    error_m: float | None = None,
) -> tuple[FloatArray, float]:
    """A flown track for a planned polyline under eq. 9, and its flight time (s).

    Each leg between waypoints is flown with a trapezoidal speed profile (accelerate at
    ``accel``, cruise at ``speed``, brake to stop at the waypoint), so short legs are flown
    slower; the leg is displaced sideways by a normal draw with standard deviation
    eq. 9(mean leg speed) (or ``error_m``). Short legs thus drift less but take longer,
    which is the trade-off seed 001 Table 2 reports for segmented paths.
    """
    p = dedupe(points)
    rng = np.random.default_rng(seed)
    out: list[FloatArray] = []
    time_s = 0.0
    for a, b in itertools.pairwise(p):
        d = b - a
        length = float(np.hypot(*d))
        if length >= speed * speed / accel:
            t = length / speed + speed / accel
        else:
            t = 2 * math.sqrt(length / accel)
        time_s += t
        v_mean = length / t
        sigma = error_m if error_m is not None else path_error_m(min(max(v_mean, EQ9_RANGE[0]), EQ9_RANGE[1]))
        normal = np.array([-d[1], d[0]]) / length
        off = rng.normal(0.0, sigma) * normal
        out.append(np.array([a + off, b + off]))
    if not out:
        return p.copy(), 0.0
    return np.vstack(out), time_s

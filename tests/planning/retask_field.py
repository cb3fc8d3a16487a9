"""The re-task field shared by tests/planning/test_retask.py and test_scattered_gaps.py: a 200 x 100 m
field split into four 50 m wide columns, one lawnmower per drone (swath 10 m), the tracks flown so far
rasterised with seen_grid exactly as the daemon does."""

from __future__ import annotations

import numpy as np

from gcs.planning.geodesy import LocalFrame
from gcs.planning.retask import Candidate
from gcs.planning.seen import SeenGrid, seen_grid

FRAME = LocalFrame(47.0, 8.0)
SWATH = 10.0
FIELD = [(float(a), float(b)) for a, b in FRAME.points_to_geodetic([(0, 0), (200, 0), (200, 100), (0, 100)])]


def ll(points_en: list[tuple[float, float]]) -> list[tuple[float, float]]:
    return [(float(a), float(b)) for a, b in FRAME.points_to_geodetic(points_en)]


def column(k: int) -> list[tuple[float, float]]:
    """Drone k's share: north-south legs over x in [50k, 50k + 50], 5 m from each side."""
    pts: list[tuple[float, float]] = []
    for j, x in enumerate(np.arange(50 * k + SWATH / 2, 50 * (k + 1), SWATH)):
        ys = (0.0, 100.0) if j % 2 == 0 else (100.0, 0.0)
        pts += [(float(x), ys[0]), (float(x), ys[1])]
    return pts


def cut(points: list[tuple[float, float]], fraction: float) -> list[tuple[float, float]]:
    """The first ``fraction`` of a polyline by length (what a drone flew before it dropped)."""
    from shapely.geometry import LineString
    from shapely.ops import substring

    line = LineString(points)
    return [(float(x), float(y)) for x, y in substring(line, 0, fraction * line.length).coords]


def track(points_en: list[tuple[float, float]]) -> list[tuple[float, float, float]]:
    return [(a, b, 20.0) for a, b in ll(points_en)]


def candidates(margin_wh: float = 50.0) -> list[Candidate]:
    home = ll([(100.0, -20.0)])[0]
    return [
        Candidate(f"drone-{k + 1}", ll([column(k)[-1]])[0], home, margin_wh, 5.0, 300.0) for k in (0, 2, 3)
    ]


def situation(fraction: float) -> tuple[SeenGrid, list[tuple[float, float]]]:
    tracks = [track(column(k)) for k in (0, 2, 3)] + [track(cut(column(1), fraction))]
    return seen_grid(FIELD, tracks, SWATH, 20.0), ll(column(1))

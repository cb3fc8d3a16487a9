"""The live coverage raster (gcs.planning.seen): footprint by height (eq. 5), capsules, coverage %."""

import numpy as np
import pytest

from gcs.planning.geodesy import LocalFrame
from gcs.planning.seen import footprint_half_widths, seen_grid

FRAME = LocalFrame(47.0, 8.0)
SQUARE = [(float(a), float(b)) for a, b in FRAME.points_to_geodetic([(0, 0), (100, 0), (100, 100), (0, 100)])]


def _track(points_en: list[tuple[float, float]], alt: float) -> list[tuple[float, float, float]]:
    return [(float(a), float(b), alt) for a, b in FRAME.points_to_geodetic(points_en)]


def _lawnmower(step: float, alt: float) -> list[tuple[float, float, float]]:
    pts: list[tuple[float, float]] = []
    for k, y in enumerate(np.arange(step / 2, 100, step)):
        xs = (0.0, 100.0) if k % 2 == 0 else (100.0, 0.0)
        pts += [(xs[0], float(y)), (xs[1], float(y))]
    return _track(pts, alt)


def test_full_lawnmower_sees_everything_and_half_of_it_half() -> None:
    full = _lawnmower(20.0, 30.0)
    grid = seen_grid(SQUARE, [full], swath_m=20.0, altitude_m=30.0)
    assert grid.covered_pct == pytest.approx(100.0, abs=0.5)
    assert grid.area_m2 == pytest.approx(10_000, rel=0.02)
    half = full[:4]  # the first two legs: y up to 40 m
    g2 = seen_grid(SQUARE, [half], swath_m=20.0, altitude_m=30.0)
    assert 38.0 <= g2.covered_pct <= 42.0
    assert "." in "".join(g2.rows()) and "#" in "".join(g2.rows())
    assert g2.unseen_geojson()["type"] == "MultiPolygon" and g2.unseen_geojson()["coordinates"]


def test_footprint_shrinks_with_height_and_ground_samples_see_nothing() -> None:
    half = footprint_half_widths(np.array([30.0, 15.0, 0.1, np.nan]), swath_m=20.0, altitude_m=30.0)
    assert half.tolist()[:3] == pytest.approx([10.0, 5.0, 0.0])
    assert half[3] == 0.0
    # the same lawnmower flown at half height sees bands half as wide: about half the area
    low = seen_grid(SQUARE, [_lawnmower(20.0, 15.0)], swath_m=20.0, altitude_m=30.0)
    assert 45.0 <= low.covered_pct <= 60.0
    ground = seen_grid(SQUARE, [_lawnmower(20.0, 0.0)], swath_m=20.0, altitude_m=30.0)
    assert ground.covered_pct == 0.0


def test_empty_and_bad_inputs() -> None:
    assert seen_grid(SQUARE, [], swath_m=20.0).covered_pct == 0.0
    with pytest.raises(ValueError, match="swath"):
        seen_grid(SQUARE, [], swath_m=0.0)
    with pytest.raises(ValueError, match="three"):
        seen_grid(SQUARE[:2], [], swath_m=10.0)

import numpy as np
import pytest
from hypothesis import given, settings
from shapely.geometry import Polygon

from gcs.planning.decompose import boustrophedon_cells, cover_area
from gcs.planning.patterns import swept_footprint

from .conftest import star_polygons

U = [(0, 0), (300, 0), (300, 200), (200, 200), (200, 50), (100, 50), (100, 200), (0, 200)]


@settings(max_examples=30, deadline=None)
@given(star_polygons())
def test_decomposition_never_leaves_the_interior_uncovered(poly):
    step = 15.0
    sw = cover_area(poly, step)
    P = Polygon(poly)
    assert P.is_valid
    missed = P.difference(swept_footprint(sw.points, step / 2 * (1 + 1e-9) + 1e-9))
    assert missed.area <= 1e-6 * P.area


def test_cells_tile_the_area():
    q = Polygon(U)
    cells = boustrophedon_cells(q)
    assert len(cells) == 3
    assert sum(c.area for c in cells) == pytest.approx(q.area)


def test_u_shape_flies_less_than_hull_filling():
    sw = cover_area(U, 20.0, angle=np.pi / 2)  # legs north-south, along the prongs
    assert sw.meta["cells"] >= 2
    assert sw.length < sw.meta["hull_length_m"]
    assert sw.meta["area_m2"] < sw.meta["hull_area_m2"]
    P = Polygon(U)
    assert P.difference(swept_footprint(sw.points, 10.0 + 1e-6)).area == pytest.approx(0.0, abs=1e-6)

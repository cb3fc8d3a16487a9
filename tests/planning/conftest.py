import numpy as np
from hypothesis import strategies as st


@st.composite
def convex_polygons(draw, max_size: float = 400.0):
    """Random convex polygons: hull of random points, scaled anisotropically and rotated."""
    n = draw(st.integers(3, 12))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, 1, (n, 2)) * [draw(st.floats(20, max_size)), draw(st.floats(5, max_size))]
    from scipy.spatial import ConvexHull

    hull = pts[ConvexHull(pts).vertices]
    a = draw(st.floats(0, np.pi))
    c, s = np.cos(a), np.sin(a)
    return hull @ np.array([[c, s], [-s, c]])


@st.composite
def star_polygons(draw):
    """Random simple (usually concave) star-shaped polygons."""
    n = draw(st.integers(5, 30))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    # one vertex per angular sector: star-shaped about the origin, hence simple
    ang = (np.arange(n) + rng.uniform(0.0, 0.8, n)) * 2 * np.pi / n
    r = rng.uniform(30, 250, n)
    return np.column_stack([r * np.cos(ang), r * np.sin(ang)])

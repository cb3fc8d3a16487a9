import numpy as np
import pytest

from gcs.planning.coverage import evaluate_coverage, path_error_m, simulate_track, split_passes
from gcs.planning.patterns import zigzag

RECT = [(0, 0), (200, 0), (200, 150), (0, 150)]


def test_eq9_values():
    assert path_error_m(3.0) == pytest.approx(0.1356 * np.sin(3 - np.pi) - 0.008092 * 49 + 1.051)
    assert path_error_m(5.0) == pytest.approx(0.97873, abs=1e-4)
    assert path_error_m(1.92) == pytest.approx(0.48, abs=0.1)  # paper measured 0.48 m at 1.92 m/s
    with pytest.raises(ValueError):
        path_error_m(12.0)


def test_planned_zigzag_fully_covered_and_gaps_returned():
    sw = zigzag(RECT, 20.0)
    rep = evaluate_coverage(RECT, [sw.points], 20.0)
    assert rep.covered_pct == pytest.approx(100.0)
    assert rep.gaps == []
    # drop the middle legs: the hole comes back as a polygon
    rep2 = evaluate_coverage(RECT, [sw.lines[0].reshape(-1, 2), sw.lines[-1].reshape(-1, 2)], 20.0)
    assert rep2.covered_pct < 40
    assert rep2.gaps and sum(g.area for g in rep2.gaps) == pytest.approx(rep2.gap_m2, rel=1e-6)


def test_overlap_grows_with_side_overlap():
    tight = zigzag(RECT, 10.0)
    loose = zigzag(RECT, 20.0)
    o_tight = evaluate_coverage(RECT, [tight.points], 20.0).overlap_pct
    o_loose = evaluate_coverage(RECT, [loose.points], 20.0).overlap_pct
    assert o_tight > o_loose + 20


def test_simulated_error_creates_gaps_at_speed():
    rect = [(0, 0), (200, 0), (200, 160), (0, 160)]  # 8 legs exactly 20 m apart: zero side overlap
    sw = zigzag(rect, 20.0)
    assert sw.spacing == pytest.approx(20.0)
    slow, t_slow = simulate_track(sw.points, 1.0, seed=1)
    fast, t_fast = simulate_track(sw.points, 5.0, seed=1)
    assert t_slow > t_fast
    c_slow = evaluate_coverage(rect, [slow], 20.0).covered_pct
    c_fast = evaluate_coverage(rect, [fast], 20.0).covered_pct
    assert c_fast < 100.0 and c_slow >= c_fast - 0.5


def test_split_passes():
    assert len(split_passes([(0, 0), (10, 0), (10, 10), (0, 10)])) == 3

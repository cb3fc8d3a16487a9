"""Scattered gaps of a dropped drone's share (gcs.planning.scattered, gcs.planning.retask): RSA pieces
by region division instead of one route along the share.

Worked example (the field, shares and drones of tests/planning/test_retask.py: 200 x 100 m, four
50 m columns flown north-south, swath 10 m). Drone-2 flew its whole column (legs at x = 55, 65, 75,
85, 95) but saw nothing over y = 40-60 of its second leg (x = 65, flown southward) and of its fifth
(x = 95, northward): two zones about 10 m wide and 10-20 m long (the footprints around the ends of a
hole close it by up to 5 m each side), 20 m apart across x = 70-90, which the third and fourth legs saw.

* One route along the share from the first gap to the last flies the rest of leg 2 from y ~ 60, legs
  3 and 4 whole, and leg 5 up to y ~ 60: computed 352.5 m, of which ~ 320 m over cells already seen.
* As RSA pieces: 250 m2 unseen (cells 2.5 m) in two zones; each zone's covering rectangle is
  10 x 15 m, flown as one 15 m channel along its length. Divided by region, drone-1 (whose way home
  passes the first) flies one for 1.6 m extra, drone-3 the other for 15.2 m extra: 30 m surveyed
  instead of 352.5 m.
"""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import LineString

from gcs.planning.retask import gap_route, propose_retask, share_gap
from gcs.planning.scattered import chain, gap_pieces
from gcs.planning.seen import SeenGrid, seen_grid
from tests.planning.retask_field import FIELD, SWATH, candidates, column, ll, situation, track

HOLES = ((1, 60.0, 40.0), (4, 40.0, 60.0))  # (leg index in the column, from y, to y) not seen


def _flown_with_holes() -> list[list[tuple[float, float]]]:
    """Drone-2's column as flown: the polyline split where it saw nothing."""
    pts = column(1)
    pieces: list[list[tuple[float, float]]] = [[pts[0]]]
    for leg in range(len(pts) // 2):
        (x, y0), (_, y1) = pts[2 * leg], pts[2 * leg + 1]
        hole = next(((a, b) for k, a, b in HOLES if k == leg), None)
        if hole is None:
            pieces[-1] += [(x, y0), (x, y1)]
        else:
            pieces[-1] += [(x, y0), (x, hole[0])]
            pieces.append([(x, hole[1]), (x, y1)])
    return pieces


def _holes() -> tuple[SeenGrid, list[tuple[float, float]]]:
    tracks = [track(column(k)) for k in (0, 2, 3)] + [track(p) for p in _flown_with_holes()]
    return seen_grid(FIELD, tracks, SWATH, 20.0), ll(column(1))


def test_two_holes_are_two_pieces_whose_channels_cover_them() -> None:
    grid, share = _holes()
    _, gap = share_gap(grid, share, SWATH)
    gap_m2 = float(gap.sum()) * grid.cell_m**2
    assert 2 * 10 * 10 <= gap_m2 <= 2 * 10 * 20  # two holes, each 10 m wide and 10-20 m long
    line = LineString(grid.frame.points_to_local(share))
    pieces = gap_pieces(grid, gap, line, SWATH)
    assert len(pieces) == 2
    assert pieces[0].order < pieces[1].order  # the share's flying order: leg 2's hole first
    for piece in pieces:
        sides = sorted(np.hypot(*np.diff(np.vstack([piece.rectangle, piece.rectangle[:1]]), axis=0).T))
        assert sides[0] == pytest.approx(10.0, abs=grid.cell_m) and 10.0 - 1e-6 <= sides[-1] <= 20.0 + 1e-6
        assert 10.0 - 1e-6 <= piece.length <= 20.0 + 1e-6  # one channel along its length
    path, survey = chain(grid.frame.local_point(*ll([(75.0, -20.0)])[0]), pieces)  # the grid's own frame
    assert survey == pytest.approx(sum(p.length for p in pieces))
    # the chained channels see every gap cell
    lat, lon = grid.frame.to_geodetic(*path.T)
    seen = seen_grid(
        FIELD, [[(float(a), float(b), 20.0) for a, b in zip(lat, lon, strict=True)]], SWATH, 20.0
    )
    assert seen.seen.shape == gap.shape and gap.any() and not (gap & ~seen.seen).any()


def test_the_proposal_flies_the_pieces_not_one_route_over_seen_legs() -> None:
    grid, share = _holes()
    _, gap = share_gap(grid, share, SWATH)
    route = gap_route(grid, share, gap, SWATH)
    assert route is not None and 300.0 <= route.length <= 400.0  # one route: 352.5 m, mostly seen
    proposal = propose_retask(grid, "drone-2", share, SWATH, candidates())
    assert proposal.verdict == "proposed" and proposal.pieces == 2, proposal.reason
    assert "in 2 pieces" in proposal.reason
    surveyed = sum(leg.survey_m for leg in proposal.legs)
    assert surveyed == pytest.approx(30.0, abs=5.0)  # two 15 m channels, against 352.5 m for the route
    assert len(proposal.legs) == 2 and len({leg.ident for leg in proposal.legs}) == 2  # one piece each
    assert all(leg.energy_wh <= leg.margin_wh for leg in proposal.legs)
    # flying the proposal closes the gap: the field is seen whole
    flown = [track(column(k)) for k in (0, 2, 3)] + [track(p) for p in _flown_with_holes()]
    added = [[(a, b, 20.0) for a, b in leg.points] for leg in proposal.legs]
    assert seen_grid(FIELD, flown + added, SWATH, 20.0).covered_pct >= 99.9


def test_one_contiguous_gap_stays_one_route() -> None:
    """Drone-2 dropped after 40 % of its share: the rest is one zone, flown along the share."""
    grid, share = situation(0.4)
    proposal = propose_retask(grid, "drone-2", share, SWATH, candidates())
    assert proposal.verdict == "proposed" and proposal.pieces == 1 and "pieces" not in proposal.reason

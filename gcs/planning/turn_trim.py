"""Leg ends cut back where the turn between two legs already sees the area (issue 27).

The strip rule (:func:`gcs.planning.patterns.strip_extent`) runs every leg to the area's extent over
its whole strip ``y +- spacing/2``, because a leg alone must see its strip. But a boustrophedon
turns at every leg end but the first and the last, and the turn (the straight jog from one leg's end
to the next leg's start) is flown at survey height with the sensor on: it sees the ground within half
a spacing of it, which is the half strip of each of the two legs that faces the other. So each leg
end next to a turn only has to reach the area's extent over its *own* half strip, the one facing away
from the turn; the jog, now slanted along the boundary, sees the other half. On a straight edge at an
angle ``a`` to the legs this saves ``spacing/2 * cot(a)`` per turn, half of the strip rule's overshoot;
an edge square to the legs saves nothing (the jog already runs along it).

The argument holds for evenly spaced legs of a convex piece; cells clipped at their ends and legs flown
in several pieces are not covered by it, so :func:`trim_at_turns` checks the trimmed path against the
area with the swept footprint and keeps the strip rule's legs when any point would be left unseen.
Pure functions in the sweep frame (legs horizontal).
"""

from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from gcs.planning.geodesy import FloatArray

Leg = tuple[float, float, float]  # (y, x0, x1), x0 <= x1
Extent = tuple[float, float] | None
UNSEEN_TOL = 1e-7  # unseen area allowed by the check, as a fraction of the area (rounding only)
MAX_RESTORE_ROUNDS = 4  # checks of a trimmed path before falling back to the strip rule


def half_strip_extents(
    poly: Polygon, ys: list[float], strip_ys: list[float], half: float
) -> list[tuple[Extent, Extent]]:
    """Per leg, the x-ranges of the polygon in its strip (``strip_y +- half``) below and above the leg's
    ordinate ``y`` (None where that half holds no area); one vectorised intersection for all legs."""
    minx, _, maxx, _ = poly.bounds
    eps = min(1e-6, half * 1e-3)
    y = np.asarray(ys, dtype=float)
    sy = np.asarray(strip_ys, dtype=float)
    lo = np.concatenate([sy - half + eps, y])
    hi = np.concatenate([y, sy + half - eps])
    ok = hi > lo
    pieces = shapely.intersection(poly, shapely.box(minx - 1.0, lo, maxx + 1.0, np.where(ok, hi, lo + 1e-9)))
    ok &= shapely.area(pieces) > 0.0
    b = shapely.bounds(pieces)
    ext: list[Extent] = [(float(b[i, 0]), float(b[i, 2])) if ok[i] else None for i in range(len(lo))]
    n = len(y)
    return [(ext[i], ext[n + i]) for i in range(n)]


def _ys(legs: list[list[Leg]], leg_ys: list[float] | None) -> list[float]:
    return [leg[0][0] for leg in legs] if leg_ys is None else leg_ys


def trimmed_ends(
    legs: list[list[Leg]],
    halves: list[tuple[Extent, Extent]],
    left_to_right_first: bool,
    leg_ys: list[float] | None = None,
) -> list[list[Leg]]:
    """``legs`` (each one straight piece at the leg's ordinate, or several for a leg whose end is
    flown as a separate piece, see :func:`gcs.planning.decompose.leg_pieces`) in flight order, leg 0
    flown left to right when ``left_to_right_first``: each end next to a turn whose piece lies on the
    leg's ordinate (``leg_ys``, default the first piece's) is cut to the extent of the leg's half
    strip facing away from that turn (never past the piece's other end, never longer than before).
    ``halves[i]`` is leg i's (below, above) half-strip extent."""
    ys = _ys(legs, leg_ys)
    out = [[list(p) for p in leg] for leg in legs]
    for i in range(len(legs) - 1):
        right = (i % 2 == 0) == left_to_right_first  # leg i ends on the right and turns into leg i+1
        up = ys[i + 1] > ys[i]
        # leg i's own half faces away from leg i+1, leg i+1's faces away from leg i
        own_i = halves[i][0] if up else halves[i][1]
        own_next = halves[i + 1][1] if up else halves[i + 1][0]
        for j, own in ((i, own_i), (i + 1, own_next)):
            piece = out[j][-1] if right else out[j][0]
            if own is None or abs(piece[0] - ys[j]) > 1e-9:
                continue
            if right:
                piece[2] = max(piece[1], min(piece[2], own[1]))
            else:
                piece[1] = min(piece[2], max(piece[1], own[0]))
    return [[(a, b, c) for a, b, c in leg] for leg in out]


def flown(legs: list[list[Leg]], left_to_right_first: bool) -> FloatArray:
    """(M, 2, 2) straight parts of the legs, flown alternately left to right and right to left."""
    out: list[list[list[float]]] = []
    for k, leg in enumerate(legs):
        if (k % 2 == 0) != left_to_right_first:
            out.extend([[x1, yy], [x0, yy]] for yy, x0, x1 in reversed(leg))
        else:
            out.extend([[x0, yy], [x1, yy]] for yy, x0, x1 in leg)
    return np.asarray(out, dtype=float).reshape(-1, 2, 2)


def unseen(poly: Polygon, lines: FloatArray, half: float) -> BaseGeometry:
    """The part of ``poly`` farther than ``half`` from the path through ``lines`` (legs and jogs)."""
    from gcs.planning.patterns import swept_footprint

    return poly.difference(swept_footprint(lines.reshape(-1, 2), half * (1 + 1e-9)))


def shortened(legs: list[list[Leg]], by: float, leg_ys: list[float] | None = None) -> list[list[Leg]]:
    """Both outer ends of every leg moved ``by`` inwards where their piece lies on the leg's ordinate
    (a piece shorter than ``2 by`` becomes its midpoint): with a footprint wider than the strip,
    ``by`` of the strip's corner is seen from the end."""
    if by <= 0.0:
        return legs
    out: list[list[Leg]] = []
    for leg, y in zip(legs, _ys(legs, leg_ys), strict=True):
        pieces = [list(p) for p in leg]
        first, last = pieces[0], pieces[-1]
        d0 = min(by, (first[2] - first[1]) / (2 if len(pieces) == 1 else 1))
        d1 = min(by, (last[2] - last[1]) / (2 if len(pieces) == 1 else 1))
        if abs(first[0] - y) <= 1e-9:
            first[1] += d0
        if abs(last[0] - y) <= 1e-9:
            last[2] -= d1
        out.append([(a, b, c) for a, b, c in pieces])
    return out


def trim_at_turns(
    poly: Polygon,
    legs: list[list[Leg]],
    strip_ys: list[float],
    half: float,
    left_to_right_first: bool,
    reach: float | None = None,
    *,
    check: bool = True,
    halves: list[tuple[Extent, Extent]] | None = None,
    leg_ys: list[float] | None = None,
) -> FloatArray:
    """The legs (flight order) flown with ends cut back where that still sees all of ``poly`` within
    ``reach`` (the footprint's half width, default ``half``, half the line spacing): at the turns (see
    the module), and by ``sqrt(reach^2 - half^2)`` at every end when the footprint is wider than the
    strip. A leg whose strip holds an unseen point gets its strip-rule ends back (it then sees its
    strip alone), at most ``MAX_RESTORE_ROUNDS`` times, then every leg does. ``check=False`` skips
    the check (an optimistic length for comparing sweep angles, never a path to fly); ``halves``
    passes :func:`half_strip_extents` of these legs when the caller already has them; ``leg_ys`` are
    the legs' ordinates when a leg's first piece is not on it (see :func:`trimmed_ends`)."""
    reach = half if reach is None else max(reach, half)
    plain = flown(legs, left_to_right_first)
    if len(legs) > 1:
        if halves is None:
            halves = half_strip_extents(poly, _ys(legs, leg_ys), strip_ys, half)
        cut = trimmed_ends(legs, halves, left_to_right_first, leg_ys)
    else:
        cut = legs
    # the corner at the cut lies exactly at ``reach``: keep it inside the 32-gon that swept_footprint
    # draws for the disc (inscribed radius reach cos(pi/32)), so the plan's own check sees it
    disc = reach * math.cos(math.pi / 32)
    cut = shortened(cut, math.sqrt(max(disc * disc - half * half, 0.0)), leg_ys)
    tol = UNSEEN_TOL * max(poly.area, 1.0)
    sy = np.asarray(strip_ys)
    for _ in range(MAX_RESTORE_ROUNDS):
        if cut == legs:
            return plain
        lines = flown(cut, left_to_right_first)
        if not check:
            return lines
        missed = unseen(poly, lines, reach)
        if missed.area <= tol:
            return lines
        for g in getattr(missed, "geoms", [missed]):
            if g.area <= tol * 1e-3:
                continue
            _, gy0, _, gy1 = g.bounds
            for j in np.nonzero((sy - half <= gy1) & (sy + half >= gy0))[0]:
                cut[j] = legs[j]
    return plain

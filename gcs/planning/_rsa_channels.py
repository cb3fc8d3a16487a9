"""RSA step 3a (seed 002, eqs. 6-12): boustrophedon channel sets inside one covering rectangle.

Rectangle vertices x1..x4 in order; length l = |x1 x4|, width w = |x1 x2|. Channels "along the
length" run from side x1x2 to side x4x3 and are stacked across the width (sets 1, 2 of the
paper); channels "along the width" run from x1x4 to x2x3 (sets 3, 4). Two deliberate changes
from the paper, both so that every point of the rectangle is within d_nbh/2 of a channel:
the channel count is ceil(size / d_nbh) (the paper's round() can leave strips up to d_nbh/4
wide unseen) and channels run edge to edge (the paper stops d_nbh/2 short of the far side, which
leaves the rectangle's corners d_nbh/sqrt(2) from the nearest channel).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def channel_count(size: float, d_nbh: float) -> int:
    """Channels needed across ``size`` metres so none is more than d_nbh/2 from a point."""
    return max(1, math.ceil(size / d_nbh - 1e-9))


def _boustrophedon(a0: FloatArray, a1: FloatArray, b0: FloatArray, b1: FloatArray, n: int) -> FloatArray:
    """n channels from side a0-a1 to side b0-b1 (a0->b0 is one long edge), alternating direction."""
    pts = []
    for j in range(n):
        f = (j + 0.5) / n
        ya = a0 + f * (a1 - a0)
        yb = b0 + f * (b1 - b0)
        pts.extend([ya, yb] if j % 2 == 0 else [yb, ya])
    return np.asarray(pts, dtype=float)


def channel_sets(rect: FloatArray, d_nbh: float) -> list[FloatArray]:
    """The paper's six cases: alternative polylines, each covering the rectangle (either direction)."""
    x1, x2, x3, x4 = (np.asarray(p, dtype=float) for p in rect)
    n_l = channel_count(float(np.hypot(*(x1 - x4))), d_nbh)
    n_w = channel_count(float(np.hypot(*(x1 - x2))), d_nbh)
    along_length_12 = _boustrophedon(x1, x2, x4, x3, n_w)  # sets 1: enter on side x1x2
    along_length_43 = _boustrophedon(x4, x3, x1, x2, n_w)  # set 2: enter on side x4x3
    along_width_14 = _boustrophedon(x1, x4, x2, x3, n_l)  # set 3: enter on side x1x4
    along_width_23 = _boustrophedon(x2, x3, x1, x4, n_l)  # set 4: enter on side x2x3
    if n_l == 1 and n_w == 1:  # case 1: any direction; the paper keeps the two mid-lines
        return [along_length_12, along_width_14]
    if n_w == 1:  # case 2: n_l > n_w = 1
        return [along_length_12]
    if n_l == 1:  # case 3: n_w > n_l = 1
        return [along_width_14]
    if n_l == n_w:  # case 4
        return [along_length_12, along_length_43, along_width_14, along_width_23]
    if n_l > n_w:  # case 5: fewer, longer channels along the length
        return [along_length_12, along_length_43]
    return [along_width_14, along_width_23]  # case 6


def polyline_length(path: FloatArray) -> float:
    """Length of a polyline in metres."""
    return float(np.hypot(*np.diff(path, axis=0).T).sum()) if len(path) > 1 else 0.0

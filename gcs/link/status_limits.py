"""Plausibility of status reports: schema-valid values that no real vehicle reports are refused.

Why: the schema (protocol/packets.py) bounds what a report may say (finite floats, latitudes,
battery percent), not what a drone can be: a time of 1e300, an altitude of -1e9 m or a speed of
1e300 m/s pass it, and then feed collision avoidance, the energy model, the telemetry history and
the API. The daemon refuses such a report: it never reaches the fleet table's readers or any
hook, and the agent's session stays open (a glitch must not cut the command link; the reports
that stop arriving make the drone's status stale, which the cooperation service acts on).

One rule set, two forms: :func:`refusal` names the first bound a report breaks (every JSON
report, and a compact row the vectorised check refused), :func:`plausible` applies the same
bounds to a tick's columns at once (gcs/link/agents_table.py); tests/backbone/test_status_validation.py
checks that they agree. Bounds (docs/protocol.md, "Plausibility"):

* ``time`` within ``max_clock_skew_s`` (default 1 h) of the daemon's clock when the report
  arrived; a replayed (``buffered``) report may also be up to :data:`REPLAY_MAX_AGE_S` older.
* ``position.alt_rel`` in [-1 000, 20 000] m, ``position.alt_amsl`` in [-1 000, 30 000] m.
* speed (the norm of ``velocity``) at most 200 m/s.
* ``vehicle_time`` (seconds since the autopilot booted) at most 1e9 s (31 years).
* ``step``, ``completed_step``, ``waiting_sync`` and ``queue_depth`` at most 1 000 000 (an
  action's step is at most that, protocol/actions.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol import status_binary
from protocol.packets import StatusReport

REPLAY_MAX_AGE_S = 86_400.0
"""How much older than the clock bound a replayed report may be: the agent replays its newest
1200 reports, which at the longest status period (60 s) span 20 h."""
_INF = math.inf


class ImplausibleStatus(ValueError):
    """A schema-valid status report refused for a value no vehicle reports (one line: which, why)."""


@dataclass(frozen=True, slots=True)
class StatusLimits:
    """The daemon's bounds on status reports: ``DaemonConfig.max_clock_skew_s`` sets the clock one,
    the others are physical (no vehicle this project flies gets near them). :data:`UNBOUNDED`
    turns them all off, for benches and tests that feed synthetic values to a bare table."""

    max_clock_skew_s: float = 3600.0
    alt_rel_m: tuple[float, float] = (-1_000.0, 20_000.0)
    alt_amsl_m: tuple[float, float] = (-1_000.0, 30_000.0)  # 20 km above the highest take-off site
    max_speed_mps: float = 200.0  # twice the fastest speed an action may ask for (100 m/s)
    max_vehicle_time_s: float = 1e9  # 31 years since the autopilot booted
    max_step: int = 1_000_000  # protocol/actions.py: an action's step is at most this
    max_queue: int = 1_000_000


UNBOUNDED = StatusLimits(_INF, (-_INF, _INF), (-_INF, _INF), _INF, _INF, 1 << 64, 1 << 64)


def refusal(
    report: StatusReport, received: float, limits: StatusLimits, *, replayed: bool = False
) -> str | None:
    """Why ``report`` (arrived at wall time ``received``) is implausible, or None when it is not."""
    lim = limits
    skew = report.time - received
    if not math.isfinite(skew) or skew > lim.max_clock_skew_s:
        bound = lim.max_clock_skew_s
        return f"time {report.time!r} is {skew:.4g} s ahead of the daemon's clock (bound {bound:g} s)"
    behind = lim.max_clock_skew_s + (REPLAY_MAX_AGE_S if replayed else 0.0)
    if -skew > behind:
        return f"time {report.time!r} is {-skew:.4g} s behind the daemon's clock (bound {behind:g} s)"
    p = report.position
    if p is not None:
        low, high = lim.alt_rel_m
        if not low <= p.alt_rel <= high:
            return f"position.alt_rel {p.alt_rel!r} m outside [{low:g}, {high:g}]"
        low, high = lim.alt_amsl_m
        if not low <= p.alt_amsl <= high:
            return f"position.alt_amsl {p.alt_amsl!r} m outside [{low:g}, {high:g}]"
    v = report.velocity
    if not v.vn * v.vn + v.ve * v.ve + v.vd * v.vd <= lim.max_speed_mps * lim.max_speed_mps:  # overflow: inf
        return f"velocity ({v.vn!r}, {v.ve!r}, {v.vd!r}) m/s is faster than {lim.max_speed_mps:g} m/s"
    if report.vehicle_time is not None and report.vehicle_time > lim.max_vehicle_time_s:
        return f"vehicle_time {report.vehicle_time!r} s above {lim.max_vehicle_time_s:g}"
    for name, value in (
        ("step", report.step),
        ("completed_step", report.completed_step),
        ("waiting_sync", report.waiting_sync),
    ):
        if value is not None and value > lim.max_step:
            return f"{name} {value} above {lim.max_step}"
    if report.queue_depth > lim.max_queue:
        return f"queue_depth {report.queue_depth} above {lim.max_queue}"
    return None


def plausible(
    cols: np.ndarray[Any, Any], received: np.ndarray[Any, np.dtype[np.float64]], limits: StatusLimits
) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Which live rows of ``cols`` (the compact layout's fixed fields, ``ROW_DTYPE``) :func:`refusal`
    accepts, as one vectorised check; ``received``: each row's arrival (wall clock)."""
    lim = limits
    skew = cols["time"] - received
    vn, ve, vd = cols["vn"], cols["ve"], cols["vd"]
    alt_rel, alt_amsl = cols["alt_rel"], cols["alt_amsl"]
    with np.errstate(invalid="ignore", over="ignore"):
        ok: np.ndarray[Any, np.dtype[np.bool_]] = (
            (np.abs(skew) <= lim.max_clock_skew_s)
            & (vn * vn + ve * ve + vd * vd <= lim.max_speed_mps * lim.max_speed_mps)
            & ~(cols["vehicle_time"] > lim.max_vehicle_time_s)  # NaN: none
            & (cols["step"] <= lim.max_step)
            & (cols["completed_step"] <= lim.max_step)
            & (cols["waiting_sync"] <= lim.max_step)
            & (cols["queue_depth"] <= lim.max_queue)
            & (
                ((cols["flags"] & status_binary.HAS_POSITION) == 0)
                | (
                    (alt_rel >= lim.alt_rel_m[0])
                    & (alt_rel <= lim.alt_rel_m[1])
                    & (alt_amsl >= lim.alt_amsl_m[0])
                    & (alt_amsl <= lim.alt_amsl_m[1])
                )
            )
        )
    return ok


__all__ = ["UNBOUNDED", "ImplausibleStatus", "StatusLimits", "plausible", "refusal"]

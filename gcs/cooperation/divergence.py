"""Divergence detection: how far a drone is from its planned leg, and what to do about it.

Cross-track error is the horizontal distance from the planned segment (start -> target); for
a hover point (waiting at a sync step) it is the distance from that point. Along-track lag is
how far the drone is behind a vehicle that left the leg start at the planned speed when the
step began. Actions, in rising order (each after the error persisted ``persist_s``, at most
one per ``cooldown_s``):

* ``correct_m``: **correction**, type-4 ``pause`` then ``resume``. The agent brakes and
  re-issues the leg target from where it is, which recovers a vehicle that lost or ignored its
  target (a dropped unacknowledged MAVLink target, a mode change); it does not pull it back.
* ``replan_m`` (or ``hover_drift_m`` at a sync point): **replan**, type-4 ``replace`` with a
  rejoin point ``lookahead_m`` ahead of the drone's projection on the planned leg, then the
  rest of the plan. The autopilot steers straight at its target, so a crosswind pushes it off
  the planned line in proportion to the distance still to fly; a near rejoin point brings it
  back onto the line the coverage was planned on.
* lag above ``lag_event_m``: an event only (re-sending targets cannot make a vehicle faster).

Legs come from :mod:`gcs.cooperation.legs`, modelled as the agent flies them (each leg starts
where the agent was when it switched, within its acceptance radius of the previous target).
Whether divergence may act at all is :func:`divergence_may_act`: never on a drone that waits
at a barrier, is paused or held, returns or lands, or is in an emergency or failsafe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from gcs.cooperation.config import DivergenceConfig
from gcs.cooperation.legs import Leg, Point
from protocol.geo import ned_offset_m, offset_latlon
from protocol.packets import StatusReport

# Modes in which the vehicle is not flying its plan: returns, landings and holds (ArduPilot BRAKE,
# or LOITER when BRAKE is refused; a held PX4 drone shows LOITER, one flying a leg GUIDED).
NON_PLAN_MODES = frozenset({"RTL", "SMART_RTL", "LAND", "BRAKE", "LOITER"})
# Agent exceptions whose reaction may have taken the vehicle off its plan (agent/monitor.py).
FAILSAFE_EXCEPTIONS = ("battery_low", "battery_critical", "fence_breach", "link_lost")


def divergence_blocked(
    status: StatusReport,
    *,
    held: bool = False,
    emergency: bool = False,
    escaping: bool = False,
    detour: bool = False,
) -> str | None:
    """Why divergence must not act on this drone now, or None when it may.

    ``held``: a hold by anyone (collision, connectivity, operator); ``emergency``: a daemon
    emergency or operator emergency command; ``escaping``: a collision escape runs;
    ``detour``: a replace the daemon sent is still being flown. A drone at a barrier is
    never moved: it waits for the others, and a replan there once flew one 31 m away.
    """
    if not status.armed or status.landed:
        return "not flying"
    if status.waiting_sync is not None:
        return f"waiting at the barrier of step {status.waiting_sync}"
    if status.paused:
        return "paused"
    if held:
        return "held"
    if emergency:
        return "in an emergency"
    if escaping:
        return "escaping a conflict"
    if detour:
        return "flying a detour"
    if status.mode in NON_PLAN_MODES:
        return f"in {status.mode}"
    failsafe = [e for e in status.exceptions if e.split(":", 1)[0] in FAILSAFE_EXCEPTIONS]
    if failsafe:
        return f"agent failsafe ({failsafe[0]})"
    return None


def divergence_may_act(
    status: StatusReport,
    *,
    held: bool = False,
    emergency: bool = False,
    escaping: bool = False,
    detour: bool = False,
) -> bool:
    """May divergence correct or replan this drone now? (see :func:`divergence_blocked`)."""
    return (
        divergence_blocked(status, held=held, emergency=emergency, escaping=escaping, detour=detour) is None
    )


@dataclass(frozen=True)
class LegError:
    cross_track_m: float
    along_m: float  # progress along the leg from its start
    length_m: float
    rejoin: Point  # on the leg, lookahead ahead of the projection (the target for a hover point)


def leg_error(leg: Leg, pos: Point, lookahead_m: float) -> LegError:
    """Cross-track distance and along-track progress of ``pos`` against ``leg`` (flat local frame)."""
    target = leg.target
    if leg.start is None:
        n, e = ned_offset_m(target[0], target[1], pos[0], pos[1])
        return LegError(math.hypot(n, e), 0.0, 0.0, target)
    start = leg.start
    sn, se = ned_offset_m(start[0], start[1], target[0], target[1])
    pn, pe = ned_offset_m(start[0], start[1], pos[0], pos[1])
    length = math.hypot(sn, se)
    if length < 1e-6:
        return LegError(math.hypot(pn, pe), 0.0, 0.0, target)
    un, ue = sn / length, se / length
    along = pn * un + pe * ue
    clamped = min(max(along, 0.0), length)
    cross = math.hypot(pn - clamped * un, pe - clamped * ue)
    ahead = min(clamped + lookahead_m, length)
    frac = ahead / length
    lat, lon = offset_latlon(start[0], start[1], ahead * un, ahead * ue)
    alt = start[2] + frac * (target[2] - start[2])
    rejoin = target if ahead >= length else (lat, lon, alt)
    return LegError(cross, along, length, rejoin)


Verdict = Literal["ok", "correct", "replan", "lag"]


@dataclass
class DivergenceJudge:
    """Per-drone persistence and cool-down around :func:`leg_error` (pure, clock passed in)."""

    config: DivergenceConfig
    _since: float | None = None
    _last_action: float = -1e18
    _lag_reported_step: int | None = None

    @property
    def persisting(self) -> bool:
        """An error above the correction limit is being timed (every report must be judged)."""
        return self._since is not None

    def lag_pending(self, leg: Leg) -> bool:
        """Could a lag event still come on ``leg`` (one per step, on a line with a planned speed)?"""
        return leg.start is not None and leg.speed is not None and self._lag_reported_step != leg.step

    def judge(
        self, leg: Leg, error: LegError, elapsed_vehicle_s: float | None, now: float, replans_left: bool
    ) -> tuple[Verdict, str]:
        cfg = self.config
        hover = leg.start is None
        limit_replan = cfg.hover_drift_m if hover else cfg.replan_m
        limit_correct = cfg.hover_drift_m if hover else cfg.correct_m
        if error.cross_track_m < limit_correct:
            self._since = None
            return self._lag(leg, error, elapsed_vehicle_s)
        if self._since is None:
            self._since = now
        if now - self._since < cfg.persist_s or now - self._last_action < cfg.cooldown_s:
            return "ok", ""
        what = "drift from the hover point" if hover else "cross-track error"
        detail = f"{what} {error.cross_track_m:.1f} m on step {leg.step}"
        self._last_action = now
        self._since = None
        if error.cross_track_m >= limit_replan and replans_left:
            return "replan", detail
        if hover:
            return "ok", ""
        return "correct", detail

    def _lag(self, leg: Leg, error: LegError, elapsed: float | None) -> tuple[Verdict, str]:
        if leg.start is None or leg.speed is None or elapsed is None or self._lag_reported_step == leg.step:
            return "ok", ""
        expected = min(error.length_m, leg.speed * elapsed)
        lag = expected - error.along_m
        if lag > self.config.lag_event_m:
            self._lag_reported_step = leg.step
            return "lag", f"{lag:.0f} m behind the planned speed {leg.speed:.1f} m/s on step {leg.step}"
        return "ok", ""

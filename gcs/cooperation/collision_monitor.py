"""Collision monitor: the fleet picture -> :class:`CollisionAvoider` -> intents (pure, clock passed in).

Who may be held: a drone flying (or waiting in) its plan, not in RTL/LAND, not in an emergency,
and not under the order of a source that outranks collision avoidance (operator, vehicle
failsafe, daemon emergency). Parked drones (landed or disarmed) are obstacles: never held,
never waited for. Escapes are detours (climb, then the rest of the plan) at collision priority.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from gcs.cooperation.collision import CollisionAvoider, Decision, DroneState, Escape
from gcs.cooperation.config import CollisionConfig
from gcs.cooperation.intents import (
    EndOrderIntent,
    EventIntent,
    HoldIntent,
    Intent,
    ReleaseIntent,
    ReplaceIntent,
)
from gcs.cooperation.tracking import Kinematics, TrackedAgent, leg_motion
from gcs.planning.geodesy import FloatArray, LocalFrame

DENSE_SHARE = 0.9
"""A pass whose prefilter would keep this share of the fleet or more hands over everyone..."""
DENSE_SKIP_PASSES = 50
"""... and the next this many passes skip the prefilter's query (1.4 ms at 2,000 drones), then
it looks again: a dense formation pays for it once in 51 passes. Decisions are the same either way."""


def reach_m(config: CollisionConfig) -> float:
    """The farthest apart (horizontally) two drones can be and still get a conflict this pass.

    :func:`~gcs.cooperation.collision.find_conflicts` pairs drones within the margin (scaled up
    to ``release_factor`` for a held drone) plus twice the fastest speed (capped at
    ``max_speed_mps``) times the horizon; this is that radius at its largest.
    """
    scale = max(1.0, config.release_factor)
    return config.horizontal_margin_m * scale + 2.0 * config.max_speed_mps * config.horizon_s


class CollisionMonitor:
    def __init__(self, config: CollisionConfig, prefilter: bool = True) -> None:
        self.config = config
        self.avoider = CollisionAvoider(config)
        self.last: Decision = Decision()
        # Build a DroneState only for a drone that could take part in a decision this pass (see
        # _involved); False hands the avoider every drone (the reference the tests compare with).
        self.prefilter = prefilter
        self._dense_passes = 0  # passes left that skip the prefilter (see DENSE_SKIP_PASSES)

    def _involved(self, agents: list[TrackedAgent], en: FloatArray) -> list[int]:
        """Indices of the drones the avoider must see: every drone with another within
        :func:`reach_m` (only such pairs can conflict), and every drone it holds, waits for or
        has escaping (it keeps state about them and forgets a drone it does not see). Order is
        kept, and conflicting pairs are handled in index order, so the avoider decides exactly what
        it decides seeing the whole fleet (tests/cooperation/units/test_fleet_gates.py)."""
        everyone = list(range(len(agents)))
        if not self.prefilter or len(agents) < 3:
            return everyone
        if self._dense_passes > 0:  # a dense formation: the query would leave nobody out
            self._dense_passes -= 1
            return everyone
        # The nearest other drone of each (no pair list: in a dense formation that is ~100 pairs
        # a drone, more work than the check it would spare).
        nearest, _ = cKDTree(en).query(en, k=2, distance_upper_bound=reach_m(self.config))
        keep = np.isfinite(nearest[:, 1])
        if keep.mean() >= DENSE_SHARE:
            self._dense_passes = DENSE_SKIP_PASSES
            return everyone
        avoider = self.avoider
        tracked = set(avoider.holds) | set(avoider.escaping)
        for blockers in avoider.holds.values():
            tracked |= blockers
        if tracked:
            for k, agent in enumerate(agents):
                if agent.ident in tracked:
                    keep[k] = True
        return np.flatnonzero(keep).tolist()

    def forget(self, ident: str) -> None:
        self.avoider.forget(ident)

    def check(
        self,
        agents: list[TrackedAgent],
        kin: Kinematics,
        frame: LocalFrame,
        outranked: Callable[[str], bool],
        now: float,
    ) -> list[Intent]:
        """One fleet-wide pass (``agents``: connected, fresh; ``kin``: their newest positions and
        velocities, one element each); returns holds, releases, escapes."""
        drones = []
        tracked = {}
        en_all = frame.stack_local(kin.lat, kin.lon)
        rows = self._involved(agents, en_all)
        if len(rows) < len(agents):
            agents = [agents[k] for k in rows]
            en_all = en_all[rows]
            kin = kin.take(rows)
        en = en_all.tolist()
        columns = zip(
            kin.lat.tolist(),
            kin.lon.tolist(),
            kin.alt_rel.tolist(),
            kin.alt_amsl.tolist(),
            kin.vn.tolist(),
            kin.ve.tolist(),
            kin.vd.tolist(),
            strict=True,
        )
        escaping, default_speed = self.avoider.escaping, self.config.default_speed_mps
        for a, (e, n), (lat, lon, alt_rel, alt_amsl, vn, ve, vd) in zip(agents, en, columns, strict=True):
            s = a.state  # state only: current without building the newest report
            grounded = not a.airborne
            yieldable = (
                not grounded
                and a.emergency is None
                and s.mode not in ("RTL", "LAND")
                and (s.step >= 0 or s.waiting_sync is not None or s.paused)
                and not outranked(a.ident)
            )
            tracked[a.ident] = a
            desired, remaining = (
                (None, None) if grounded else leg_motion(a, frame, default_speed, (lat, lon, alt_rel), (e, n))
            )
            drones.append(
                DroneState(
                    ident=a.ident,
                    cid=a.cid,
                    position=(e, n, alt_amsl),
                    velocity=(0.0, 0.0, 0.0) if grounded else (ve, vn, -vd),
                    desired=desired,
                    yieldable=yieldable,
                    grounded=grounded,
                    remaining_m=None if a.ident in escaping else remaining,
                )
            )
        decision = self.avoider.update(drones, now)
        self.last = decision
        intents: list[Intent] = []
        for ident, reason in decision.pause.items():
            intents.append(HoldIntent(ident, "collision", reason))
            blockers = sorted(self.avoider.holds.get(ident, ()))
            intents.append(EventIntent("collision_hold", reason, ident, "warning", {"blockers": blockers}))
        for ident in decision.resume:
            intents.append(ReleaseIntent(ident, "collision", "collision avoidance: clear"))
            intents.append(EventIntent("collision_release", "clear of other drones; resumed", ident))
        for escape in decision.escapes:
            intents += self._escape(tracked[escape.ident], escape, now)
        for kind, message, data in decision.events:
            who = data.get("agent")
            agent = who if isinstance(who, str) else None
            if kind in ("collision_escaped", "collision_escape_timeout") and agent is not None:
                intents.append(EndOrderIntent(agent, "collision", message))
            intents.append(EventIntent(kind, message, agent, "warning", dict(data)))
        return intents

    def _escape(self, agent: TrackedAgent, escape: Escape, now: float) -> list[Intent]:
        s = agent.status
        p = agent.position
        reason = escape.reason
        alt_rel = max(escape.target_up - (p.alt_amsl - p.alt_rel), self.config.min_escape_alt_m)
        detour = agent.plan.detour(s, (p.lat, p.lon, alt_rel), agent.completed) if agent.plan else None
        if detour is None:
            self.avoider.escape_impossible(escape, now)
            return [
                HoldIntent(agent.ident, "collision", reason),
                EventIntent(
                    "collision_escape_impossible",
                    f"cannot re-plan {agent.ident} now; holding it: {reason}",
                    agent.ident,
                    "error",
                ),
            ]
        agent.detour_step = detour[0].step
        return [
            ReplaceIntent(agent.ident, "collision", detour, reason, "escape"),
            EventIntent(
                "collision_escape",
                f"{reason}; climbing to {alt_rel:.1f} m",
                agent.ident,
                "warning",
                {"alt_rel": alt_rel},
            ),
        ]

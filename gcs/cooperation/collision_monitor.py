"""Collision monitor: the fleet picture -> :class:`CollisionAvoider` -> intents (pure, clock passed in).

Who may be held: a drone flying (or waiting in) its plan, not in RTL/LAND, not in an emergency,
and not under the order of a source that outranks collision avoidance (operator, vehicle
failsafe, daemon emergency). Parked drones (landed or disarmed) are obstacles: never held,
never waited for. Escapes are detours (climb, then the rest of the plan) at collision priority.
"""

from __future__ import annotations

from collections.abc import Callable

from gcs.cooperation.collision import CollisionAvoider, Decision, DroneState, Escape
from gcs.cooperation.config import CollisionConfig
from gcs.cooperation.geo import LocalFrame
from gcs.cooperation.intents import (
    EndOrderIntent,
    EventIntent,
    HoldIntent,
    Intent,
    ReleaseIntent,
    ReplaceIntent,
)
from gcs.cooperation.tracking import Kinematics, TrackedAgent, leg_motion


class CollisionMonitor:
    def __init__(self, config: CollisionConfig) -> None:
        self.config = config
        self.avoider = CollisionAvoider(config)
        self.last: Decision = Decision()

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
        ne = frame.to_ne(kin.lat, kin.lon).tolist()
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
        for a, (n, e), (lat, lon, alt_rel, alt_amsl, vn, ve, vd) in zip(agents, ne, columns, strict=True):
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
                (None, None) if grounded else leg_motion(a, frame, default_speed, (lat, lon, alt_rel))
            )
            drones.append(
                DroneState(
                    ident=a.ident,
                    cid=a.cid,
                    position=(n, e, alt_amsl),
                    velocity=(0.0, 0.0, 0.0) if grounded else (vn, ve, -vd),
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

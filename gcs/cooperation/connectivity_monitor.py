"""Connectivity monitor: disk-model link graph of base + drones -> holds, returns, warnings (pure)."""

from __future__ import annotations

import numpy as np

from gcs.cooperation.config import ConnectivityConfig
from gcs.cooperation.connectivity import connected_to_base, nearest_connected
from gcs.cooperation.intents import (
    EventIntent,
    HoldIntent,
    Intent,
    ReleaseIntent,
    ReplaceIntent,
    ReturnIntent,
)
from gcs.cooperation.tracking import Kinematics, TrackedAgent
from gcs.planning.geodesy import LocalFrame
from protocol.actions import Goto


class ConnectivityMonitor:
    def __init__(self, config: ConnectivityConfig) -> None:
        self.config = config

    def check(
        self,
        agents: list[TrackedAgent],
        kin: Kinematics,
        frame: LocalFrame,
        base_latlon: tuple[float, float],
        w: float,
        now: float,
    ) -> list[Intent]:
        """Who lost its link to the base (``kin``: the agents' newest positions, one each)."""
        cfg = self.config
        if not agents:
            return []
        intents: list[Intent] = []
        base = frame.local_point(*base_latlon)
        points = frame.stack_local(kin.lat, kin.lon)
        ok = connected_to_base(base, points, w, cfg.multihop)
        for k, agent in enumerate(agents):
            if ok[k] or not agent.airborne:
                if agent.disconnected_since is not None:
                    agent.disconnected_since, agent.link_acted = None, False
                    intents.append(
                        EventIntent(
                            "connectivity_restored", "back within link range of the fleet", agent.ident
                        )
                    )
                    intents.append(ReleaseIntent(agent.ident, "connectivity", "connectivity restored"))
                if agent.airborne:
                    intents += self._warn_leg(agent, points, k, base, w, frame)
                continue
            if agent.disconnected_since is None:
                agent.disconnected_since = now
            if agent.link_acted or now - agent.disconnected_since < cfg.grace_s:
                continue
            agent.link_acted = True
            intents += self._disconnected(agent, base, points, ok, k, w, frame)
        return intents

    def _warn_leg(
        self,
        agent: TrackedAgent,
        points: np.ndarray,
        k: int,
        base: tuple[float, float],
        w: float,
        frame: LocalFrame,
    ) -> list[Intent]:
        """Warn once per leg when its target would leave the drone without a link (others where they are)."""
        plan = agent.plan
        if plan is None:
            return []
        leg = plan.leg(agent.state.waiting_sync)
        if leg is None or leg.start is None or (leg.step, plan.waypoint) in agent.warned:
            return []
        agent.warned.add((leg.step, plan.waypoint))
        moved = points.copy()
        moved[k] = frame.local_point(leg.target[0], leg.target[1])
        if connected_to_base(base, moved, w, self.config.multihop)[k]:
            return []
        return [
            EventIntent(
                "connectivity_warning",
                f"step {leg.step} leads out of link range ({w:.0f} m) of the base and the fleet",
                agent.ident,
                "warning",
                {"step": leg.step, "target": list(leg.target)},
            )
        ]

    def _disconnected(
        self,
        agent: TrackedAgent,
        base: tuple[float, float],
        points: np.ndarray,
        ok: np.ndarray,
        k: int,
        w: float,
        frame: LocalFrame,
    ) -> list[Intent]:
        policy = self.config.policy
        intents: list[Intent] = [
            EventIntent(
                "connectivity_lost",
                f"out of link range ({w:.0f} m) of the fleet; policy {policy}",
                agent.ident,
                "error",
            )
        ]
        if policy == "hold":
            intents.append(HoldIntent(agent.ident, "connectivity", "connectivity: out of link range"))
        elif policy == "rtl":
            agent.emergency = "rtl"
            intents.append(
                ReturnIntent(agent.ident, "connectivity", "rtl", "connectivity: out of link range")
            )
        elif policy == "return":
            near = nearest_connected(base, points, ok, k)
            here = points[k]
            gap = float(np.linalg.norm(here - np.array(near)))
            frac = self.config.return_fraction * w / gap if gap > 0 else 1.0
            east, north = near[0] + (here[0] - near[0]) * frac, near[1] + (here[1] - near[1]) * frac
            lat, lon = frame.geodetic_point(east, north)
            step = max(agent.completed, 0)
            agent.detour_step = step
            goto = Goto(step=step, lat=lat, lon=lon, alt=agent.position.alt_rel)
            intents.append(
                ReplaceIntent(agent.ident, "connectivity", [goto], "return toward the fleet", "return")
            )
        return intents

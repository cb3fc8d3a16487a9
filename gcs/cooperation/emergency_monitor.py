"""Daemon emergency monitor (defence in depth beside the agent's own): fence, battery, GPS, silence.

Pure over the tracked agents: each check is edge-triggered (acts once when a condition has held
for its grace time, re-armed when it clears) and returns intents at ``daemon_emergency`` priority.
"""

from __future__ import annotations

from gcs.cooperation.config import EmergencyAction, EmergencyConfig
from gcs.cooperation.emergency import NO_RETURN_MODES, fence_violation, gps_lost, return_home_shortfall
from gcs.cooperation.intents import EventIntent, HoldIntent, Intent, ReturnIntent
from gcs.cooperation.tracking import TrackedAgent
from protocol.packets import Geofence, StatusReport


def edge(agent: TrackedAgent, name: str, holds: bool, now: float, grace: float = 0.0) -> bool:
    """True once when ``name`` has held for ``grace`` seconds; re-armed when it clears."""
    if not holds:
        agent.conditions.pop(name, None)
        agent.acted.discard(name)
        return False
    since = agent.conditions.setdefault(name, now)
    if name in agent.acted or now - since < grace:
        return False
    agent.acted.add(name)
    return True


class EmergencyMonitor:
    def __init__(self, config: EmergencyConfig, vehicle_time_scale: float) -> None:
        self.config = config
        self.vehicle_time_scale = vehicle_time_scale

    def on_status(
        self, agent: TrackedAgent, status: StatusReport, fence: Geofence | None, now: float
    ) -> list[Intent]:
        """The checks of one report; ``agent.battery`` must have been fed it (``Fleet.feed_battery``)."""
        cfg = self.config
        intents: list[Intent] = []
        why = fence_violation(status, fence) if status.armed else None
        if edge(agent, "fence", why is not None, now):
            assert fence is not None and why is not None
            chosen = fence.breach_action if cfg.fence_action == "fence" else cfg.fence_action
            action: EmergencyAction = {"hold": "pause", "report": "event"}.get(chosen, chosen)  # type: ignore[assignment]
            intents += self.act(agent, "emergency_fence_breach", f"fence breach: {why}", action)
        home = agent.home
        short = None
        battery = agent.battery  # fed this report already (the service feeds a whole tick at once)
        if (
            battery is not None
            and home is not None
            and status.armed
            and not status.landed
            and status.mode not in NO_RETURN_MODES
        ):
            short = return_home_shortfall(
                status,
                (home.lat, home.lon),
                battery,
                cfg.descent_mps,
                self.vehicle_time_scale,
                cfg.battery_reserve_pct,
                cfg.battery_safety_factor,
            )
        if edge(agent, "battery", bool(short and short[0]), now):
            assert short is not None
            intents += self.act(agent, "emergency_battery", short[1], cfg.battery_action)
        if edge(agent, "gps", gps_lost(status), now, cfg.gps_grace_s):
            intents += self.act(
                agent, "emergency_gps", f"GPS fix {status.gps.fix} (below 3D)", cfg.gps_action
            )
        return intents

    def stale(self, agents: list[TrackedAgent], limit: float, now: float) -> list[Intent]:
        """Drones in the air whose reports stopped (their connection still open)."""
        intents: list[Intent] = []
        for agent in agents:
            age = now - agent.received
            if edge(agent, "stale", agent.connected and agent.airborne and age > limit, now):
                intents += self.act(
                    agent,
                    "emergency_stale",
                    f"no status for {age:.1f} s (limit {limit:.1f} s)",
                    self.config.stale_action,
                )
        return intents

    @staticmethod
    def act(agent: TrackedAgent, kind: str, message: str, action: EmergencyAction) -> list[Intent]:
        intents: list[Intent] = [
            EventIntent(kind, f"{message}; daemon action {action}", agent.ident, "error", {"action": action})
        ]
        if action == "pause":
            intents.append(HoldIntent(agent.ident, "daemon_emergency", message))
        elif action in ("rtl", "land"):
            agent.emergency = action
            intents.append(ReturnIntent(agent.ident, "daemon_emergency", action, message))
        return intents

"""The cooperation service: runs the pure checks on live status and sends what they decide.

I/O lives here and only here: status hooks in, type-4 packets and events out. Decisions are
made synchronously inside the status hook (cheap, numpy), the packets go through one worker
task so a slow agent connection never stalls another agent's frame loop, and they stay in
order per agent. A ticker re-asserts holds (seed 000: "for safety reasons ... sent
periodically") and catches drones whose status stopped arriving.

Holds have owners (collision, connectivity, emergency). A drone is resumed only when no owner
holds it any more and its mission is not paused by the operator.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcs.agents import AgentSession
from gcs.cooperation.collision import CollisionAvoider, Decision, DroneState
from gcs.cooperation.config import CooperationConfig, EmergencyAction
from gcs.cooperation.connectivity import connected_to_base, nearest_connected, preflight_disconnections
from gcs.cooperation.divergence import DivergenceJudge, leg_error
from gcs.cooperation.emergency import BatteryEstimator, fence_violation, gps_lost, return_home_shortfall
from gcs.cooperation.energy import EnergyModel, estimate_mission, fallback_model
from gcs.cooperation.flightlog import FlightLogWriter
from gcs.cooperation.geo import LocalFrame
from gcs.cooperation.legs import AgentPlanState, Point
from gcs.events import Severity
from gcs.missions import ActiveMission, MissionRejected
from protocol.actions import Action, Goto, Land, ReturnToLaunch
from protocol.packets import AgentParameters, PerformActions, Resume, SetParameters, StatusReport
from protocol.taskfile import TaskFile

if TYPE_CHECKING:
    from gcs.daemon import Daemon

log = logging.getLogger("gcs.cooperation")

EMERGENCY_MISSION = "cooperation-emergency"
LOST_LINK_ACTION = {"event": "continue", "hold": "hold", "return": "rtl", "rtl": "rtl"}


@dataclass
class _Agent:
    """What the service keeps per agent between status reports."""

    session: AgentSession
    status: StatusReport
    received: float  # monotonic
    plan: AgentPlanState | None = None
    completed: int = -1
    detour_step: int | None = None
    judge: DivergenceJudge | None = None
    battery: BatteryEstimator | None = None
    conditions: dict[str, float] = field(default_factory=dict)  # condition -> since (monotonic)
    acted: set[str] = field(default_factory=set)
    emergency: str | None = None
    disconnected_since: float | None = None
    link_acted: bool = False
    warned: set[tuple[int, int]] = field(default_factory=set)
    recorder: FlightLogWriter | None = None


class CooperationService:
    """Collision avoidance, divergence, connectivity, emergency monitor and energy checks."""

    name = "cooperation"

    def __init__(self, config: CooperationConfig) -> None:
        self.config = config
        self.avoider = CollisionAvoider(config.collision)
        self.agents: dict[str, _Agent] = {}
        self.holds: dict[str, dict[str, str]] = {}  # ident -> owner -> reason
        self.energy_model: EnergyModel = fallback_model(config.energy.fallback_power_w)
        self.frame: LocalFrame | None = None
        self.base: tuple[float, float] | None = config.connectivity.base
        self._daemon: Daemon | None = None
        self._queue: asyncio.Queue[tuple[str, Callable[[], Awaitable[object]]]] = asyncio.Queue()
        self._tasks: list[asyncio.Task[None]] = []
        self._last_fleet_check = 0.0
        self._last_link_check = 0.0
        self._recordings = 0

    # --- lifecycle ------------------------------------------------------------------------------

    async def start(self, daemon: Daemon) -> None:
        self._daemon = daemon
        daemon.agents.on_status.append(self._on_status)
        daemon.agents.on_join.append(self._on_join)
        daemon.agents.on_lost.append(self._on_lost)
        daemon.missions.preflight_checks.append(self._preflight)
        if self.config.energy.model_path is not None:
            self.energy_model = EnergyModel.load(self.config.energy.model_path)
        self._tasks = [
            asyncio.create_task(self._worker(), name="cooperation-worker"),
            asyncio.create_task(self._ticker(), name="cooperation-ticker"),
        ]

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        if self._tasks:  # bounded: a cancel swallowed inside a send must not hang the daemon's stop
            await asyncio.wait(self._tasks, timeout=2.0)
        self._tasks = []
        daemon = self._daemon
        if daemon is not None:
            for hooks, hook in (
                (daemon.agents.on_status, self._on_status),
                (daemon.agents.on_join, self._on_join),
                (daemon.agents.on_lost, self._on_lost),
                (daemon.missions.preflight_checks, self._preflight),
            ):
                with contextlib.suppress(ValueError):
                    hooks.remove(hook)  # type: ignore[arg-type]
        for agent in self.agents.values():
            if agent.recorder is not None:
                agent.recorder.close()

    @property
    def daemon(self) -> Daemon:
        assert self._daemon is not None, "service not started"
        return self._daemon

    # --- outgoing -------------------------------------------------------------------------------

    def _send(self, ident: str, body: PerformActions | SetParameters) -> None:
        self._queue.put_nowait((ident, lambda: self.daemon.agents.send(ident, body)))

    def _event(
        self,
        kind: str,
        message: str,
        agent: str | None = None,
        severity: Severity = "info",
        data: dict[str, Any] | None = None,
    ) -> None:
        mission = self.agents[agent].status.mission_id if agent in self.agents else None
        self.daemon.events.publish(
            kind, message, severity=severity, agent=agent, mission_id=mission, data=data
        )

    async def _worker(self) -> None:
        while True:
            ident, send = await self._queue.get()
            try:
                await send()
            except Exception:  # one failed send must not stop the service
                log.exception("cooperation: sending to %s failed", ident)

    def _mission_id(self, ident: str) -> str:
        status = self.agents[ident].status if ident in self.agents else None
        return status.mission_id if status is not None and status.mission_id else EMERGENCY_MISSION

    def hold(self, ident: str, owner: str, reason: str) -> None:
        owners = self.holds.setdefault(ident, {})
        first = not owners
        owners[owner] = reason
        if first:
            self._send(
                ident, PerformActions(mission_id=self._mission_id(ident), mode="pause", reason=reason[:200])
            )

    def release(self, ident: str, owner: str, reason: str) -> None:
        owners = self.holds.get(ident)
        if owners is None or owner not in owners:
            return
        del owners[owner]
        if owners:
            return
        del self.holds[ident]
        mission_id = self._mission_id(ident)
        if mission_id in self.daemon.missions.paused:
            return  # the operator paused the mission; only the operator resumes it
        self._send(ident, PerformActions(mission_id=mission_id, mode="resume", reason=reason[:200]))

    def _replace(self, ident: str, actions: list[Action]) -> None:
        self.holds.pop(ident, None)  # a replace overrides the agent's pause
        self._send(ident, PerformActions(mission_id=self._mission_id(ident), mode="replace", actions=actions))

    # --- hooks ----------------------------------------------------------------------------------

    async def _on_join(self, session: AgentSession, resume: Resume | None) -> None:
        if self.base is None and session.home is not None:
            self.base = (session.home.lat, session.home.lon)
        cfg = self.config.connectivity
        w = self._link_range()
        if cfg.enabled and cfg.push_lost_link_action and w is not None:
            parameters = AgentParameters(link_range_m=w, lost_link_action=LOST_LINK_ACTION[cfg.policy])  # type: ignore[arg-type]
            self._send(session.identity, SetParameters(parameters=parameters))

    async def _on_lost(self, identity: str) -> None:
        agent = self.agents.pop(identity, None)
        if agent is not None and agent.recorder is not None:
            agent.recorder.close()
        self.avoider.forget(identity)
        self.holds.pop(identity, None)

    async def _on_status(self, session: AgentSession, status: StatusReport) -> None:
        if status.buffered or status.position is None:
            return  # link-outage history, or no 3-D fix yet: nothing to track or check from
        now = time.monotonic()
        ident = session.identity
        agent = self.agents.get(ident)
        if agent is None:
            agent = _Agent(session, status, now)
            self.agents[ident] = agent
            if self.frame is None:
                self.frame = LocalFrame(status.position.lat, status.position.lon)
            if self.base is None:
                home = session.home
                self.base = (home.lat, home.lon) if home else (status.position.lat, status.position.lon)
        agent.session, agent.status, agent.received = session, status, now
        try:
            self._track(agent, status)
            self._record(agent, status)
            if self.config.emergency.enabled:
                self._emergency_checks(agent, status, now)
            if self.config.divergence.enabled:
                self._divergence(agent, status, now)
            if now - self._last_fleet_check >= self.config.collision.min_check_interval_s:
                self._last_fleet_check = now
                if self.config.collision.enabled:
                    self.check_collisions(now)
                if self.config.connectivity.enabled:
                    self.check_connectivity(now)
        except Exception:  # a bug here must not cost the agent its connection
            log.exception("cooperation: status handling failed for %s", ident)

    # --- plan tracking --------------------------------------------------------------------------

    def _active_mission(self, status: StatusReport) -> ActiveMission | None:
        return self.daemon.missions.active.get(status.mission_id) if status.mission_id else None

    def _track(self, agent: _Agent, status: StatusReport) -> None:
        ident = agent.session.identity
        mission = self._active_mission(status)
        if mission is None or ident not in mission.plans:
            agent.plan = None
            if status.landed and not status.armed:
                agent.emergency = None
            return
        if agent.plan is None or agent.plan.mission_id != mission.id:
            home = agent.session.home
            origin: Point = (
                (home.lat, home.lon, 0.0) if home else (status.position.lat, status.position.lon, 0.0)
            )
            agent.plan = AgentPlanState(
                mission.id, mission.plans[ident], origin, self.config.divergence.acceptance_radius_m
            )
            agent.completed, agent.detour_step, agent.emergency = -1, None, None
            agent.judge = DivergenceJudge(self.config.divergence)
            agent.warned.clear()
        agent.completed = max(agent.completed, status.completed_step)
        if agent.detour_step is not None:
            if status.step == agent.detour_step and status.waiting_sync is None:
                return  # flying a detour the service inserted; the plan position is unchanged
            agent.detour_step = None
        agent.plan.update(status)

    def _leg_target_velocity(self, agent: _Agent) -> tuple[float, float, float] | None:
        """Where a held drone wants to go: toward its leg target at the planned speed."""
        plan, status = agent.plan, agent.status
        if plan is None or self.frame is None:
            return None
        leg = plan.leg(status.waiting_sync)
        if leg is None or leg.start is None:
            return (0.0, 0.0, 0.0) if status.waiting_sync is not None else None
        here = self.frame.point(status.position.lat, status.position.lon)
        there = self.frame.point(leg.target[0], leg.target[1])
        delta = np.array([there[0] - here[0], there[1] - here[1], leg.target[2] - status.position.alt_rel])
        norm = float(np.linalg.norm(delta))
        if norm < 0.5:
            return (0.0, 0.0, 0.0)
        v = delta / norm * (leg.speed or self.config.collision.default_speed_mps)
        return (float(v[0]), float(v[1]), float(v[2]))

    # --- collision ------------------------------------------------------------------------------

    def _stale_limit(self) -> float:
        cfg = self.config.emergency
        return max(cfg.stale_after_periods * self.daemon.config.status_period_s, cfg.stale_min_s)

    def _airborne(self, now: float) -> list[_Agent]:
        limit = self._stale_limit()
        return [
            a
            for a in self.agents.values()
            if a.session.open and a.status.armed and not a.status.landed and now - a.received <= limit
        ]

    def check_collisions(self, now: float) -> Decision:
        """One fleet-wide pass: conflicts -> holds, releases and escapes (sent by the worker)."""
        assert self.frame is not None
        airborne = self._airborne(now)
        drones = []
        for a in airborne:
            s = a.status
            n, e = self.frame.point(s.position.lat, s.position.lon)
            yieldable = (
                a.emergency is None
                and s.mode not in ("RTL", "LAND")
                and (s.step >= 0 or s.waiting_sync is not None or s.paused)
            )
            drones.append(
                DroneState(
                    ident=a.session.identity,
                    cid=a.session.cid,
                    position=(n, e, s.position.alt_amsl),
                    velocity=(s.velocity.vn, s.velocity.ve, -s.velocity.vd),
                    desired=self._leg_target_velocity(a),
                    yieldable=yieldable,
                )
            )
        decision = self.avoider.update(drones, now)
        for ident, reason in decision.pause.items():
            self.hold(ident, "collision", reason)
            self._event(
                "collision_hold",
                reason,
                ident,
                "warning",
                {"blockers": sorted(self.avoider.holds.get(ident, ()))},
            )
        for ident in decision.resume:
            self.release(ident, "collision", "collision avoidance: clear")
            self._event("collision_release", "clear of other drones; resumed", ident)
        for escape in decision.escapes:
            self._escape(escape.ident, escape.target_up, escape.reason)
        for kind, message, data in decision.events:
            who = data.get("agent")
            self._event(kind, message, who if isinstance(who, str) else None, "warning", data)
        return decision

    def _escape(self, ident: str, target_amsl: float, reason: str) -> None:
        agent = self.agents[ident]
        s = agent.status
        alt_rel = max(
            target_amsl - (s.position.alt_amsl - s.position.alt_rel), self.config.collision.min_escape_alt_m
        )
        detour = (
            agent.plan.detour(s, (s.position.lat, s.position.lon, alt_rel), agent.completed)
            if agent.plan
            else None
        )
        if detour is None:
            self.avoider.escaping.pop(ident, None)
            self.hold(ident, "collision", reason)
            self._event(
                "collision_escape_impossible",
                f"cannot re-plan {ident} now; holding it: {reason}",
                ident,
                "error",
            )
            return
        agent.detour_step = detour[0].step
        self._replace(ident, detour)
        self._event(
            "collision_escape",
            f"{reason}; climbing to {alt_rel:.1f} m",
            ident,
            "warning",
            {"alt_rel": alt_rel},
        )

    # --- divergence -----------------------------------------------------------------------------

    def _divergence(self, agent: _Agent, status: StatusReport, now: float) -> None:
        ident = agent.session.identity
        plan, judge = agent.plan, agent.judge
        if (
            plan is None
            or judge is None
            or agent.detour_step is not None
            or agent.emergency is not None
            or ident in self.holds
            or ident in self.avoider.escaping
            or status.paused
            or status.landed
            or not status.armed
            or status.mode in ("RTL", "LAND")
        ):
            return
        leg = plan.leg(status.waiting_sync)
        if leg is None:
            return
        cfg = self.config.divergence
        pos = (status.position.lat, status.position.lon, status.position.alt_rel)
        error = leg_error(leg, pos, cfg.lookahead_m)
        elapsed = (status.time - plan.segment_started) * self.config.vehicle_time_scale
        verdict, detail = judge.judge(leg, error, elapsed, now, plan.replans < cfg.max_replans_per_step)
        data = {"cross_track_m": round(error.cross_track_m, 2), "step": leg.step}
        if verdict == "lag":
            self._event("divergence_lag", detail, ident, "warning", data)
        elif verdict == "correct":
            self._event(
                "divergence_correction",
                f"{detail}: pause + resume re-issues the leg target",
                ident,
                "warning",
                data,
            )
            mission_id = self._mission_id(ident)
            self._send(
                ident, PerformActions(mission_id=mission_id, mode="pause", reason="divergence correction")
            )
            self._send(
                ident, PerformActions(mission_id=mission_id, mode="resume", reason="divergence correction")
            )
        elif verdict == "replan":
            detour = plan.detour(status, error.rejoin, agent.completed)
            if detour is None:
                return
            plan.replans += 1
            agent.detour_step = detour[0].step
            self._event(
                "divergence_replan",
                f"{detail}: re-planned the rest from here via a rejoin point on the planned leg",
                ident,
                "warning",
                {**data, "rejoin": list(error.rejoin), "actions": len(detour)},
            )
            self._replace(ident, detour)

    # --- connectivity ---------------------------------------------------------------------------

    def _link_range(self) -> float | None:
        cfg = self.config.connectivity
        if cfg.link_range_m is not None:
            return cfg.link_range_m
        return self.daemon.config.agent_parameters.link_range_m if self._daemon else None

    def check_connectivity(self, now: float) -> None:
        cfg = self.config.connectivity
        w = self._link_range()
        if w is None or self.frame is None or self.base is None:
            return
        agents = [a for a in self.agents.values() if a.session.open]
        if not agents:
            return
        base = self.frame.point(*self.base)
        points = self.frame.to_ne(
            [a.status.position.lat for a in agents], [a.status.position.lon for a in agents]
        )
        ok = connected_to_base(base, points, w, cfg.multihop)
        for k, agent in enumerate(agents):
            ident = agent.session.identity
            airborne = agent.status.armed and not agent.status.landed
            if ok[k] or not airborne:
                if agent.disconnected_since is not None:
                    agent.disconnected_since, agent.link_acted = None, False
                    self._event("connectivity_restored", "back within link range of the fleet", ident)
                    self.release(ident, "connectivity", "connectivity restored")
                if airborne:
                    self._warn_leg(agent, agents, points, k, base, w)
                continue
            if agent.disconnected_since is None:
                agent.disconnected_since = now
            if agent.link_acted or now - agent.disconnected_since < cfg.grace_s:
                continue
            agent.link_acted = True
            self._disconnected(agent, base, points, ok, k, w)

    def _warn_leg(
        self,
        agent: _Agent,
        agents: list[_Agent],
        points: np.ndarray,
        k: int,
        base: tuple[float, float],
        w: float,
    ) -> None:
        """Warn once per leg when its target would leave the drone without a link (others where they are)."""
        plan = agent.plan
        if plan is None or self.frame is None:
            return
        leg = plan.leg(agent.status.waiting_sync)
        if leg is None or leg.start is None or (leg.step, plan.waypoint) in agent.warned:
            return
        agent.warned.add((leg.step, plan.waypoint))
        moved = points.copy()
        moved[k] = self.frame.point(leg.target[0], leg.target[1])
        if not connected_to_base(base, moved, w, self.config.connectivity.multihop)[k]:
            self._event(
                "connectivity_warning",
                f"step {leg.step} leads out of link range ({w:.0f} m) of the base and the fleet",
                agent.session.identity,
                "warning",
                {"step": leg.step, "target": list(leg.target)},
            )

    def _disconnected(
        self, agent: _Agent, base: tuple[float, float], points: np.ndarray, ok: np.ndarray, k: int, w: float
    ) -> None:
        ident = agent.session.identity
        policy = self.config.connectivity.policy
        self._event(
            "connectivity_lost",
            f"out of link range ({w:.0f} m) of the fleet; policy {policy}",
            ident,
            "error",
        )
        if policy == "hold":
            self.hold(ident, "connectivity", "connectivity: out of link range")
        elif policy == "rtl":
            self._emergency_order(ident, "rtl")
        elif policy == "return" and self.frame is not None:
            near = nearest_connected(base, points, ok, k)
            here = points[k]
            gap = float(np.linalg.norm(here - np.array(near)))
            frac = self.config.connectivity.return_fraction * w / gap if gap > 0 else 1.0
            north, east = near[0] + (here[0] - near[0]) * frac, near[1] + (here[1] - near[1]) * frac
            lat, lon = self.frame.to_latlon(north, east)
            step = max(agent.completed, 0)
            agent.detour_step = step
            self._replace(ident, [Goto(step=step, lat=lat, lon=lon, alt=agent.status.position.alt_rel)])

    # --- emergencies ----------------------------------------------------------------------------

    def _condition(self, agent: _Agent, name: str, holds: bool, now: float, grace: float = 0.0) -> bool:
        """Edge trigger: True once when ``name`` has held for ``grace`` seconds; re-armed when it clears."""
        if not holds:
            agent.conditions.pop(name, None)
            agent.acted.discard(name)
            return False
        since = agent.conditions.setdefault(name, now)
        if name in agent.acted or now - since < grace:
            return False
        agent.acted.add(name)
        return True

    def _emergency_checks(self, agent: _Agent, status: StatusReport, now: float) -> None:
        cfg = self.config.emergency
        ident = agent.session.identity
        fence = self.daemon.geofences.get(ident)
        why = fence_violation(status, fence) if status.armed else None
        if self._condition(agent, "fence", why is not None, now):
            assert fence is not None and why is not None
            chosen = fence.breach_action if cfg.fence_action == "fence" else cfg.fence_action
            action: EmergencyAction = {"hold": "pause", "report": "event"}.get(chosen, chosen)  # type: ignore[assignment]
            self._act(agent, "emergency_fence_breach", f"fence breach: {why}", action)
        if agent.battery is None:
            agent.battery = BatteryEstimator(cfg.battery_window_s)
        agent.battery.add(status)
        home = agent.session.home
        short = None
        if home is not None and status.armed and not status.landed and status.mode not in ("RTL", "LAND"):
            short = return_home_shortfall(
                status,
                (home.lat, home.lon),
                agent.battery,
                cfg.descent_mps,
                self.config.vehicle_time_scale,
                cfg.battery_reserve_pct,
                cfg.battery_safety_factor,
            )
        if self._condition(agent, "battery", bool(short and short[0]), now):
            assert short is not None
            self._act(agent, "emergency_battery", short[1], cfg.battery_action)
        if self._condition(agent, "gps", gps_lost(status), now, cfg.gps_grace_s):
            self._act(agent, "emergency_gps", f"GPS fix {status.gps.fix} (below 3D)", cfg.gps_action)

    def _act(self, agent: _Agent, kind: str, message: str, action: EmergencyAction) -> None:
        ident = agent.session.identity
        self._event(kind, f"{message}; daemon action {action}", ident, "error", {"action": action})
        if action == "pause":
            self.hold(ident, "emergency", message)
        elif action in ("rtl", "land"):
            self._emergency_order(ident, action)

    def _emergency_order(self, ident: str, action: str) -> None:
        agent = self.agents.get(ident)
        mission = self._active_mission(agent.status) if agent else None
        step = max((a[-1].step for a in mission.plans.values()), default=0) + 1 if mission else 0
        order: Action = ReturnToLaunch(step=step) if action == "rtl" else Land(step=step)
        if agent is not None:
            agent.emergency = action
        self.avoider.forget(ident)
        if mission is None:
            self._replace(ident, [order])
            return
        # Out of the mission, so its landing does not count as finishing the mission.
        self.holds.pop(ident, None)
        reason = f"daemon emergency action {action}"
        self._queue.put_nowait((ident, lambda: self.daemon.missions.withdraw(ident, reason, [order])))

    async def _ticker(self) -> None:
        """Re-assert holds periodically and catch drones whose reports stopped."""
        last_reassert = time.monotonic()
        while True:
            await asyncio.sleep(
                min(self.config.emergency.check_period_s, self.config.collision.reassert_period_s)
            )
            now = time.monotonic()
            try:
                if now - last_reassert >= self.config.collision.reassert_period_s:
                    last_reassert = now
                    for ident, owners in list(self.holds.items()):
                        reason = next(iter(owners.values()))
                        self._send(
                            ident,
                            PerformActions(
                                mission_id=self._mission_id(ident), mode="pause", reason=reason[:200]
                            ),
                        )
                if self.config.emergency.enabled:
                    self._stale_checks(now)
                if self.config.collision.enabled and self.frame is not None and self.avoider.holds:
                    self.check_collisions(now)  # releases must not wait for the next report
            except Exception:
                log.exception("cooperation ticker failed")

    def _stale_checks(self, now: float) -> None:
        limit = self._stale_limit()
        for agent in list(self.agents.values()):
            airborne = agent.status.armed and not agent.status.landed
            age = now - agent.received
            if self._condition(agent, "stale", agent.session.open and airborne and age > limit, now):
                self._act(
                    agent,
                    "emergency_stale",
                    f"no status for {age:.1f} s (limit {limit:.1f} s)",
                    self.config.emergency.stale_action,
                )

    # --- pre-flight -----------------------------------------------------------------------------

    def _start_points(self, plans: dict[str, list[Action]]) -> dict[str, tuple[float, float, float]]:
        homes: dict[str, tuple[float, float, float]] = {}
        for ident in plans:
            session = self.daemon.agents.session(ident)
            status = session.status if session else None
            if status is not None and status.position is not None:
                homes[ident] = (status.position.lat, status.position.lon, max(status.position.alt_rel, 0.0))
            elif session is not None and session.home is not None:
                homes[ident] = (session.home.lat, session.home.lon, 0.0)
        return homes

    async def _preflight(self, task: TaskFile, plans: dict[str, list[Action]]) -> None:
        homes = self._start_points(plans)
        if set(homes) != set(plans):
            return  # positions unknown yet; the mission runner checks connections itself
        if self.config.connectivity.enabled and self.config.connectivity.preflight:
            self._preflight_links(plans, homes)
        if self.config.energy.enabled:
            self._preflight_energy(task, plans, homes)

    def _preflight_links(
        self, plans: dict[str, list[Action]], homes: dict[str, tuple[float, float, float]]
    ) -> None:
        w = self._link_range()
        first = next(iter(homes.values()))
        base = self.base or (first[0], first[1])
        if w is None:
            return
        frame = self.frame or LocalFrame(base[0], base[1])
        problems = preflight_disconnections(
            plans, homes, frame, frame.point(*base), w, self.config.connectivity.multihop
        )
        for step, ident in problems:
            self.daemon.events.publish(
                "connectivity_warning",
                f"planned step {step} leaves {ident} out of link range ({w:.0f} m) of the base and the fleet",
                severity="warning",
                agent=ident,
                data={"step": step, "preflight": True},
            )

    def predict_energy(
        self, plans: dict[str, list[Action]], homes: dict[str, tuple[float, float, float]]
    ) -> dict[str, tuple[float, float, float]]:
        """Per agent: (plan time s, plan distance m, predicted Wh)."""
        estimates = estimate_mission(plans, homes, self.config.energy)
        return {a: (t, d, self.energy_model.predict_wh(t, d)) for a, (t, d) in estimates.items()}

    def _preflight_energy(
        self, task: TaskFile, plans: dict[str, list[Action]], homes: dict[str, tuple[float, float, float]]
    ) -> None:
        cfg = self.config.energy
        refusals = []
        report: dict[str, dict[str, float]] = {}
        for ident, (t, d, need) in self.predict_energy(plans, homes).items():
            session = self.daemon.agents.session(ident)
            capacity = (session.capabilities.battery_wh if session else None) or cfg.default_battery_wh
            status = session.status if session else None
            pct = status.battery.pct if status is not None and status.battery.pct is not None else 100.0
            available = capacity * pct / 100.0
            reserve = capacity * cfg.reserve_pct / 100.0
            report[ident] = {
                "plan_time_s": round(t, 1),
                "plan_distance_m": round(d, 1),
                "predicted_wh": round(need, 2),
                "available_wh": round(available, 2),
                "reserve_wh": round(reserve, 2),
            }
            if need + reserve > available:
                refusals.append(
                    f"{ident} needs {need:.1f} Wh (plan {t:.0f} s, {d:.0f} m) + reserve {reserve:.1f} Wh "
                    f"but has {available:.1f} Wh ({pct:.0f}% of {capacity:.0f} Wh)"
                )
        self.daemon.events.publish(
            "energy_prediction",
            f"{task.name}: "
            + "; ".join(
                f"{a} {r['predicted_wh']:.1f} of {r['available_wh']:.1f} Wh" for a, r in report.items()
            ),
            severity="warning" if refusals else "info",
            data={"agents": report, "model_trained_on": self.energy_model.trained_on},
        )
        if refusals:
            raise MissionRejected("energy check: " + "; ".join(refusals))

    # --- flight logs ----------------------------------------------------------------------------

    def _record(self, agent: _Agent, status: StatusReport) -> None:
        directory = self.config.energy.record_dir
        if directory is None:
            return
        if agent.recorder is None and status.armed:
            self._recordings += 1
            name = f"{status.mission_id or 'none'}_{agent.session.identity}_{self._recordings}"
            agent.recorder = FlightLogWriter(
                Path(directory) / f"{name}.csv", self.config.energy.record_time_scale
            )
            self._write_plan_sidecar(agent, Path(directory) / f"{name}.plan.json", status)
        if agent.recorder is not None:
            agent.recorder.add(status)
            if status.landed and not status.armed:
                agent.recorder.close()
                agent.recorder = None

    def _write_plan_sidecar(self, agent: _Agent, path: Path, status: StatusReport) -> None:
        mission = self._active_mission(status)
        ident = agent.session.identity
        if mission is None or ident not in mission.plans:
            return
        homes = self._start_points(mission.plans)
        if set(homes) != set(mission.plans):
            return
        estimate = estimate_mission(mission.plans, homes, self.config.energy)[ident]
        payload = {
            "agent": ident,
            "mission_id": mission.id,
            "home": list(homes[ident]),
            "planned": [round(v, 3) for v in estimate],
            "actions": [a.model_dump(exclude_none=True) for a in mission.plans[ident]],
        }
        path.write_text(json.dumps(payload))


def finite(value: float) -> bool:
    return math.isfinite(value)

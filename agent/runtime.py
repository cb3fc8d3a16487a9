"""Composition root of the agent: autopilot + command queue + monitor + daemon link + status loop."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

from agent.autopilot.base import (
    HEARTBEAT_TIMEOUT_S,
    Autopilot,
    AutopilotError,
    FenceCircle,
    FenceSpec,
    Telemetry,
)
from agent.beacon import BeaconListener
from agent.command_queue import CommandQueue
from agent.config import AgentConfig
from agent.executor import ActionExecutor
from agent.limits import Place, Refusal, first_crossing, project, queue_refusal
from agent.link import DaemonLink
from agent.monitor import ExceptionMonitor, finite_or_zero
from agent.tasks import cancel_and_wait
from protocol.actions import Action, GoBy
from protocol.auth import parse_key
from protocol.beacon import parse_beacon_address
from protocol.packets import (
    ActionFailure,
    Battery,
    Geofence,
    GeoPoint,
    Gps,
    PerformActions,
    Position,
    Resume,
    SetParameters,
    StatusReport,
    SyncSignal,
    VelocityNed,
)

log = logging.getLogger("agent")

EVENT_HISTORY = 50
RECENT_EXCEPTION_S = 10.0


def fence_spec(fence: Geofence) -> FenceSpec:
    """The autopilot-side form of a protocol geofence."""
    return FenceSpec(
        polygon=tuple((v.lat, v.lon) for v in fence.polygon or ()),
        circle=FenceCircle(fence.circle.lat, fence.circle.lon, fence.circle.radius_m)
        if fence.circle
        else None,
        max_alt_m=fence.max_alt_m,
        breach_action=fence.breach_action,
    )


def _clamp_pct(value: float | None) -> float | None:
    return None if value is None else min(100.0, max(0.0, value))


def build_status(
    t: Telemetry,
    queue: CommandQueue,
    exceptions: list[str],
    autopilot_link: bool,
    failure: ActionFailure | None = None,
    failsafe: str | None = None,
    pilot: str | None = None,
) -> StatusReport:
    """A type-2 report from telemetry and queue state (no position before the first 3-D fix)."""
    return StatusReport(
        time=time.time(),
        vehicle_time=t.vehicle_time_s,
        position=Position(
            lat=finite_or_zero(t.lat),
            lon=finite_or_zero(t.lon),
            alt_rel=finite_or_zero(t.alt_rel),
            alt_amsl=finite_or_zero(t.alt_amsl),
        )
        if t.position_known
        else None,
        failure=failure,
        velocity=VelocityNed(vn=finite_or_zero(t.vn), ve=finite_or_zero(t.ve), vd=finite_or_zero(t.vd)),
        heading_deg=finite_or_zero(t.heading_deg) % 360.0,
        battery=Battery(pct=_clamp_pct(t.battery_pct), voltage_v=t.voltage_v, current_a=t.current_a),
        mode=t.mode[:32],
        armed=t.armed,
        landed=t.landed,
        gps=Gps(fix=max(0, min(8, t.gps_fix)), satellites=max(0, min(255, t.satellites))),
        mission_id=queue.mission_id,
        step=queue.current_step,
        completed_step=queue.completed_step,
        queue_depth=queue.depth,
        waiting_sync=queue.waiting_sync,
        paused=queue.paused,
        exceptions=exceptions[:32],
        autopilot_link=autopilot_link,
        failsafe=failsafe,
        pilot=pilot[:32] if pilot else None,
    )


class Agent:
    """One companion-computer agent: ``await run()`` until cancelled."""

    def __init__(self, config: AgentConfig, autopilot: Autopilot) -> None:
        self.config = config
        self.settings = config.settings
        self.autopilot = autopilot
        self.executor = ActionExecutor(autopilot, config)
        self.queue = CommandQueue(
            self.executor,
            self._on_step_finished,
            self._on_action_failed,
            on_refused=self._on_refused,
            vet=self._vet,
        )
        self.link = DaemonLink(
            config,
            parse_key(config.key_hex),
            on_actions=self._on_actions,
            on_release=self._on_release,
            on_parameters=self._on_parameters,
            home=self._home,
            resume=self._resume,
            current_status=self._build_status,
        )
        self.beacon: BeaconListener | None = None  # release beacons: only when configured
        if config.release_beacon is not None:
            address = parse_beacon_address(config.release_beacon)
            self.beacon = BeaconListener(address, self.queue, self._release)
            self.link.offer_release_beacon = True
        self.monitor = ExceptionMonitor(
            autopilot,
            self.settings,
            last_daemon_contact=lambda: self.link.last_contact,
            interrupt_queue=self.queue.interrupt,
            report=self._on_exception,
        )
        self.reported: list[tuple[float, str, str]] = []  # (monotonic time, name, detail)
        self._tasks: list[asyncio.Task[None]] = []
        self._status_wakeup = asyncio.Event()

    async def run(self) -> None:
        await self.autopilot.connect()
        self.queue.start()
        self._tasks = [
            asyncio.create_task(self.link.run(), name="daemon-link"),
            asyncio.create_task(self.monitor.run(self.config.monitor_period_s), name="monitor"),
            asyncio.create_task(self._status_loop(), name="status"),
        ]
        try:
            # asyncio.wait, not gather: cancelling us must not wait on a child that ignores it;
            # shutdown() cancels the children with a bound.
            done, _ = await asyncio.wait(self._tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in done:
                task.result()  # a crashed part of the agent is an error, not a silent stop
        finally:
            await self.shutdown()

    async def shutdown(self) -> None:
        """Stop every part, each even when one before it fails: a part left running (above all
        the autopilot link's reader thread, which reconnects by itself) outlives the agent."""
        await cancel_and_wait(self._tasks)
        self._tasks = []
        steps = [self.link.stop, self.queue.stop, self.autopilot.close]
        if self.beacon is not None:
            steps.insert(1, self.beacon.close)
        for step in steps:
            try:
                await step()
            except Exception:
                log.exception("agent shutdown: %s failed", getattr(step, "__qualname__", step))

    # --- status ---------------------------------------------------------------------------------

    async def _status_loop(self) -> None:
        while True:
            await self.link.send_status(self._build_status())
            self._status_wakeup.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.settings.status_period_s):
                    await self._status_wakeup.wait()

    def _build_status(self) -> StatusReport:
        t = self.autopilot.telemetry()
        link_ok = time.monotonic() - t.last_heartbeat_monotonic < HEARTBEAT_TIMEOUT_S
        return build_status(
            t,
            self.queue,
            self.exception_list(),
            link_ok,
            self.executor.failure,
            self.monitor.failsafe_text(),
            self.monitor.pilot.mode,
        )

    def exception_list(self) -> list[str]:
        """Active conditions plus one-shot exceptions of the last ``RECENT_EXCEPTION_S`` seconds."""
        now = time.monotonic()
        active = {name: f"{name}: {c.detail}" for name, c in self.monitor.active.items()}
        for when, name, detail in self.reported:
            if now - when <= RECENT_EXCEPTION_S and name not in active and not name.endswith("_cleared"):
                active[name] = f"{name}: {detail}" if detail else name
        return [text[:200] for _, text in sorted(active.items())]

    def _home(self) -> GeoPoint | None:
        t = self.autopilot.telemetry()
        if t.home_lat is None or t.home_lon is None:
            return None
        return GeoPoint(lat=t.home_lat, lon=t.home_lon, alt_amsl=t.home_alt_amsl or 0.0)

    def _resume(self) -> Resume | None:
        if self.queue.mission_id is None:
            return None
        return Resume(
            mission_id=self.queue.mission_id,
            completed_step=self.queue.completed_step,
            waiting_step=self.queue.waiting_sync,
            queue_depth=self.queue.depth,
        )

    # --- handlers -------------------------------------------------------------------------------

    async def _on_actions(self, packet: PerformActions) -> None:
        if packet.release_anchor is not None and self.beacon is not None:
            await self.beacon.arm(packet.mission_id, packet.release_anchor)
        if self.monitor.pilot.active:
            await self._pilot_has_it(packet)
            self._status_wakeup.set()
            return
        failsafe = self.monitor.failsafe
        if failsafe is not None:
            if packet.source != "operator":
                await self._on_exception(
                    "command_refused",
                    f"{packet.mode} from {packet.source or 'daemon'} refused: in failsafe "
                    f"{failsafe.name} ({failsafe.reaction}); only an operator command overrides it",
                )
                return
            log.warning("operator %s overrides failsafe %s", packet.mode, failsafe.name)
            self.monitor.clear_failsafe()
        if packet.mode == "pause":
            log.info("paused: %s", packet.reason or "no reason given")
            try:
                await self.queue.pause(packet.reason)
            except AutopilotError as exc:
                await self._on_exception("pause_failed", str(exc))
        elif packet.mode == "resume":
            log.info("resumed: %s", packet.reason or "no reason given")
            self.queue.resume()
        else:
            await self._take_actions(packet)
        self._status_wakeup.set()

    async def _pilot_has_it(self, packet: PerformActions) -> None:
        """A type-4 order while a pilot flies the vehicle: refused, but for the operator's release."""
        pilot = self.monitor.pilot
        who = packet.source or "daemon"
        if packet.mode != "resume" or packet.source != "operator":
            await self._on_exception(
                "command_refused",
                f"{packet.mode} from {who} refused: pilot in control in {pilot.mode}; the pilot hands "
                "back by selecting the agent's mode, or the operator releases (resume)",
            )
            return
        t = self.autopilot.telemetry()
        refusal = pilot.release_refusal(t)
        if refusal is not None:
            await self._on_exception("command_refused", f"release from operator refused: {refusal}")
            return
        log.warning("operator released the pilot's control in %s", pilot.mode)
        mode = pilot.mode
        pilot.release()
        self.queue.resume()
        await self._on_exception("pilot_released", f"by the operator in {mode}; the agent commands it again")

    async def _take_actions(self, packet: PerformActions) -> None:
        """Queue a replace/append batch within the agent's limits (agent/limits.py).

        A batch that would overfill the queue is refused whole. Otherwise the batch is applied
        in sequence from where the vehicle will be (its position, then whatever stays queued
        ahead): the actions before the first one that would cross a limit are queued and fly;
        that one and the rest of the batch are refused. The daemon is told at once
        (``command_refused``), and again with the status ``failure`` when the vehicle gets to
        the refused step, empties its queue and holds (the contract of a failed action).
        """
        actions: list[Action] = list(packet.actions)
        replacing = packet.mode == "replace" or packet.mission_id != self.queue.mission_id
        limits = self.config.limits
        whole = queue_refusal(len(actions), 0 if replacing else self.queue.depth, limits)
        if whole is not None:
            await self._refuse_batch(packet, len(actions), whole, replacing)
            return
        home = self._home_latlon()
        start = self._place()
        if not replacing:
            start = project(self.queue.planned(), start, home)
        crossing = first_crossing(actions, start, limits, home, self.monitor.geofence)
        if crossing is not None and crossing.index is not None:
            kept = crossing.index
            detail = (
                f"{packet.mode} of {len(actions)} actions for {packet.mission_id}: {crossing.reason}; "
                f"refused from step {crossing.step} on ({len(actions) - kept} actions), "
                f"the {kept} before it fly, then the vehicle holds"
            )
            log.error("%s", detail)
            await self._on_exception("command_refused", detail)
            actions = actions[:kept]
        log.info("%s %d actions for mission %s", packet.mode, len(actions), packet.mission_id)
        await self.queue.submit(
            packet.mission_id,
            actions,
            replace=packet.mode == "replace",
            await_release=packet.await_release,
            refusal=crossing,
        )

    async def _refuse_batch(
        self, packet: PerformActions, count: int, refusal: Refusal, replacing: bool
    ) -> None:
        """Refuse a whole batch: the queue is emptied and the vehicle holds, as after a failure."""
        detail = f"{packet.mode} of {count} actions for {packet.mission_id} refused: {refusal.reason}"
        log.error("%s", detail)
        if replacing:
            await self.queue.submit(packet.mission_id, [], replace=True)
        else:
            await self.queue.interrupt()
        step = refusal.step if refusal.step >= 0 else max(0, self.queue.completed_step + 1)
        await self._on_refused(Refusal(None, step, refusal.kind, refusal.reason), detail)

    def _home_latlon(self) -> tuple[float, float] | None:
        t = self.autopilot.telemetry()
        return (t.home_lat, t.home_lon) if t.home_lat is not None and t.home_lon is not None else None

    def _place(self) -> Place:
        """Where the vehicle is now, for the limits (no lat/lon before the first 3-D fix)."""
        t = self.autopilot.telemetry()
        alt = finite_or_zero(t.alt_rel)
        if not t.position_known:
            return Place(None, None, alt)
        return Place(t.lat, t.lon, alt)

    def _vet(self, action: Action) -> Refusal | None:
        """The last check before ``action`` starts: its limits from the actual position (a go_by
        from the point the plan so far leads to, where the executor takes it from)."""
        anchor = self.executor.anchor
        start = Place(*anchor) if isinstance(action, GoBy) and anchor is not None else self._place()
        return first_crossing([action], start, self.config.limits, self._home_latlon(), self.monitor.geofence)

    async def _on_refused(self, refusal: Refusal, detail: str | None = None) -> None:
        """An action refused by the agent's limits: reported like a failure, the vehicle holds."""
        self.executor.failure = ActionFailure(
            step=refusal.step,
            kind=refusal.kind,
            reason=f"refused by the agent: {refusal.reason}"[:300],
            time=time.time(),
        )
        await self._on_exception("command_refused", detail or f"{refusal.reason}; queue emptied, holding")
        if self.monitor.pilot.active:
            return  # the pilot flies it: nothing that moves the vehicle
        with contextlib.suppress(AutopilotError):
            await self.executor.hold_vehicle()

    async def _on_release(self, signal: SyncSignal) -> None:
        self._release(signal.mission_id, signal.step)

    def _release(self, mission_id: str, step: int) -> None:
        """A barrier release, by TCP (type 5) or by a release beacon: whichever comes first counts."""
        self.queue.release(mission_id, step)

    async def _on_parameters(self, packet: SetParameters) -> None:
        if packet.parameters is not None:
            changed = self.settings.apply(packet.parameters)
            if changed:
                log.info("parameters changed: %s", ", ".join(changed))
        if packet.clear_geofence:
            self.monitor.geofence = None
        if packet.geofence is not None:
            self.monitor.geofence = packet.geofence
            enforced = await self.autopilot.upload_fence(fence_spec(packet.geofence))
            log.info("geofence installed (autopilot enforces it too: %s)", enforced)

    async def _on_step_finished(self, mission_id: str, step: int) -> None:
        self._status_wakeup.set()
        await self.link.send_control(SyncSignal(mission_id=mission_id, step=step, kind="finished"))

    async def _on_action_failed(self, action: Action, reason: str) -> None:
        await self._on_exception("action_failed", reason)
        if self.monitor.pilot.active:
            return  # the pilot flies it: nothing that moves the vehicle
        with contextlib.suppress(AutopilotError):
            await self.executor.hold_vehicle()

    async def _on_exception(self, name: str, detail: str) -> None:
        self.reported.append((time.monotonic(), name, detail))
        del self.reported[:-EVENT_HISTORY]
        self._status_wakeup.set()

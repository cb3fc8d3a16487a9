"""Prometheus metrics of one daemon (``GET /metrics``).

A private :class:`CollectorRegistry` per daemon, so several daemons in one process (tests,
benchmarks) never share counters. Fed from the agent manager's hooks and the event stream:

* ``fleetgcs_agents_connected`` / ``fleetgcs_agents_lost``: gauges read at scrape time;
* ``fleetgcs_status_reports_total`` (per agent) and ``fleetgcs_status_rate_hz`` (fleet-wide,
  over the last 10 s), so a silent or chatty agent shows without a PromQL ``rate()``;
* ``fleetgcs_barrier_wait_seconds``: per agent, from its ``finished`` to the barrier's release;
* ``fleetgcs_agents_waiting_sync``: agents currently held at a barrier;
* ``fleetgcs_command_latency_seconds`` (per command): time to deliver an operator command to
  every target agent (write + drain on each TCP connection);
* ``fleetgcs_agents_held`` / ``fleetgcs_holds_total``: agents reporting ``paused`` and how often
  an agent entered a hold (operator pause, collision-avoidance hold...);
* ``fleetgcs_hook_events_total`` (per consumer and outcome: delivered, coalesced, dropped,
  overflow, failed) and ``fleetgcs_hook_queue_depth`` (per consumer): the hook consumers of
  gcs/link/dispatch.py, so a slow or failing service shows;
* ``fleetgcs_outbox_frames_queued``: frames waiting in all agents' outbound queues;
* ``fleetgcs_release_beacons_total`` (outcome: sent, failed): barrier releases announced by UDP
  beacon (protocol/beacon.py), when ``release_beacon`` is configured.
"""

from __future__ import annotations

import collections
import time
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from gcs.observe.events import Event
from protocol.packets import StatusReport, SyncSignal

if TYPE_CHECKING:
    from gcs.core.context import DaemonParts
    from gcs.link.session import AgentSession

RATE_WINDOW_S = 10.0
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class DaemonMetrics:
    """Counters and gauges of one daemon; ``render()`` gives the Prometheus text format."""

    def __init__(self, daemon: DaemonParts) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self._daemon = daemon
        self.connected = Gauge("fleetgcs_agents_connected", "agents with an open session", registry=r)
        self.connected.set_function(lambda: len(daemon.agents.connected()))
        self.lost = Gauge("fleetgcs_agents_lost", "agents marked lost", registry=r)
        self.lost.set_function(lambda: len(daemon.agents.lost))
        self.missions = Gauge("fleetgcs_missions_active", "missions running", registry=r)
        self.missions.set_function(lambda: len(daemon.missions.active))
        self.status = Counter("fleetgcs_status_reports", "status reports received", ["agent"], registry=r)
        self.rate = Gauge(
            "fleetgcs_status_rate_hz", "fleet status reports per second (10 s window)", registry=r
        )
        self.rate.set_function(self.status_rate_hz)
        self.barrier_wait = Histogram(
            "fleetgcs_barrier_wait_seconds",
            "time an agent waited at a sync barrier (its finished -> release)",
            buckets=(0.05, 0.1, 0.25, 0.5, 1, 2, 5, 10, 30, 60, 120, 300),
            registry=r,
        )
        self.waiting = Gauge("fleetgcs_agents_waiting_sync", "agents waiting at a sync barrier", registry=r)
        self.waiting.set_function(
            lambda: sum(
                1 for s in daemon.agents.connected() if s.status and s.status.waiting_sync is not None
            )
        )
        self.command_latency = Histogram(
            "fleetgcs_command_latency_seconds",
            "time to deliver an operator command to all its target agents",
            ["command"],
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 5),
            registry=r,
        )
        self.held = Gauge("fleetgcs_agents_held", "agents reporting a hold (paused)", registry=r)
        self.held.set_function(
            lambda: sum(1 for s in daemon.agents.connected() if s.status and s.status.paused)
        )
        self.holds = Counter("fleetgcs_holds", "times an agent entered a hold", ["agent"], registry=r)
        self.events = Counter("fleetgcs_events", "events published", ["kind", "severity"], registry=r)
        self.ws_clients = Gauge("fleetgcs_stream_clients", "WebSocket stream clients", registry=r)
        self.outbox = Gauge(
            "fleetgcs_outbox_frames_queued", "frames waiting in the agents' outbound queues", registry=r
        )
        self.outbox.set_function(lambda: sum(s.outbox.queued for s in daemon.agents.connected()))
        r.register(_HookCollector(daemon))
        r.register(_BeaconCollector(daemon))
        self._recent: collections.deque[float] = collections.deque(maxlen=200_000)
        self._arrivals: dict[tuple[str, int, str], float] = {}
        self._paused: dict[str, bool] = {}
        self._first: float | None = None

    # --- hooks ------------------------------------------------------------------------------------

    def on_status(self, session: AgentSession, status: StatusReport) -> None:
        self.on_report(session.identity, status.paused)

    def on_report(self, identity: str, paused: bool) -> None:
        """One status report of ``identity`` (the live hub reads ``paused`` from the tick's columns)."""
        now = time.monotonic()
        self.status.labels(identity).inc()
        self._recent.append(now)
        if self._first is None:
            self._first = now
        was = self._paused.get(identity, False)
        if paused and not was:
            self.holds.labels(identity).inc()
        self._paused[identity] = paused

    def on_sync(self, session: AgentSession, signal: SyncSignal) -> None:
        self._arrivals.setdefault((signal.mission_id, signal.step, session.identity), time.monotonic())

    def on_event(self, event: Event) -> None:
        self.events.labels(event.kind, event.severity).inc()
        if event.kind != "sync_released" or event.mission_id is None:
            return
        step = event.data.get("step")
        now = time.monotonic()
        for key in [k for k in self._arrivals if k[0] == event.mission_id and k[1] == step]:
            self.barrier_wait.observe(now - self._arrivals.pop(key))

    # --- reads ------------------------------------------------------------------------------------

    def status_rate_hz(self) -> float:
        now = time.monotonic()
        while self._recent and self._recent[0] < now - RATE_WINDOW_S:
            self._recent.popleft()
        if self._first is None:
            return 0.0
        return len(self._recent) / max(0.5, min(RATE_WINDOW_S, now - self._first))

    def render(self) -> bytes:
        return generate_latest(self.registry)


class _HookCollector:
    """Reads the hook consumers' counters at scrape time (gcs/link/dispatch.py keeps them)."""

    def __init__(self, daemon: DaemonParts) -> None:
        self._daemon = daemon

    def describe(self) -> list[Metric]:
        return []

    def collect(self) -> list[Metric]:
        events = CounterMetricFamily(
            "fleetgcs_hook_events", "hook events per consumer and outcome", labels=["consumer", "outcome"]
        )
        depth = GaugeMetricFamily(
            "fleetgcs_hook_queue_depth", "events waiting for a hook consumer", labels=["consumer"]
        )
        for s in self._daemon.agents.hook_stats():
            for outcome in ("delivered", "coalesced", "dropped", "overflow", "failed"):
                events.add_metric([s.name, outcome], getattr(s, outcome))
            depth.add_metric([s.name], s.queued)
        return [events, depth]


class _BeaconCollector:
    """Reads the release-beacon sender's counters at scrape time (none when beacons are off)."""

    def __init__(self, daemon: DaemonParts) -> None:
        self._daemon = daemon

    def describe(self) -> list[Metric]:
        return []

    def collect(self) -> list[Metric]:
        sender = self._daemon.missions.beacon
        if sender is None:
            return []
        beacons = CounterMetricFamily(
            "fleetgcs_release_beacons", "barrier releases announced by UDP beacon", labels=["outcome"]
        )
        beacons.add_metric(["sent"], sender.sent)
        beacons.add_metric(["failed"], sender.failed)
        return [beacons]

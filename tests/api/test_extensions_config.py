"""Extensions (hook API + the geofence-proximity alarm), TOML configuration, and `agent doctor`."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from agent.autopilot.memory import MemoryAutopilot
from agent.config import AgentConfig
from agent.config_file import load_agent_config
from agent.doctor import diagnose
from gcs.core.config_file import load_daemon_config
from gcs.core.daemon import Daemon
from gcs.extensions import Extension, ExtensionError, load_extension
from gcs.extensions.builtin.geofence_alarm import GeofenceProximityAlarm, distance_to_fence
from protocol.geo import offset_latlon
from protocol.packets import FenceCircle, Geofence, StatusReport
from protocol.settings_file import ConfigFileError, JsonFormatter, LoggingConfig, configure_logging
from tests.api.fleet import running_fleet
from tests.backbone.helpers import HOME, new_key, running_daemon, survey_mission
from tests.support.polling import wait_for


class Recorder(Extension):
    """A test extension using every hook and helper."""

    name = "recorder"

    def __init__(self, options: dict[str, Any] | None = None) -> None:
        super().__init__(options)
        self.statuses_seen: set[str] = set()
        self.events: list[str] = []
        self.joined: list[str] = []
        self.left: list[str] = []
        self.ticks = 0

    async def setup(self) -> None:
        self.every(0.05, self._tick)

    async def _tick(self) -> None:
        self.ticks += 1

    async def on_status(self, agent: str, status: StatusReport) -> None:
        self.statuses_seen.add(agent)
        if agent == "drone-2":
            raise RuntimeError("a buggy hook must not cost the agent its connection")

    async def on_event(self, event: Any) -> None:
        self.events.append(event.kind)

    async def on_join(self, agent: str) -> None:
        self.joined.append(agent)

    async def on_leave(self, agent: str, why: str) -> None:
        self.left.append(agent)


def create_recorder(options: dict[str, Any]) -> Recorder:
    return Recorder(options)


async def test_extension_hooks_schedules_and_commands(tmp_path: Path) -> None:
    async with running_fleet(
        tmp_path, drones=2, speedup=12.0, extensions=["tests.api.test_extensions_config:create_recorder"]
    ) as fleet:
        ext = next(s for s in fleet.daemon.services if isinstance(s, Recorder))
        await wait_for(lambda: ext.statuses_seen == {"drone-1", "drone-2"} and ext.ticks >= 3, 5, "hooks")
        assert sorted(ext.joined) == ["drone-1", "drone-2"]
        assert "agent_joined" in ext.events and ext.hook_errors > 0
        assert fleet.daemon.agents.session("drone-2") is not None  # still connected despite the bug
        ext.publish("recorder_note", "hello", agent="drone-1")
        assert await ext.command("drone-1", "hold", "test")
        await wait_for(lambda: ext.statuses["drone-1"].paused, 5, "hold by an extension")
        assert await ext.command("drone-1", "resume")
        await fleet.agents[1].kill()
        await wait_for(lambda: "drone-2" in ext.left, 5, "on_leave")
    assert ext.context is not None and ext._tasks == set()
    hooks = [*fleet.daemon.agents.on_status, *fleet.daemon.agents.on_join]
    assert not [h for h in hooks if getattr(h, "__self__", None) is ext]  # its subscriptions ended with it


def test_extension_loading_errors() -> None:
    with pytest.raises(ExtensionError, match="cannot import"):
        load_extension("no.such.module")
    with pytest.raises(ExtensionError, match="create_extension"):
        load_extension("gcs.observe.events")
    alarm = load_extension("gcs.extensions.builtin.geofence_alarm", {"margin_m": 5})
    assert isinstance(alarm, GeofenceProximityAlarm) and alarm.margin_m == 5


def test_distance_to_fence_circle_polygon_and_ceiling() -> None:
    lat, lon = HOME[0], HOME[1]
    circle = Geofence(circle=FenceCircle(lat=lat, lon=lon, radius_m=100))
    assert distance_to_fence(circle, lat, lon, 0) == pytest.approx(100, abs=0.5)
    ring = [offset_latlon(lat, lon, n, e) for n, e in ((-50, -50), (-50, 50), (50, 50), (50, -50))]
    square = Geofence.model_validate({"polygon": [{"lat": a, "lon": b} for a, b in ring], "max_alt_m": 30})
    inside = offset_latlon(lat, lon, 40, 0)
    assert distance_to_fence(square, *inside, 0) == pytest.approx(10, abs=0.5)
    outside = offset_latlon(lat, lon, 60, 0)
    assert distance_to_fence(square, *outside, 0) == pytest.approx(-10, abs=0.5)
    assert distance_to_fence(square, lat, lon, 25) == pytest.approx(5, abs=0.01)


async def test_geofence_alarm_warns_and_holds_a_drone_near_the_fence(tmp_path: Path) -> None:
    fence = {"circle": {"lat": HOME[0], "lon": HOME[1], "radius_m": 40.0}}
    module = "gcs.extensions.builtin.geofence_alarm"
    async with running_fleet(
        tmp_path,
        drones=1,
        speedup=10.0,
        extensions=[module],
        extension_options={module: {"margin_m": 20.0, "action": "hold", **fence}},
    ) as fleet:
        alarm = next(s for s in fleet.daemon.services if isinstance(s, GeofenceProximityAlarm))
        await fleet.daemon.missions.submit(
            survey_mission(["drone-1"], sync_legs=3)
        )  # flies 10, then 30 m north
        await wait_for(lambda: alarm.alarms == 1, 30, "the proximity alarm")
        events = fleet.daemon.events.history(kind="geofence_proximity")
        assert len(events) == 1 and events[0].agent == "drone-1" and events[0].data["action"] == "hold"
        session = fleet.daemon.agents.session("drone-1")
        await wait_for(
            lambda: session is not None and session.status is not None and session.status.paused, 5, "hold"
        )


def test_daemon_toml_environment_and_flags(tmp_path: Path) -> None:
    path = tmp_path / "gcs.toml"
    path.write_text(
        """
[daemon]
listen_host = "0.0.0.0"
http_port = 9000
status_period_s = 0.25
extensions = ["gcs.extensions.builtin.geofence_alarm"]
[daemon.agent_parameters]
battery_low_pct = 30
[daemon.extension_options."gcs.extensions.builtin.geofence_alarm"]
margin_m = 12
[log]
json_format = true
"""
    )
    env = {
        "FLEETGCS_HTTP_PORT": "9100",
        "FLEETGCS_TELEMETRY__ENABLED": "false",
        "FLEETGCS_LOG_LEVEL": "debug",
    }
    config, log = load_daemon_config(path, {"listen_port": 5000}, env)
    assert config.listen_host == "0.0.0.0" and config.http_port == 9100 and config.listen_port == 5000
    assert config.agent_parameters.battery_low_pct == 30 and config.telemetry.enabled is False
    assert config.extension_options["gcs.extensions.builtin.geofence_alarm"]["margin_m"] == 12
    assert log.json_format and log.level == "debug"
    path.write_text("[daemon]\nhttp_port = 'eighty'\n")
    with pytest.raises(ConfigFileError, match=r"daemon\.http_port"):
        load_daemon_config(path, environ={})
    path.write_text("[deamon]\n")
    with pytest.raises(ConfigFileError, match="unknown table"):
        load_daemon_config(path, environ={})
    with pytest.raises(ConfigFileError, match="not valid TOML"):
        path.write_text("[daemon\n")
        load_daemon_config(path, environ={})
    for example in Path(__file__).resolve().parents[2].glob("deploy/*.toml"):
        if example.name.startswith("gcs"):
            load_daemon_config(example, environ={})
        else:
            load_agent_config(example, {"key_hex": "ab" * 16}, environ={})


def test_agent_toml_with_key_file_and_environment(tmp_path: Path) -> None:
    key = tmp_path / "fleet.key"
    key.write_text("cd" * 32 + "\n")
    path = tmp_path / "agent.toml"
    path.write_text(
        f"""
[agent]
identity = "drone-7"
gcs_host = "10.0.0.1"
key_file = "{key}"
[agent.settings]
battery_low_pct = 35
[autopilot]
connection = "/dev/serial0:921600"
"""
    )
    loaded = load_agent_config(path, environ={"FLEETGCS_AGENT_GCS_PORT": "4500"})
    assert loaded.agent.identity == "drone-7" and loaded.agent.gcs_port == 4500
    assert loaded.agent.key_hex == "cd" * 32 and loaded.agent.settings.battery_low_pct == 35
    assert loaded.autopilot.connection == "/dev/serial0:921600" and loaded.autopilot.backend == "mavlink"
    overridden = load_agent_config(path, {"identity": "drone-8"}, environ={"FLEETGCS_AGENT_IDENTITY": "x"})
    assert overridden.agent.identity == "drone-8"


def test_json_logs_rotate(tmp_path: Path) -> None:
    import logging

    log_file = tmp_path / "logs" / "gcs.log"
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        configure_logging(LoggingConfig(json_format=True, file=log_file, max_bytes=2048, backups=2))
        for i in range(200):
            logging.getLogger("gcs.test").info("message %d", i)
    finally:
        for handler in list(root.handlers):
            root.removeHandler(handler)
            handler.close()
        for handler in saved[0]:
            root.addHandler(handler)
        root.setLevel(saved[1])
    files = sorted(p.name for p in log_file.parent.iterdir())
    assert files == ["gcs.log", "gcs.log.1", "gcs.log.2"]
    last = json.loads(log_file.read_text().splitlines()[-1])
    assert last["logger"] == "gcs.test" and last["message"] == "message 199" and last["level"] == "info"
    assert JsonFormatter().format(logging.LogRecord("x", 40, "f", 1, "boom", None, None)).startswith("{")


async def test_agent_doctor_reports_a_healthy_setup_and_a_wrong_key(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        config = AgentConfig(identity="doc-1", gcs_port=daemon.listen_port, key_hex=key)
        autopilot = MemoryAutopilot((HOME[0], HOME[1], HOME[2]), speedup=5.0)
        report = await diagnose(config, autopilot, drift_interval_s=0.2, timeout=5)
        text = report.render()
        assert report.ok, text
        names = [c.name for c in report.checks]
        assert {"key", "autopilot link", "GPS", "daemon link", "time sync", "clock drift"} <= set(names), text
        assert "accepted doc-1" in text
        wrong = config.model_copy(update={"key_hex": new_key()})
        bad = await diagnose(wrong, None, drift_interval_s=0, timeout=5)
        assert not bad.ok and "[FAIL] daemon link" in bad.render() and "wrong key" in bad.render()
    closed = await diagnose(config, None, drift_interval_s=0, timeout=2)
    assert "[FAIL] daemon link: cannot connect" in closed.render()
    assert "gcs serve" in closed.render()
    await asyncio.sleep(0)


def test_daemon_loads_extensions_from_its_config(tmp_path: Path) -> None:
    from tests.backbone.helpers import daemon_config

    daemon = Daemon(daemon_config(tmp_path, new_key(), extensions=["gcs.extensions.builtin.geofence_alarm"]))
    assert any(isinstance(s, GeofenceProximityAlarm) for s in daemon.services)
    daemon.store.close()


def test_examples_import_and_the_example_extension_loads() -> None:
    import importlib

    for name in ("examples.watch_fleet", "examples.fly_search"):
        importlib.import_module(name)
    ext = load_extension("examples.battery_watch_extension:BatteryWatch", {"hold_below_pct": 40})
    assert ext.name == "battery-watch" and ext.limit == 40  # type: ignore[attr-defined]

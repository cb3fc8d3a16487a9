"""The API's shape (gcs/http/): its route table, routes that reach the daemon only through ports, the
live hub built once by the daemon, and retiring an agent as the agent manager's own use case."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from fastapi.routing import APIRoute, APIWebSocketRoute

import gcs.http.routes
from gcs.core.daemon import Daemon
from gcs.http.app import create_app, flat_routes
from gcs.link.sessions import RetireRefused
from gcs.observe.live import LiveHub
from tests.backbone.helpers import daemon_config, new_key, running_daemon, start_agent, stop_agents
from tests.support.polling import wait_for

pytestmark = pytest.mark.timeout(60)

ROUTES = {
    ("/api/v1/health", "GET"),
    ("/api/v1/ui-config", "GET"),
    ("/api/v1/tiles/{z}/{x}/{y}", "GET"),
    ("/api/v1/agents", "GET"),
    ("/api/v1/agents/{identity}", "GET"),
    ("/api/v1/agents/{identity}", "DELETE"),
    ("/api/v1/agents/{identity}/history", "GET"),
    ("/api/v1/agents/{identity}/authority", "GET"),
    ("/api/v1/events", "GET"),
    ("/api/v1/stream", "WEBSOCKET"),
    ("/metrics", "GET"),
    ("/api/v1/missions", "GET"),
    ("/api/v1/missions", "POST"),
    ("/api/v1/plan", "POST"),
    ("/api/v1/missions/plan", "POST"),
    ("/api/v1/missions/import", "POST"),
    ("/api/v1/missions/{mission_id}", "GET"),
    ("/api/v1/missions/{mission_id}/plan", "GET"),
    ("/api/v1/missions/{mission_id}/coverage", "GET"),
    ("/api/v1/missions/{mission_id}/retask", "GET"),
    ("/api/v1/missions/{mission_id}/retask/{decision_id}/{answer}", "POST"),
    ("/api/v1/missions/{mission_id}/report", "GET"),
    ("/api/v1/missions/{mission_id}/abort", "POST"),
    ("/api/v1/missions/{mission_id}/pause", "POST"),
    ("/api/v1/missions/{mission_id}/resume", "POST"),
    ("/api/v1/fleet/rtl", "POST"),
    ("/api/v1/fleet/land", "POST"),
    ("/api/v1/fleet/hold", "POST"),
    ("/api/v1/fleet/resume", "POST"),
    ("/api/v1/geofence", "GET"),
    ("/api/v1/geofence", "POST"),
    ("/", "GET"),
    ("/docs", "GET"),
}
"""Every route of a standalone daemon (the split into routers kept them all, methods included)."""


def test_route_table_and_schema_paths(tmp_path: Path) -> None:
    daemon = Daemon(daemon_config(tmp_path, new_key(), http_host="127.0.0.1", api_token="t"))
    app = create_app(daemon)
    every = flat_routes(app)
    routes = {(r.path, m) for r in every if isinstance(r, APIRoute) for m in r.methods or ()}
    routes |= {(r.path, "WEBSOCKET") for r in every if isinstance(r, APIWebSocketRoute)}
    assert routes == ROUTES
    schema = {(p, m.upper()) for p, ops in app.openapi()["paths"].items() for m in ops}
    hidden = {("/api/v1/tiles/{z}/{x}/{y}", "GET"), ("/metrics", "GET"), ("/", "GET"), ("/docs", "GET")}
    assert schema == {r for r in ROUTES if r[1] != "WEBSOCKET"} - hidden
    assert len(app.openapi()["paths"]) == 25


def test_routes_never_import_the_daemon() -> None:
    """Routes get ports (gcs/http/ports.py) through dependencies, never the whole Daemon."""
    folder = Path(gcs.http.routes.__file__).parent
    for source in sorted(folder.glob("*.py")):
        tree = ast.parse(source.read_text())
        imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        assert "gcs.core.daemon" not in imported, source.name
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        assert "daemon" not in names, source.name


async def test_the_daemon_builds_one_live_hub(tmp_path: Path) -> None:
    async with running_daemon(tmp_path, new_key(), http_host="127.0.0.1", http_port=0) as daemon:
        hubs = [s for s in daemon.services if isinstance(s, LiveHub)]
        assert hubs == [daemon.live_hub()]
        second = create_app(daemon)  # another app over the same daemon shares its hub
        assert second.state.hub is hubs[0]
        assert [s for s in daemon.services if isinstance(s, LiveHub)] == hubs


async def test_retire_takes_a_lost_agent_off_the_list(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = daemon.agents
        drone = start_agent("drone-1", daemon.listen_port, key)
        try:
            await wait_for(lambda: agents.session("drone-1") is not None, 10, "drone-1 to join")
            with pytest.raises(RetireRefused) as connected:
                agents.retire("drone-1")
            assert connected.value.status == 409 and "stop its agent first" in connected.value.detail
        finally:
            await stop_agents([drone])
        await wait_for(lambda: "drone-1" in agents.lost, 15, "drone-1 to be lost")
        with pytest.raises(RetireRefused) as busy:
            agents.retire("drone-1", mission="m-1")
        assert busy.value.status == 409 and "m-1" in busy.value.detail
        assert "drone-1" in agents.sessions and "drone-1" in agents.lost
        session = agents.retire("drone-1")
        assert session.identity == "drone-1" and not session.open
        assert "drone-1" not in agents.sessions and "drone-1" not in agents.lost
        with pytest.raises(RetireRefused) as gone:
            agents.retire("drone-1")
        assert gone.value.status == 404
        assert "drone-1" in daemon.store.known_agents()  # its CID stays reserved

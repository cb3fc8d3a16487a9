"""What the agent loads to run with the MAVLink backend, and what it must not (issue 29: the agent's memory).

A fresh interpreter imports what ``agent run`` imports with ``--autopilot-backend mavlink`` (the
command line, the runtime, the backend) and lists ``sys.modules``: none of the modules below may
be in it. Each was measured in the agent's RSS (docs/performance.md, "Issue 29") and is kept out
or loaded on first use; an eager import of any of them again fails here by name, before the
bench would show the memory come back.
"""

from __future__ import annotations

import json
import subprocess
import sys

from tests.support.paths import ROOT

AGENT_RUN_IMPORTS = (
    "import agent.cli, agent.runtime\n"
    "from agent.autopilot import mavlink_backend\n"
    "import sys, json\n"
    "print(json.dumps(sorted(sys.modules)))\n"
)

KEPT_OUT = {
    "gcs": "the ground station (never imported by the agent)",
    "sitl": "the simulator",
    "numpy": "pymavlink's mavexpression -> mavextra (log filtering only)",
    "shapely": "geometry of the ground station",
    "scipy": "planning of the ground station",
    "fastapi": "the daemon's HTTP API",
    "mavsdk": "the PX4 backend (an extra)",
    "pymavlink.mavexpression": "log-expression evaluator (agent/autopilot/lean_mavutil.py)",
    "pymavlink.dialects.v10.all": "the v1 'all' dialect mavutil imports for pyinstaller",
    "pymavlink.generator.mavparse": "the XML dialect parser (with expat)",
    "xml.parsers.expat": "expat, for the dialect parser",
    "curses": "ncurses, for mavutil's is_printable",
    "tomllib": "the TOML reader (only when a config file is read)",
    "logging.handlers": "the rotating file handler (only when logging to a file)",
}


def agent_modules() -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", AGENT_RUN_IMPORTS], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return set(json.loads(out.stdout))


def test_the_agent_with_the_mavlink_backend_loads_none_of_the_heavy_modules() -> None:
    modules = agent_modules()
    assert "pymavlink.mavutil" in modules and "agent.autopilot.mavlink_backend" in modules  # it did load
    loaded = {name: why for name, why in KEPT_OUT.items() if name in modules}
    assert not loaded, f"the agent now imports: {loaded}"


OPEN_A_LINK = """
import socket, sys
from agent.autopilot.mavlink_link import MavlinkLink, mavlink
autopilot = socket.create_server(("127.0.0.1", 0))  # a TCP autopilot that accepts (and stays silent)
link = MavlinkLink(
    f"tcp:127.0.0.1:{autopilot.getsockname()[1]}", target_system=None, source_system=None,
    source_component=191, heartbeat_timeout_s=1.0, command_timeout_s=1.0, command_retries=1,
    on_message=print, on_tick=lambda: None, on_link_restored=lambda: None,
)
link.open()
assert isinstance(link._conn.mav, mavlink.MAVLink) and link._conn.WIRE_PROTOCOL_VERSION == "2.0"
link._conn.close()
autopilot.close()
print(sorted(m for m in sys.modules if m in sys.argv[1:]))
# What was kept out still imports when asked for: the placeholders are gone once mavutil has loaded.
from pymavlink import mavutil
import pymavlink.generator.mavparse as mavparse, curses.ascii
assert mavparse.PROTOCOL_2_0 == "2.0" and mavparse.MAVXML
assert mavutil.is_printable(65) and not mavutil.is_printable(7) and curses.ascii.isprint(65)
from protocol.settings_file import read_toml, configure_logging
print("ok")
"""


def test_opening_the_link_loads_none_of_them_and_each_still_imports_when_asked_for() -> None:
    """``mavlink_connection(dialect=...)`` would set the dialect again, importing the XML parser; the
    stand-ins ``lean_mavutil`` puts in place while mavutil loads must be gone afterwards."""
    out = subprocess.run(
        [sys.executable, "-c", OPEN_A_LINK, *KEPT_OUT], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-2:] == ["[]", "ok"], out.stdout

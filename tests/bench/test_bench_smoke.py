"""`bench/bench_load.py --quick` runs and prints every row issue 29 asks for (no timing asserted):
the load at start, the knee, barrier releases by beacon, TCP now and TCP before side by side with
the send floor, the fleet RTL fan-out, the flood ratio and the agent's RSS with both backends."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]

ROWS = (
    "load average",
    "largest fleet sustained (the knee):",
    "barrier release at 50 agents (beacon):",
    "barrier release at 50 agents (tcp):",
    "barrier release at 50 agents (tcp_old):",
    "send floor p50",
    "TCP now / before (paired barriers)",
    "fleet RTL to the last of 20 agents:",
    "daemon / bare asyncio flood ratio:",
    "agent RSS (memory backend):",
    "agent RSS (mavlink backend):",
)


def test_bench_load_quick_prints_every_row(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "bench_load.py"), "--quick"],
        capture_output=True,
        text=True,
        timeout=400,
        env=env,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    missing = [row for row in ROWS if row not in done.stdout]
    assert not missing, f"rows not printed: {missing}\n{done.stdout[-3000:]}"
    assert "STOPPED" not in done.stdout, done.stdout[-3000:]

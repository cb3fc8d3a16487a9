"""`gcs run` on CoUAS files: a drone that never lands is refused unless the operator allows it."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _gcs_run(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    rows = [
        {"Action_type": 0, "CID": 1, "Alt": 10, "Step": 0, "Sync": False},
        {"Action_type": 2, "CID": 1, "N": 5, "E": 0, "Alt": 10, "Time": 5, "Step": 1, "Sync": True},
    ]
    task = tmp_path / "hover.json"
    task.write_text(json.dumps(rows))
    # Nothing listens on the port: an accepted file gets as far as "cannot reach the daemon".
    api = f"http://127.0.0.1:{_free_port()}"
    return subprocess.run(
        [sys.executable, "-m", "gcs", "run", str(task), "--api", api, "--token", "t", *extra],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_gcs_run_refuses_a_drone_that_never_lands(tmp_path: Path) -> None:
    refused = _gcs_run(tmp_path)
    assert refused.returncode == 2
    assert "row 2 (CID 1, Step 1): CID 1 never lands" in refused.stderr
    assert "--allow-airborne-end" in refused.stderr


def test_gcs_run_flies_it_with_a_warning_when_allowed(tmp_path: Path) -> None:
    allowed = _gcs_run(tmp_path, "--allow-airborne-end")
    assert "warning: cid 1 never land" in allowed.stderr
    assert allowed.returncode == 3 and "cannot reach the daemon" in allowed.stderr

"""`gcs serve` as the operator runs it, in a subprocess: started, then stopped with SIGTERM, or
stopped by itself at start-up (its exit code and stderr are what a test checks)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

BIN = Path(sys.executable).parent


@dataclass(frozen=True)
class ServeResult:
    started: bool  # it wrote its ready file (then it was stopped with SIGTERM)
    returncode: int
    stderr: str


def run_serve(data_dir: Path, *extra: str, start_timeout_s: float = 60.0) -> ServeResult:
    """Run ``gcs serve --data-dir DATA_DIR`` on free loopback ports without HTTP until it is ready
    (then SIGTERM) or exits by itself; bounded by ``start_timeout_s``, the process always reaped."""
    ready = data_dir.parent / f"{data_dir.name}.ready"
    ready.unlink(missing_ok=True)
    command = [str(BIN / "gcs"), "serve", "--data-dir", str(data_dir), "--listen", "127.0.0.1:0"]
    command += ["--http", "none", "--ready-file", str(ready), *extra]
    with subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) as daemon:
        try:
            deadline = time.monotonic() + start_timeout_s
            while time.monotonic() < deadline and daemon.poll() is None and not ready.exists():
                time.sleep(0.05)
        finally:
            if daemon.poll() is None:
                daemon.send_signal(signal.SIGTERM)
            try:
                _, stderr = daemon.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                daemon.kill()
                _, stderr = daemon.communicate()
    return ServeResult(ready.exists(), daemon.returncode, stderr)

"""The two installs, from the built wheel into clean venvs, as a Raspberry Pi and a ground station get them.

* the **agent** (``pip install fleetgcs``): protocol + agent + sitl with pydantic, pymavlink and
  pyserial only. It must not pull in the ground station (OR-Tools, SciPy, scikit-learn, FastAPI);
  it opens a *serial* autopilot (a pseudo-terminal relayed to the simulator, as a UART would be)
  with `agent doctor` and `agent run`, and the agent's own tests run in it;
* the **ground station** (``pip install 'fleetgcs[gcs]'``): `gcs serve` from the wheel serves
  the dashboard and offline /docs, and lists the serial agent.

Installs are offline: dependencies come from a wheelhouse kept in this venv (filled once from
pip's cache or the index, then reused with ``--no-index``), the project from the wheel just built.
"""

from __future__ import annotations

import contextlib
import os
import pty
import select
import shutil
import socket
import subprocess
import sys
import threading
import time
import tty
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.support.paths import ROOT

WHEELHOUSE = Path(sys.prefix) / "wheelhouse"
HEAVY = ("ortools", "scipy", "sklearn", "fastapi", "uvicorn", "matplotlib", "numpy", "shapely", "mavsdk")
AGENT_TESTS = ["tests/backends/units/test_backend_units.py", "tests/protocol"]

pytestmark = pytest.mark.slow


def pip(*args: str | Path, python: Path | None = None, timeout: float = 600) -> None:
    """This venv's pip (optionally installing into another interpreter's environment)."""
    target = ["--python", str(python)] if python else []
    argv = [sys.executable, "-m", "pip", *target, *map(str, args), "--disable-pip-version-check", "-q"]
    result = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"pip {' '.join(map(str, args))}:\n{result.stdout}\n{result.stderr}"


def fill_wheelhouse(dist: Path, requirements: list[str]) -> None:
    """Every dependency as a wheel in WHEELHOUSE: a no-op offline once filled."""
    WHEELHOUSE.mkdir(exist_ok=True)
    common = ["download", "-d", WHEELHOUSE, "--find-links", dist, "--only-binary", ":all:", *requirements]
    try:
        pip(*common, "--no-index", "--find-links", WHEELHOUSE)
    except AssertionError:  # first run: fetch what is missing (pip's cache makes this quick)
        pip(*common)
    for stale in WHEELHOUSE.glob("fleetgcs-*.whl"):  # the project itself always comes from dist
        stale.unlink()


def clean_venv(path: Path, dist: Path, requirement: str) -> Path:
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", path], check=True, timeout=120)
    python = path / "bin" / "python"
    pip("install", "--no-index", "--find-links", dist, "--find-links", WHEELHOUSE, "--no-compile",
        requirement, python=python)  # fmt: skip
    return python


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def serial_autopilot(sitl_port: int) -> Iterator[str]:
    """A pseudo-terminal whose other end is relayed to the simulator's TCP port: a serial autopilot."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    sock = socket.create_connection(("127.0.0.1", sitl_port), timeout=10)
    stop = threading.Event()

    def relay() -> None:
        while not stop.is_set():
            ready, _, _ = select.select([master, sock], [], [], 0.1)
            with contextlib.suppress(OSError):
                if master in ready:
                    sock.sendall(os.read(master, 4096))
                if sock in ready:
                    data = sock.recv(4096)
                    if not data:
                        return
                    os.write(master, data)

    thread = threading.Thread(target=relay, name="pty-relay", daemon=True)
    thread.start()
    try:
        yield path
    finally:
        stop.set()
        thread.join(5)
        sock.close()
        os.close(master)
        os.close(slave)


def wait_ready(path: Path, proc: subprocess.Popen[str], what: str, timeout: float = 30.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().strip():
            return path.read_text()
        assert proc.poll() is None, f"{what} exited with {proc.returncode}"
        time.sleep(0.1)
    raise AssertionError(f"{what} not ready within {timeout:.0f} s")


def stop(procs: list[subprocess.Popen[str]]) -> None:
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_agent_alone_opens_a_serial_autopilot_and_the_ground_station_serves_its_dashboard(
    tmp_path: Path,
) -> None:
    started = time.monotonic()
    dist, source = tmp_path / "dist", tmp_path / "source"
    for package in ("protocol", "gcs", "agent", "sitl"):  # what the wheel is made of
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    pip("wheel", "--no-deps", "--no-build-isolation", "-w", dist, source)  # builds in the copy, not in ROOT
    (wheel,) = dist.glob("fleetgcs-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"gcs/web/index.html", "gcs/web/app.js", "gcs/web/style.css"} <= names, sorted(names)[:20]
    fill_wheelhouse(dist, ["fleetgcs[gcs,test]"])

    agent_py = clean_venv(tmp_path / "agent-venv", dist, "fleetgcs[test]")
    gcs_py = clean_venv(tmp_path / "gcs-venv", dist, "fleetgcs[gcs]")
    present = subprocess.run(
        [agent_py, "-c", f"import importlib.util as u; print([m for m in {HEAVY!r} if u.find_spec(m)])"],
        capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    assert present == "[]", f"the agent install pulled in {present}"
    for module in ("serial", "pymavlink", "pydantic", "agent", "protocol", "sitl"):
        subprocess.run([agent_py, "-c", f"import {module}"], check=True, cwd=tmp_path)
    needs_gcs = subprocess.run(
        [agent_py.parent / "gcs", "agents"], capture_output=True, text=True, cwd=tmp_path
    )
    assert needs_gcs.returncode == 2 and "pip install 'fleetgcs[gcs]'" in needs_gcs.stderr, needs_gcs.stderr
    installed = time.monotonic() - started

    data, ready = tmp_path / "gcs-data", tmp_path / "ready"
    serve = subprocess.Popen(
        [gcs_py.parent / "gcs", "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0",
         "--data-dir", data, "--status-period", "0.2", "--ready-file", ready],
        cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    sitl_port = free_port()
    sitl = subprocess.Popen(
        [agent_py.parent / "sitl", "run", "--vehicles", "1", "--base-port", str(sitl_port),
         "--home", "47.397742,8.545594,488", "--prearm-delay", "0"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    procs = [serve, sitl]
    try:
        agent_port, http_port = map(int, wait_ready(ready, serve, "gcs serve").split())
        base = f"http://127.0.0.1:{http_port}"
        page = httpx.get(f"{base}/", follow_redirects=True, timeout=10)
        assert page.status_code == 200 and "<title>fleetgcs</title>" in page.text
        assert httpx.get(f"{base}/ui/app.js", timeout=10).status_code == 200
        docs = httpx.get(f"{base}/docs", timeout=10)
        assert docs.status_code == 200 and "/docs-assets/swagger-ui-bundle.js" in docs.text
        assert httpx.get(f"{base}/docs-assets/swagger-ui-bundle.js", timeout=10).status_code == 200

        assert sitl.stdout is not None and sitl.stdout.readline().startswith("SITL READY")
        with serial_autopilot(sitl_port) as device:
            key_file = str(data / "fleet.key")
            common = ["--id", "pi-1", "--gcs", f"127.0.0.1:{agent_port}", "--key-file", key_file,
                      "--autopilot", f"{device}:921600"]  # fmt: skip
            doctor = subprocess.run(
                [agent_py.parent / "agent", "doctor", *common, "--drift-interval", "0", "--timeout", "20"],
                capture_output=True, text=True, timeout=90, cwd=tmp_path,
            )  # fmt: skip
            assert "[ OK ] autopilot link: heartbeat" in doctor.stdout, doctor.stdout + doctor.stderr
            assert "[ OK ] daemon link" in doctor.stdout and "probe" in doctor.stdout, doctor.stdout
            agent = subprocess.Popen(
                [agent_py.parent / "agent", "run", *common], cwd=tmp_path,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            procs.insert(0, agent)  # type: ignore[arg-type]
            listing, deadline = "", time.monotonic() + 40
            while time.monotonic() < deadline:
                listing = subprocess.run(
                    [gcs_py.parent / "gcs", "agents", "--api", base],
                    capture_output=True,
                    text=True,
                    timeout=30,
                ).stdout
                rows = [line.split() for line in listing.splitlines() if "pi-1" in line]
                if rows and rows[0][2] == "up" and rows[0][3] != "-":  # joined, and reporting status
                    break
                time.sleep(0.5)
            rows = [line for line in listing.splitlines() if "pi-1" in line]
            assert rows and " up " in rows[0], listing
            assert "doctor" not in listing and len(listing.splitlines()) == 2, (
                listing
            )  # the probe never joined
            stop([agent])
    finally:
        stop(procs)

    tests = subprocess.run(
        [agent_py, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--import-mode=append", *AGENT_TESTS],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert tests.returncode == 0, tests.stdout[-3000:] + tests.stderr[-2000:]
    assert " passed" in tests.stdout
    print(doctor.stdout)
    print(f"installs {installed:.1f} s, whole test {time.monotonic() - started:.1f} s")

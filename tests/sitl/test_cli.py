"""``sitl run``: READY line, fixed and ephemeral ports, clean exit; the real ArduPilot launcher."""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from gcs.cli import build_parser as gcs_parser
from sitl.ardupilot import ArduPilotFleet
from sitl.cli import build_parser
from tests.ardupilot.binary import SKIP_REASON, ardupilot_binary
from tests.sitl.conftest import Gcs, mavlink

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _start(*args: str) -> tuple[subprocess.Popen[str], str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "sitl", "run", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 15.0)
    if not ready:
        proc.kill()
        raise AssertionError("no READY line within 15 s")
    return proc, proc.stdout.readline()


def _stop(proc: subprocess.Popen[str], sig: int = signal.SIGTERM) -> int:
    proc.send_signal(sig)
    try:
        return proc.wait(10.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5.0)
        raise AssertionError("sitl did not exit on signal") from None


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_cli_ready_line_and_clean_exit(sig: int) -> None:
    proc, line = _start(
        "--vehicles",
        "2",
        "--base-port",
        "0",
        "--speedup",
        "10",
        "--home",
        "47.39,8.54,500",
        "--seed",
        "3",
        "--legacy-mission-request",
        "--param",
        "WPNAV_SPEED=700",
        "--fail",
        "2:gps_loss@100+5",
    )
    try:
        words = line.split()
        assert words[:2] == ["SITL", "READY"] and len(words) == 4, line
        assert all(w.startswith("tcp:127.0.0.1:") for w in words[2:])
        g = Gcs(words[3], sysid=2)
        try:
            hb = g.heartbeat_msg()
            assert hb.type == mavlink.MAV_TYPE_QUADROTOR
            g.m.mav.param_request_read_send(2, 1, b"WPNAV_SPEED", -1)
            assert g.wait("PARAM_VALUE", lambda m: m.param_id == "WPNAV_SPEED").param_value == 700
        finally:
            g.close()
    finally:
        rc = _stop(proc, sig)
    assert rc == 0
    assert proc.stdout is not None and proc.stdout.read() == ""  # exactly one line on stdout


def _free_base(n: int) -> int:
    for _ in range(20):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + 10 * n > 65000:
            continue
        ok = True
        for i in range(n):
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", base + 10 * i))
                except OSError:
                    ok = False
        if ok:
            return base
    raise AssertionError("no free port range")


def test_cli_fixed_base_port_layout() -> None:
    base = _free_base(3)
    proc, line = _start("--vehicles", "3", "--base-port", str(base), "--spacing", "8")
    try:
        assert line.split()[2:] == [f"tcp:127.0.0.1:{base + 10 * i}" for i in range(3)]
    finally:
        assert _stop(proc) == 0


def test_cli_rejects_bad_arguments() -> None:
    for args in (["--fail", "1:boom@3"], ["--vehicles", "0"], ["--home", "abc"]):
        proc = subprocess.run(
            [sys.executable, "-m", "sitl", "run", "--base-port", "0", *args],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=20,
        )
        assert proc.returncode == 2, (args, proc.stderr)
        assert "SITL READY" not in proc.stdout


def test_ardupilot_command_line_layout() -> None:
    apf = ArduPilotFleet(
        "/opt/arducopter",
        3,
        (-35.36, 149.16, 500.0),
        spacing_m=10.0,
        defaults="/x/copter.parm",
        base_port=6000,
        params={"wpnav_speed": 300},
    )
    try:
        cmd = apf.command(2)
        assert cmd[0] == "/opt/arducopter" and "--wipe" in cmd
        assert cmd[cmd.index("-I") + 1] == "2" and cmd[cmd.index("--model") + 1] == "quad"
        assert cmd[cmd.index("--base-port") + 1] == "6000"
        assert cmd[cmd.index("--sysid") + 1] == "3"
        defaults = cmd[cmd.index("--defaults") + 1].split(",")
        assert defaults[0] == "/x/copter.parm"
        overrides = Path(defaults[1]).read_text()
        assert "WPNAV_SPEED 300" in overrides and "LOG_BACKEND_TYPE 0" in overrides  # no logs by default
        assert apf.endpoints == ["tcp:127.0.0.1:6000", "tcp:127.0.0.1:6010", "tcp:127.0.0.1:6020"]
        homes = {apf.command(i)[apf.command(i).index("--home") + 1] for i in range(3)}
        assert len(homes) == 3 and all(h.startswith("-35.36") for h in homes)
    finally:
        apf.stop()
    assert not Path(apf.workdir).exists()  # scratch directory removed
    with pytest.raises(ValueError, match=r"0\.0\.0\.0"):
        ArduPilotFleet("/opt/arducopter", 1, (0.0, 0.0), base_port=0, host="0.0.0.0")


def test_cli_parses_negative_coordinates_and_rejects_what_ardupilot_cannot_do() -> None:
    args = build_parser().parse_args(["run", "--home", "-35.36,149.16,584", "--wind", "-2,1"])
    assert args.home == (-35.36, 149.16, 584.0) and args.wind == (-2.0, 1.0)
    gcs = gcs_parser()
    assert gcs.parse_args(["plan", "area.json", "--home", "-35.36,-149.16"]).home == (-35.36, -149.16)
    assert gcs.parse_args(["demo", "--home", "-35.36,149.16,584"]).home == (-35.36, 149.16, 584.0)
    proc = subprocess.run(
        [sys.executable, "-m", "sitl", "run", "--ardupilot", "/nonexistent", "--fail", "1:link_drop@3+1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert proc.returncode == 2 and "--fail not supported with --ardupilot" in proc.stderr


def _listening_addresses(port: int) -> set[str]:
    """IPv4 addresses with a TCP socket listening on ``port`` (from /proc/net/tcp)."""
    found = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        addr, hexport = local.split(":")
        if state == "0A" and int(hexport, 16) == port:  # 0A = LISTEN
            found.add(socket.inet_ntoa(bytes.fromhex(addr)[::-1]))
    return found


@pytest.mark.ardupilot
@pytest.mark.skipif(ardupilot_binary() is None, reason=SKIP_REASON)
def test_real_ardupilot_fleet_via_cli() -> None:
    """Loopback only, the given base port, parameters applied, scratch directory removed at exit."""
    binary = ardupilot_binary()
    assert binary is not None
    base = _free_base(2)
    before = set(Path("/tmp").glob("fleetgcs-ardupilot-*"))
    proc, line = _start(
        "--vehicles", "2", "--ardupilot", binary, "--speedup", "5", "--base-port", str(base),
        "--home", "-35.363261,149.165230,584", "--param", "WPNAV_SPEED=600",
    )  # fmt: skip
    try:
        urls = line.split()[2:]
        assert urls == [f"tcp:127.0.0.1:{base}", f"tcp:127.0.0.1:{base + 10}"]
        assert _listening_addresses(base) == {"127.0.0.1"}  # not every interface, as SITL itself would
        for i, url in enumerate(urls):
            g = Gcs(url, sysid=i + 1)
            try:
                hb = g.heartbeat_msg(timeout=30.0)
                assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
                g.m.mav.param_request_read_send(i + 1, 1, b"WPNAV_SPEED", -1)
                assert g.wait("PARAM_VALUE", lambda m: m.param_id == "WPNAV_SPEED").param_value == 600
            finally:
                g.close()
    finally:
        assert _stop(proc) == 0
    assert set(Path("/tmp").glob("fleetgcs-ardupilot-*")) <= before  # its scratch directory is gone

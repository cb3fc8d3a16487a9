"""``agent doctor``: check what a field agent needs and print what is wrong, in plain words.

Checks, in order: the key (readable, long enough, not world-readable), the autopilot link
(heartbeat, GPS, battery, home), the daemon link (TCP/TLS connect and the full authenticated
handshake with the key, round-trip time), time sync (clock offset against the daemon's
``server_time`` in the accept, NTP state) and clock drift (the offset measured twice,
``drift_interval_s`` apart), and with ``release_beacon`` set, whether the agent can listen for
release beacons there. Exit code 0 when nothing failed.

The handshake uses the agent's own identity by default and is a *probe* (``probe: true`` in the
type-0 request): the daemon authenticates it and answers without a CID, so the check never
registers a fleet member and never replaces a running agent of that identity.
"""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import stat
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from agent.autopilot.base import Autopilot
from agent.beacon import beacon_socket
from agent.config import AgentConfig
from agent.link import V1_FALLBACK_AFTER, client_tls_context
from protocol import auth
from protocol.beacon import parse_beacon_address
from protocol.packets import SUPPORTED_VERSIONS, Close, CloseReason
from protocol.session import V1_DAEMON, ClientHandshake, Refused
from protocol.stream import FramedStream
from protocol.wire import ProtocolError

Verdict = Literal["ok", "warn", "fail", "skip"]
OFFSET_WARN_S, OFFSET_FAIL_S = 0.2, 1.0
DRIFT_WARN_PPM = 100.0
FIRST_REPORT_WAIT_S = 5.0  # GPS_RAW_INT is streamed at 2 Hz once the link is up


@dataclass
class Check:
    name: str
    verdict: Verdict
    detail: str
    hint: str = ""


@dataclass
class Report:
    checks: list[Check] = field(default_factory=list)

    def add(self, name: str, verdict: Verdict, detail: str, hint: str = "") -> Check:
        check = Check(name, verdict, detail, hint)
        self.checks.append(check)
        return check

    @property
    def ok(self) -> bool:
        return not any(c.verdict == "fail" for c in self.checks)

    def render(self) -> str:
        tags = {"ok": "[ OK ]", "warn": "[WARN]", "fail": "[FAIL]", "skip": "[SKIP]"}
        lines = []
        for c in self.checks:
            lines.append(f"{tags[c.verdict]} {c.name}: {c.detail}")
            if c.hint and c.verdict in ("warn", "fail"):
                lines.append(f"       -> {c.hint}")
        failed = sum(c.verdict == "fail" for c in self.checks)
        warned = sum(c.verdict == "warn" for c in self.checks)
        lines.append(
            "all checks passed" if not failed and not warned else f"{failed} failed, {warned} warnings"
        )
        return "\n".join(lines)


@dataclass
class Handshake:
    cid: int | None  # None: the daemon answered the probe without a CID, as it should
    rtt_s: float
    offset_s: float  # daemon clock - our clock
    version: int = 2  # the protocol version the daemon accepted


class HandshakeError(Exception):
    def __init__(self, message: str, hint: str = "") -> None:
        super().__init__(message)
        self.hint = hint


def check_key_file(report: Report, key_file: Path | None, key_hex: str) -> None:
    if key_file is not None:
        try:
            mode = key_file.stat().st_mode
        except OSError as exc:
            report.add(
                "key",
                "fail",
                f"cannot read {key_file}: {exc.strerror}",
                "copy the fleet key here (gcs keygen)",
            )
            return
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            report.add(
                "key file permissions",
                "warn",
                f"{key_file} is readable by other users (mode {stat.S_IMODE(mode):o})",
                f"chmod 600 {key_file}",
            )
    try:
        key = auth.parse_key(key_hex)
    except ValueError as exc:
        report.add("key", "fail", str(exc), "the key is hex, at least 32 digits (gcs keygen makes one)")
        return
    report.add("key", "ok", f"{len(key) * 8}-bit key")


async def check_autopilot(report: Report, autopilot: Autopilot, timeout: float) -> None:
    try:
        await asyncio.wait_for(autopilot.connect(timeout), timeout + 5)
    except Exception as exc:
        cannot_open = serial_hint(str(exc))
        report.add(
            "autopilot link",
            "fail",
            f"no heartbeat: {type(exc).__name__}: {exc}",
            cannot_open
            or "check the wiring (TX->RX, RX->TX, GND), the baud rate, SERIALn_PROTOCOL=2 on ArduPilot, "
            "and that the serial console is off "
            "(raspi-config -> Interface -> Serial: login shell no, port yes)",
        )
        return
    try:
        await _first_reports(autopilot, min(timeout, FIRST_REPORT_WAIT_S))
        t = autopilot.telemetry()
        seen = (
            f"heartbeat {time.monotonic() - t.last_heartbeat_monotonic:.1f} s ago"
            if t.last_heartbeat_monotonic > 0
            else "connected"
        )
        report.add("autopilot link", "ok", f"{seen}, mode {t.mode}, armed {t.armed}")
        if t.gps_fix >= 3:
            report.add("GPS", "ok", f"fix {t.gps_fix}, {t.satellites} satellites")
        else:
            report.add(
                "GPS", "warn", f"fix {t.gps_fix} ({t.satellites} satellites)", "wait for a 3D fix outdoors"
            )
        if t.home_lat is None:
            report.add("home position", "warn", "not set yet", "the autopilot sets home at the first 3D fix")
        pct = t.battery_pct
        if pct is None:
            report.add("battery", "warn", "no battery percentage reported", "configure the battery monitor")
        else:
            report.add("battery", "ok" if pct > 30 else "warn", f"{pct:.0f} %")
    finally:
        with contextlib.suppress(Exception):
            await autopilot.close()


async def _first_reports(autopilot: Autopilot, wait_s: float) -> None:
    """Wait (bounded) for the GPS, home and battery reports that follow the first heartbeat.

    Why: ``connect`` returns at the first heartbeat; GPS_RAW_INT and the others are streamed at
    1-2 Hz after it, so reading at once showed "fix 0 (0 satellites)" for a vehicle with a fix.
    A vehicle really without a fix costs ``wait_s`` and is then reported as it is.
    """
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        t = autopilot.telemetry()
        if t.gps_fix >= 3 and t.home_lat is not None and t.battery_pct is not None:
            return
        await asyncio.sleep(0.1)


def serial_hint(error: str) -> str:
    """What to check when a serial autopilot cannot be opened ('' when it is not that kind of error).

    A device that does not exist or may not be opened is not a wiring problem: say what it is.
    """
    if "No such file or directory" in error:
        return "no such device: is the flight controller connected? ls /dev/serial0 /dev/ttyACM* /dev/ttyUSB*"
    if "Permission denied" in error:
        return "permission denied: add the user to the dialout group (and see the unit's DeviceAllow=)"
    if "No module named" in error:
        return "a dependency is missing: reinstall fleetgcs (it brings pyserial)"
    return ""


async def handshake(config: AgentConfig, identity: str, timeout: float) -> Handshake:
    """One full authenticated handshake (a probe); measures round trip and clock offset (midpoint method).

    A version-1 daemon refuses the v2 hello without a code (an unauthenticated answer anyone on the
    path could forge); as the agent's link does, the probe speaks v1 only after
    ``V1_FALLBACK_AFTER`` such answers in a row.
    """
    for _ in range(V1_FALLBACK_AFTER):
        try:
            return await _probe(config, identity, timeout, SUPPORTED_VERSIONS)
        except _OldDaemon:
            continue
    return await _probe(config, identity, timeout, (1,))


class _OldDaemon(Exception):
    pass


async def _probe(config: AgentConfig, identity: str, timeout: float, versions: tuple[int, ...]) -> Handshake:
    key = auth.parse_key(config.key_hex)
    tls = client_tls_context(config)
    try:
        async with asyncio.timeout(timeout):
            reader, writer = await asyncio.open_connection(
                config.gcs_host,
                config.gcs_port,
                ssl=tls,
                server_hostname=(config.tls_server_name or config.gcs_host) if tls else None,
            )
    except (OSError, TimeoutError) as exc:
        raise HandshakeError(
            f"cannot connect to {config.gcs_host}:{config.gcs_port}: {exc or 'timeout'}",
            "is `gcs serve` running, listening beyond loopback (--listen 0.0.0.0:4396), "
            "and is the port open in the firewall?",
        ) from None
    stream = FramedStream(reader, writer)
    session = ClientHandshake(identity, key, versions=versions, capabilities=config.capabilities, probe=True)
    try:
        stream.version = max(session.versions)
        async with asyncio.timeout(timeout):
            await stream.send(session.hello())
            proof = session.on_challenge((await stream.read_frame()).body)
            sent = time.time()
            await stream.send(proof)
            answer = (await stream.read_frame()).body
        received = time.time()
        accepted = session.on_answer(answer)
        if accepted.server_time is None:
            raise HandshakeError("the daemon sent no server_time", "upgrade the daemon")
        offset = accepted.server_time - (sent + received) / 2
        await stream.close(Close(reason=CloseReason.NORMAL, message="agent doctor"))
        return Handshake(cid=accepted.cid, rtt_s=received - sent, offset_s=offset, version=accepted.version)
    except Refused as exc:
        if exc.code == V1_DAEMON and versions != (1,):
            raise _OldDaemon from None
        hints = {
            "unknown_identity": "is this identity listed in the daemon's agent keys?",
            "wrong_key": "the key must be the daemon's fleet key (or this agent's own key)",
            "enrollment_closed": "enroll the identity on the daemon first (or allow enrollment)",
            "banned": "the operator banned this identity",
            "certificate_mismatch": "the client certificate must name this identity (CN or DNS SAN)",
        }
        raise HandshakeError(
            f"refused ({exc.code or 'no code'}): {exc}", hints.get(exc.code or "", "")
        ) from None
    except ConnectionError:
        raise HandshakeError(
            "the daemon closed the connection", "see the daemon's log (agent_refused)"
        ) from None
    except ProtocolError as exc:
        raise HandshakeError(
            f"protocol error: {exc}", "is this port really the fleetgcs agent listener?"
        ) from None
    except TimeoutError:
        raise HandshakeError("the daemon did not answer in time", "network or daemon overloaded") from None
    finally:
        with contextlib.suppress(Exception):
            writer.close()


def ntp_state() -> str | None:
    """'yes'/'no' from timedatectl when available."""
    if shutil.which("timedatectl") is None:
        return None
    with contextlib.suppress(Exception):
        out = subprocess.run(
            ["timedatectl", "show", "-p", "NTPSynchronized", "--value"],
            capture_output=True,
            text=True,
            timeout=3,
        )
        return out.stdout.strip() or None
    return None


async def check_daemon(
    report: Report, config: AgentConfig, identity: str, timeout: float, drift_interval_s: float
) -> None:
    try:
        first = await handshake(config, identity, timeout)
    except HandshakeError as exc:
        report.add("daemon link", "fail", str(exc), exc.hint)
        report.add("time sync", "skip", "needs the daemon link")
        return
    joined = f"as cid {first.cid}" if first.cid is not None else "(probe: not a fleet member)"
    report.add(
        "daemon link",
        "ok",
        f"{config.gcs_host}:{config.gcs_port} accepted {identity} {joined}, "
        f"protocol v{first.version}, round trip {first.rtt_s * 1000:.1f} ms",
    )
    off = first.offset_s
    verdict: Verdict = "ok" if abs(off) < OFFSET_WARN_S else ("warn" if abs(off) < OFFSET_FAIL_S else "fail")
    report.add(
        "time sync",
        verdict,
        f"clock offset to the daemon {off * 1000:+.0f} ms (+/- {first.rtt_s * 500:.0f} ms)",
        "sync both clocks with NTP (timedatectl set-ntp true; chrony on a field network)",
    )
    ntp = ntp_state()
    if ntp == "no":
        report.add("NTP", "warn", "this clock is not NTP-synchronised", "timedatectl set-ntp true")
    if drift_interval_s > 0:
        await asyncio.sleep(drift_interval_s)
        try:
            second = await handshake(config, identity, timeout)
        except HandshakeError as exc:
            report.add("clock drift", "fail", f"second handshake failed: {exc}", exc.hint)
            return
        elapsed = drift_interval_s + (second.rtt_s + first.rtt_s) / 2
        ppm = (second.offset_s - first.offset_s) / elapsed * 1e6
        noise = (first.rtt_s + second.rtt_s) / 2 / elapsed * 1e6
        report.add(
            "clock drift",
            "ok" if abs(ppm) < max(DRIFT_WARN_PPM, noise) else "warn",
            f"{ppm:+.0f} ppm over {elapsed:.1f} s (resolution {noise:.0f} ppm)",
            "a drifting clock needs NTP; a Raspberry Pi has no RTC, so sync before flight",
        )


async def diagnose(
    config: AgentConfig,
    autopilot: Autopilot | None,
    key_file: Path | None = None,
    identity: str | None = None,
    timeout: float = 10.0,
    drift_interval_s: float = 3.0,
) -> Report:
    report = Report()
    check_key_file(report, key_file, config.key_hex)
    if autopilot is None:
        report.add("autopilot link", "skip", "not checked (--skip-autopilot)")
    else:
        await check_autopilot(report, autopilot, timeout)
    await check_daemon(report, config, identity or config.identity, timeout, drift_interval_s)
    check_release_beacon(report, config)
    return report


def check_release_beacon(report: Report, config: AgentConfig) -> None:
    """With ``release_beacon`` set: can the agent listen there (beside a running agent)?"""
    if config.release_beacon is None:
        return
    try:
        beacon_socket(parse_beacon_address(config.release_beacon)).close()
    except OSError as exc:
        report.add(
            "release beacon",
            "warn",
            f"cannot listen on {config.release_beacon}: {exc.strerror or exc}",
            "use the broadcast address of a network this machine is on (`ip -br addr`), or "
            "127.255.255.255 on one host; until then barriers wait for their TCP release",
        )
    else:
        report.add("release beacon", "ok", f"can listen on {config.release_beacon}")

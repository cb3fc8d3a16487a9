"""Dashboard/stream benchmark: 100 drones at 10 Hz, WebSocket clients, end-to-end status latency.

Three processes on one machine (one clock, so latencies are exact):

* the daemon (this process) with its HTTP/WebSocket API;
* synthetic agents (a child process): real protocol clients that do the authenticated handshake,
  then send a status report every 0.1 s stamped with the send time (``status.time``);
* stream clients (a child process): ``--clients`` WebSocket subscribers, full rate, each
  recording ``receive time - status.time`` (agent -> daemon -> hub -> WebSocket -> client);
* optionally a headless chromium page (Debian's /usr/bin/chromium) doing the same in JS, which
  is the dashboard's path (``--browser``; skipped when chromium is missing).

Writes bench/results/dashboard.json. Run: ``.venv/bin/python bench/bench_dashboard.py``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing
import os
import platform
import queue
import secrets
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcs.core.config import DaemonConfig  # noqa: E402
from gcs.core.daemon import Daemon  # noqa: E402
from protocol import auth  # noqa: E402
from protocol.geo import offset_latlon  # noqa: E402
from protocol.packets import (  # noqa: E402
    Battery,
    Gps,
    Position,
    StatusReport,
)
from protocol.session import ClientHandshake  # noqa: E402
from protocol.stream import open_client  # noqa: E402

HOME = (47.397742, 8.545594, 488.0)


# --- synthetic agents (child process) ---------------------------------------------------------------


async def _agent(identity: str, index: int, port: int, key_hex: str, rate_hz: float, stop_at: float) -> int:
    key = auth.parse_key(key_hex)
    stream, _ = await open_client("127.0.0.1", port, ClientHandshake(identity, key), timeout=30.0)
    reader, writer = stream.reader, stream.writer

    async def drain() -> None:
        while await reader.read(65_536):
            pass

    drainer = asyncio.create_task(drain())
    sent = 0
    period = 1.0 / rate_hz
    await asyncio.sleep((index % 100) / 100 * period)  # spread the fleet over the period
    next_at = time.monotonic()
    lat0, lon0 = offset_latlon(HOME[0], HOME[1], 0.0, 5.0 * index)
    while time.time() < stop_at:
        angle = sent * 0.05
        lat, lon = offset_latlon(lat0, lon0, 20 * math.sin(angle), 20 * math.cos(angle))
        status = StatusReport(
            time=time.time(),
            position=Position(lat=lat, lon=lon, alt_rel=20.0, alt_amsl=HOME[2] + 20.0),
            heading_deg=(math.degrees(angle) + 90) % 360,
            battery=Battery(pct=90.0),
            mode="GUIDED",
            armed=True,
            landed=False,
            gps=Gps(fix=3, satellites=12),
        )
        await stream.send(status)
        sent += 1
        next_at += period
        await asyncio.sleep(max(0.0, next_at - time.monotonic()))
    drainer.cancel()
    writer.close()
    return sent


def agents_process(port: int, key_hex: str, drones: int, rate_hz: float, stop_at: float, out: Any) -> None:
    async def main() -> None:
        results = await asyncio.gather(
            *(_agent(f"drone-{i + 1}", i, port, key_hex, rate_hz, stop_at) for i in range(drones))
        )
        out.put({"sent": sum(results)})

    asyncio.run(main())


# --- stream clients (child process) --------------------------------------------------------------------


def clients_process(http_port: int, clients: int, start_at: float, stop_at: float, out: Any) -> None:
    import websockets

    async def client() -> dict[str, Any]:
        latencies: list[float] = []
        frames = 0
        url = f"ws://127.0.0.1:{http_port}/api/v1/stream?events=false"
        async with websockets.connect(url, max_size=None) as ws:
            while time.time() < stop_at:
                try:
                    frame = await asyncio.wait_for(ws.recv(), timeout=max(0.1, stop_at - time.time()))
                except TimeoutError:
                    break
                now = time.time()
                frames += 1
                if now < start_at:
                    continue
                for message in json.loads(frame):
                    if message.get("type") == "status":
                        latencies.append(now - message["status"]["time"])
        return {"latencies": latencies, "frames": frames}

    async def main() -> None:
        results = await asyncio.gather(*(client() for _ in range(clients)))
        out.put(results)

    asyncio.run(main())


# --- browser client (optional) --------------------------------------------------------------------------

BROWSER_JS = """async ([url, seconds]) => {
  const lat = [];
  await new Promise((resolve) => {
    const ws = new WebSocket(url);
    const t0 = Date.now();
    ws.onmessage = (e) => {
      const now = Date.now() / 1000;
      for (const m of JSON.parse(e.data)) if (m.type === "status") lat.push(now - m.status.time);
      if (Date.now() - t0 > seconds * 1000) { ws.close(); resolve(); }
    };
    setTimeout(resolve, (seconds + 5) * 1000);
  });
  return lat;
}"""


async def browser_latencies(http_port: int, seconds: float) -> list[float] | None:
    chromium = "/usr/bin/chromium"
    if not Path(chromium).exists():
        return None
    try:
        from playwright.async_api import async_playwright
    except ImportError:
        return None
    args = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync"]  # fmt: skip
    async with async_playwright() as p:
        browser = await p.chromium.launch(executable_path=chromium, args=args)
        page = await browser.new_page()
        await page.goto(f"http://127.0.0.1:{http_port}/api/v1/health")
        url = f"ws://127.0.0.1:{http_port}/api/v1/stream?events=false&max_rate_hz=10"
        result = await page.evaluate(BROWSER_JS, [url, seconds])
        await browser.close()
        return [float(x) for x in result]


def summary(latencies: list[float]) -> dict[str, float]:
    if not latencies:
        return {"count": 0}
    ordered = sorted(latencies)

    def pct(q: float) -> float:
        return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))] * 1000, 2)

    return {
        "count": len(ordered),
        "p50_ms": pct(0.50),
        "p90_ms": pct(0.90),
        "p99_ms": pct(0.99),
        "max_ms": round(ordered[-1] * 1000, 2),
        "mean_ms": round(statistics.fmean(ordered) * 1000, 2),
    }


async def run(args: argparse.Namespace) -> dict[str, Any]:
    key = secrets.token_hex(32)
    with tempfile.TemporaryDirectory(prefix="fleetgcs-bench-") as data:
        config = DaemonConfig(
            listen_port=0,
            http_port=0,
            data_dir=Path(data),
            fleet_key_hex=key,
            api_token="bench",
            status_period_s=1.0 / args.rate,
            max_agents=max(1000, args.drones),
            lost_after_periods=100.0,  # the synthetic fleet stops at once at the end: not "lost"
        )
        daemon = Daemon(config)
        await daemon.start()
        ctx = multiprocessing.get_context("spawn")
        out: Any = ctx.Queue()
        now = time.time()
        start_at = now + args.warmup
        stop_at = start_at + args.seconds
        agents = ctx.Process(
            target=agents_process, args=(daemon.listen_port, key, args.drones, args.rate, stop_at, out)
        )
        agents.start()
        while len(daemon.agents.connected()) < args.drones and time.time() < now + 30:
            await asyncio.sleep(0.1)
        joined = len(daemon.agents.connected())
        clients = ctx.Process(
            target=clients_process, args=(daemon.http_port, args.clients, start_at, stop_at, out)
        )
        clients.start()
        cpu0 = os.times()
        browser: list[float] | None = None
        await asyncio.sleep(max(0.0, start_at - time.time()))
        count0 = sum(x.status_count for x in daemon.agents.sessions.values())
        if args.browser:
            browser = await browser_latencies(daemon.http_port, max(1.0, stop_at - time.time() - 1))
        await asyncio.sleep(max(0.0, stop_at - time.time()))
        received = sum(x.status_count for x in daemon.agents.sessions.values()) - count0
        results: list[Any] = []
        deadline = stop_at + 60
        while len(results) < 2 and time.time() < deadline:  # read before joining: a child with
            try:  # queued data does not exit until it is read
                results.append(out.get_nowait())
            except queue.Empty:
                await asyncio.sleep(0.2)
        cpu1 = os.times()
        clients.join(10)
        agents.join(10)
        sent = next(r["sent"] for r in results if isinstance(r, dict))
        client_results = next(r for r in results if isinstance(r, list))
        hub = next(s for s in daemon.services if getattr(s, "name", "") == "live-hub")
        dropped = sum(c.dropped for c in hub.clients)  # type: ignore[attr-defined]
        await daemon.stop()
    all_latencies = [x for c in client_results for x in c["latencies"]]
    elapsed = args.seconds + args.warmup
    return {
        "benchmark": "dashboard",
        "machine": {
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
        },
        "drones": args.drones,
        "joined": joined,
        "status_rate_hz_per_drone": args.rate,
        "status_sent": sent,
        "daemon_status_rate_hz": round(received / args.seconds, 1),
        "ws_clients": args.clients,
        "seconds_measured": args.seconds,
        "messages_per_client_per_s": round(
            statistics.fmean(len(c["latencies"]) for c in client_results) / args.seconds, 1
        ),
        "frames_per_client_per_s": round(statistics.fmean(c["frames"] for c in client_results) / elapsed, 1),
        "dropped_by_slow_clients": dropped,
        "daemon_cpu_s_per_s": round((cpu1.user + cpu1.system - cpu0.user - cpu0.system) / elapsed, 3),
        "latency_ws_client": summary(all_latencies),
        "latency_browser_10hz_per_drone": summary(browser) if browser is not None else "skipped: no chromium",
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--drones", type=int, default=100)
    parser.add_argument("--rate", type=float, default=10.0, help="status reports per drone per second")
    parser.add_argument("--clients", type=int, default=5, help="WebSocket stream clients")
    parser.add_argument("--seconds", type=float, default=15.0, help="measured time")
    parser.add_argument("--warmup", type=float, default=3.0)
    parser.add_argument("--no-browser", dest="browser", action="store_false", help="skip the chromium client")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "dashboard.json")
    args = parser.parse_args()
    result = asyncio.run(run(args))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Event-loop benchmark of the daemon's link layer: what SQLite work costs the loop.

Run: python bench/bench_link.py [--rows 2000000] [--telemetry-rate 5000] [--seconds 10]
Prints a table; writes bench/results/link.json.

Measured:

* **event writes under telemetry load**: ``Store.add_event`` (the synchronous write every event
  makes on the loop) p50/p99/max, alone and while the telemetry writer thread inserts
  ``--telemetry-rate`` rows/s (500 agents at 10 Hz is 5 000).
* **history over a big log**: a daemon (in-process, HTTP API on loopback) over a telemetry log
  of ``--rows`` samples written straight into its SQLite file; four history pages at the caps
  (10 000 x 100, 1 000 x 1 000, 10 000 x 100, 10 000 x 1) requested at once, the time they
  take and the longest event-loop stall meanwhile (a 10 ms sleep that comes back late).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import secrets
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import httpx

from gcs.core.config import DaemonConfig, TelemetryConfig
from gcs.core.daemon import Daemon
from gcs.observe.live import LiveHub
from gcs.observe.telemetry import TelemetryWriter
from gcs.storage.store import Store
from tests.backbone.helpers import telemetry_row
from tests.link.test_history import LoopLag, fill_log

RESULTS = Path(__file__).resolve().parent / "results"
ROW = telemetry_row("bench", 0.0, 0.0)


def _percentiles(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {
        "p50_ms": ordered[len(ordered) // 2] * 1000,
        "p99_ms": ordered[int(len(ordered) * 0.99)] * 1000,
        "max_ms": ordered[-1] * 1000,
        "n": len(ordered),
    }


def event_writes(rate: int, seconds: float) -> dict[str, float]:
    """add_event latency while a writer thread stores ``rate`` telemetry rows/s (0: none)."""
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(Path(tmp) / "db.sqlite")
        writer = TelemetryWriter(store, TelemetryConfig(flush_s=0.5))
        writer.start()
        stop = threading.Event()

        def feed() -> None:
            for _ in range(int(seconds * 10) + 10):
                if stop.is_set():
                    return
                for _ in range(rate // 10):
                    writer.add((ROW[0], time.time(), time.time(), *ROW[3:]))
                time.sleep(0.1)

        feeder = threading.Thread(target=feed)
        feeder.start()
        durations = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            began = time.perf_counter()
            store.add_event("bench", "info", "an event", agent="a", data={"n": 1})
            durations.append(time.perf_counter() - began)
            time.sleep(0.005)
        stop.set()
        feeder.join()
        writer.stop()
        store.close()
    return {**_percentiles(durations), "telemetry_rows_per_s": rate, "rows_written": writer.written}


async def history(rows: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        newest = time.time() - 3600.0
        began = time.monotonic()
        fill_log(Path(tmp) / "fleetgcs.sqlite", "bench", rows, newest)
        fill_s = time.monotonic() - began
        config = DaemonConfig(
            listen_port=0,
            http_host="127.0.0.1",
            http_port=0,
            data_dir=Path(tmp),
            fleet_key_hex=secrets.token_hex(32),
        )
        daemon = Daemon(config)
        await daemon.start()
        hub = next(s for s in daemon.services if isinstance(s, LiveHub))
        hub.history.setdefault("bench", collections.deque())  # an agent the API knows, no ring yet
        try:
            async with httpx.AsyncClient(
                base_url=f"http://127.0.0.1:{daemon.http_port}", timeout=120
            ) as http:
                url = "/api/v1/agents/bench/history"
                pages = ((10_000, 100), (1000, 1000), (10_000, 100), (10_000, 1))
                with LoopLag() as lag:
                    began = time.monotonic()
                    answers = await asyncio.gather(
                        *(
                            http.get(url, params={"since": 1, "until": newest, "limit": n, "every": k})
                            for n, k in pages
                        )
                    )
                    took = time.monotonic() - began
                    refused = await http.get(url, params={"since": 1, "limit": 100_000, "every": 10_000})
        finally:
            await daemon.stop()
    return {
        "rows": rows,
        "fill_s": fill_s,
        "four_pages_s": took,
        "samples": [len(a.json()) for a in answers],
        "worst_loop_stall_ms": lag.worst * 1000,
        "issue_query_status": refused.status_code,
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", type=int, default=2_000_000)
    parser.add_argument("--telemetry-rate", type=int, default=5000)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    out: dict[str, Any] = {}
    for rate in (0, args.telemetry_rate):
        row = event_writes(rate, args.seconds)
        out[f"event_writes_{rate}"] = row
        print(
            f"event write, telemetry {rate:>5} rows/s: p50 {row['p50_ms']:.2f} ms  "
            f"p99 {row['p99_ms']:.2f} ms  max {row['max_ms']:.1f} ms  ({row['n']} events)",
            flush=True,
        )
    result = asyncio.run(history(args.rows))
    out["history"] = result
    print(
        f"history over {result['rows']} rows: 4 capped pages in {result['four_pages_s']:.2f} s "
        f"({result['samples']} samples), worst loop stall {result['worst_loop_stall_ms']:.0f} ms; "
        f"the issue's query answers {result['issue_query_status']}"
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "link.json").write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""`gcs log`: flight logs out of the daemon's database (CSV or GeoJSON), for replay and energy models.

Reads the SQLite file directly, so it works with the daemon running (WAL) or stopped.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gcs.core.config import default_data_dir
from gcs.observe.telemetry import split_flights, to_csv, to_geojson_text
from gcs.storage.store import Store, StoreError


def _store(args: argparse.Namespace) -> Store:
    path = args.database or Path(args.data_dir) / "fleetgcs.sqlite"
    if not Path(path).exists():
        raise SystemExit(f"gcs log: no database at {path} (use --data-dir or --database)")
    try:
        return Store(path, read_only=True)  # beside a running daemon: no migration, no journal recovery
    except StoreError as exc:
        raise SystemExit(f"gcs log: {exc}") from None


def run_agents(args: argparse.Namespace) -> int:
    store = _store(args)
    for agent in store.telemetry_agents():
        samples = store.telemetry(agent)
        flights = split_flights(samples)
        print(f"{agent:20} {len(samples):8} samples {len(flights):4} flights")
    return 0


def run_export(args: argparse.Namespace) -> int:
    store = _store(args)
    samples = store.telemetry(args.agent, args.since, args.until, args.mission)
    if not samples:
        print(f"gcs log: no telemetry for {args.agent!r} with these filters", file=sys.stderr)
        return 1
    flights = split_flights(samples) if args.by_flight or args.format == "geojson" else [samples]
    out = Path(args.out)
    if args.format == "geojson":
        out.write_text(to_geojson_text(args.agent, flights))
        print(f"{out}: {len(flights)} flights")
    elif args.by_flight:
        out.mkdir(parents=True, exist_ok=True)
        for index, flight in enumerate(flights):
            (out / f"{args.agent}-flight{index:03d}.csv").write_text(to_csv(flight))
        print(f"{out}/: {len(flights)} flight CSV files")
    else:
        out.write_text(to_csv(samples))
        print(f"{out}: {len(samples)} samples")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("log", help="export logged telemetry (CSV/GeoJSON flight logs)")
    sub = parser.add_subparsers(dest="log_command", required=True)
    for name, runner, text in (
        ("agents", run_agents, "agents with logged telemetry"),
        ("export", run_export, "one agent's telemetry as CSV or GeoJSON"),
    ):
        p = sub.add_parser(name, help=text)
        p.add_argument(
            "--data-dir",
            type=Path,
            default=default_data_dir(),
            help="the daemon's data directory (its database)",
        )
        p.add_argument("--database", type=Path, help="SQLite file (default DATA_DIR/fleetgcs.sqlite)")
        p.set_defaults(run=runner)
        if name == "export":
            p.add_argument("--agent", required=True, help="the drone whose flight log to export")
            p.add_argument("--mission", help="only samples of this mission")
            p.add_argument("--since", type=float, default=0.0, help="UNIX time")
            p.add_argument("--until", type=float, default=float("inf"), help="UNIX time")
            p.add_argument(
                "--format", choices=["csv", "geojson"], default="csv", help="csv (default) or geojson"
            )
            p.add_argument("--by-flight", action="store_true", help="CSV: one file per flight into OUT/")
            p.add_argument("--out", required=True, help="the file to write")

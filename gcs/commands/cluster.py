"""`gcs cluster up`: a local cluster to try cluster mode: a 3-node NATS JetStream and N daemons.

Everything listens on loopback; the state lives in a temporary directory (removed on exit) or in
``--dir`` (kept). Ctrl-C (or SIGTERM, SIGHUP) stops every process it started
(gcs/cluster/localrun.py).
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path
from types import FrameType

from gcs.commands._api import CommandError

WATCH_PERIOD_S = 0.2


STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""Stop it like Ctrl-C (the children, in sessions of their own, would outlive a closed terminal)."""


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt  # SIGTERM or SIGHUP stops it like Ctrl-C: everything started is stopped


def run(args: argparse.Namespace) -> int:
    from gcs.cluster.localrun import LocalCluster, LocalClusterError  # cluster mode only

    if args.daemons < 1 or args.nats < 1:
        raise CommandError("--daemons and --nats need at least 1")
    base = args.dir or Path(tempfile.mkdtemp(prefix="fleetgcs-cluster-"))
    cluster = LocalCluster(
        base, daemons=args.daemons, nats_nodes=args.nats, agent_port=args.agent_port, http_port=args.http_port
    )
    previous = {sig: signal.signal(sig, _interrupt) for sig in STOP_SIGNALS}
    code = 0
    try:
        print(f"starting {args.nats} nats-server and {args.daemons} daemons in {base} ...", flush=True)
        cluster.start()
        print(cluster.banner(), flush=True)
        if args.ready_file is not None:
            args.ready_file.write_text(json.dumps(cluster.describe()) + "\n")
        told: set[str] = set()
        while any(d.process.poll() is None for d in cluster.serves):  # until Ctrl-C or no daemon left
            for line in cluster.exited():  # a daemon or nats-server killed to try a failure: said once
                if line not in told:
                    told.add(line)
                    print(f"gcs cluster: {line}", file=sys.stderr, flush=True)
            time.sleep(WATCH_PERIOD_S)
        print("gcs cluster: every daemon exited", file=sys.stderr)
        code = 1
    except LocalClusterError as exc:
        print(f"gcs cluster: cannot start: {exc}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print("stopping ...", flush=True)
    finally:
        for sig in (signal.SIGINT, *STOP_SIGNALS):  # a second Ctrl-C must not cut the stop short
            signal.signal(sig, signal.SIG_IGN)
        try:
            cluster.stop()
        finally:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if args.dir is None and code == 0:
            shutil.rmtree(base, ignore_errors=True)
        elif code:
            print(f"gcs cluster: logs kept in {base}", file=sys.stderr)
    if code == 0:
        print("stopped: every daemon and nats-server", flush=True)
    return code


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "cluster",
        help="up: start a local 3-node NATS JetStream cluster and daemons to try cluster mode (Ctrl-C stops)",
    )
    parser.add_argument("action", choices=["up"], help="up: start it and wait for Ctrl-C")
    parser.add_argument(
        "--daemons", type=int, default=2, help="gcs serve --cluster daemons (default %(default)s)"
    )
    parser.add_argument("--nats", type=int, default=3, help="nats-server nodes (default %(default)s)")
    parser.add_argument(
        "--dir", type=Path, help="keep everything here (default: a temporary directory, removed on exit)"
    )
    parser.add_argument(
        "--agent-port",
        type=int,
        default=0,
        help="first daemon's agent port, the next count up (default: free)",
    )
    parser.add_argument(
        "--http-port", type=int, default=0, help="first daemon's API port, the next count up (default: free)"
    )
    parser.add_argument("--ready-file", type=Path, help="write where everything listens here (JSON) once up")
    parser.set_defaults(run=run)

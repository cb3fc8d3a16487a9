"""`gcs run TASKFILE`: submit a mission to a running daemon and follow it to the end."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from gcs.commands._api import api_arguments, api_token, unreachable
from protocol.taskfile import TaskFileError, load_task_text, task_warnings

TERMINAL = {"completed", "aborted"}
__all__ = ["api_arguments", "api_token", "follow", "problem_text", "render_progress"]


def problem_text(response: httpx.Response) -> str:
    try:
        body: dict[str, Any] = response.json()
        return f"{body.get('title', response.reason_phrase)}: {body.get('detail', '')}"
    except ValueError:
        return f"HTTP {response.status_code}: {response.text[:300]}"


def render_progress(progress: dict[str, Any]) -> str:
    cells = []
    for agent in progress["agents"]:
        state = "done" if agent["done"] else ("lost" if not agent["connected"] else f"step {agent['step']}")
        if agent.get("waiting_sync") is not None:
            state = f"sync {agent['waiting_sync']}"
        if agent["excluded"]:
            state = "excluded"
        cells.append(f"{agent['agent']}[{agent['completed_step'] + 1}/{agent['last_step'] + 1} {state}]")
    released = len(progress["released_steps"])
    return f"{progress['state']:9} sync {released}/{len(progress['sync_steps'])}  " + "  ".join(cells)


def follow(client: httpx.Client, mission_id: str, timeout_s: float, quiet: bool = False) -> dict[str, Any]:
    """Poll the mission until it ends (or ``timeout_s``); prints one line per change."""
    deadline = time.monotonic() + timeout_s
    last_line = ""
    progress: dict[str, Any] = {}
    while time.monotonic() < deadline:
        response = client.get(f"/api/v1/missions/{mission_id}")
        response.raise_for_status()
        progress = response.json()
        line = render_progress(progress)
        if line != last_line and not quiet:
            print(line, flush=True)
            last_line = line
        if progress["state"] in TERMINAL:
            return progress
        time.sleep(0.5)
    return progress


def run(args: argparse.Namespace) -> int:
    try:
        task = load_task_text(
            Path(args.taskfile).read_text(), allow_airborne_end=args.allow_airborne_end, gcj02=args.gcj02
        )
    except (OSError, TaskFileError) as exc:
        print(f"gcs run: {exc}", file=sys.stderr)
        return 2
    for warning in task_warnings(task):
        print(f"gcs run: warning: {warning}", file=sys.stderr)
    headers = {"Authorization": f"Bearer {api_token(args)}"}
    with httpx.Client(base_url=args.api, headers=headers, timeout=10.0) as client:
        try:
            # The daemon waits up to fix_wait_s for every agent's first 3-D fix before accepting.
            response = client.post(
                "/api/v1/missions", json=task.model_dump(mode="json"), timeout=task.fix_wait_s + 30.0
            )
        except httpx.HTTPError as exc:
            print(f"gcs run: cannot reach the daemon at {args.api}: {exc}", file=sys.stderr)
            return 3
        if response.status_code != 201:
            print(f"gcs run: {problem_text(response)}", file=sys.stderr)
            return 2
        mission_id = response.json()["mission_id"]
        try:  # from here on Ctrl-C only stops the following, whenever it comes
            print(f"mission {mission_id} started", flush=True)
            progress = follow(client, mission_id, args.timeout)
        except KeyboardInterrupt:
            print(
                f"\ngcs run: stopped following; mission {mission_id} keeps flying on the daemon "
                f"(`gcs mission pause|abort {mission_id}`, or `gcs fleet rtl`)",
                file=sys.stderr,
            )
            return 130
        except httpx.TransportError as exc:
            raise unreachable(args.api, exc) from None
    state = progress.get("state", "unknown")
    print(f"mission {mission_id}: {state} - {progress.get('result')}")
    return 0 if state == "completed" else 1


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("run", help="submit a task file to a running daemon and follow it")
    parser.add_argument("taskfile", help="fleetgcs task file or CoUAS task file (JSON)")
    parser.add_argument("--timeout", type=float, default=3600.0, help="give up following after this many s")
    parser.add_argument(
        "--allow-airborne-end",
        action="store_true",
        help="fly plans that never land (refused otherwise: the drones would stay armed in the air)",
    )
    parser.add_argument(
        "--gcj02",
        action="store_true",
        help="CoUAS go-to/land coordinates are GCJ-02 (Chinese web maps): convert them to WGS-84",
    )
    api_arguments(parser)
    parser.set_defaults(run=run)

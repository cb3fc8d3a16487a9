"""`gcs run TASKFILE`: submit a mission to a running daemon and follow it to the end."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from gcs.commands._api import api_arguments, api_token, unreachable
from gcs.missions.mission_files import is_mission_path, load_mission_files
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


COVERAGE_POLL_S = 2.0  # the daemon rasterises the tracks per request: not every half second


@dataclass
class SeenProgress:
    """A survey's progress by seen area and flown distance (steps say 2/4 while 8 % or 84 % is
    seen), with an ETA.

    The ETA is the daemon's (``GET .../coverage``: each drone's planned metres left at its current
    speed, the slowest one's); from a daemon that gives none it extrapolates the seen rate since
    the first sample that saw anything (take-off and transit see nothing, so they do not slow the
    estimate down).
    """

    history: list[tuple[float, float]] = field(default_factory=list)  # (monotonic s, covered %)
    flown_m: float | None = None
    planned_m: float | None = None
    daemon_eta_s: float | None = None
    daemon_eta: bool = False  # the daemon answers with distances: its ETA (None: nobody flying) rules

    def add(self, t: float, pct: float, body: dict[str, Any] | None = None) -> None:
        self.history.append((t, pct))
        if body is not None and isinstance(body.get("planned_m"), int | float):
            self.flown_m, self.planned_m = float(body.get("flown_m") or 0.0), float(body["planned_m"])
            eta = body.get("eta_s")
            self.daemon_eta, self.daemon_eta_s = True, float(eta) if isinstance(eta, int | float) else None

    @property
    def pct(self) -> float | None:
        return self.history[-1][1] if self.history else None

    def eta_s(self) -> float | None:
        if self.daemon_eta:
            return self.daemon_eta_s
        seeing = [(t, p) for t, p in self.history if p > 0]
        if len(seeing) < 2 or seeing[-1][1] >= 100.0:
            return None
        (t0, p0), (t1, p1) = seeing[0], seeing[-1]
        if p1 <= p0 or t1 <= t0:
            return None
        return (100.0 - p1) * (t1 - t0) / (p1 - p0)

    def text(self) -> str:
        if self.pct is None:
            return ""
        eta = self.eta_s()
        flown = "" if self.planned_m is None else f"  flown {self.flown_m or 0:.0f}/{self.planned_m:.0f} m"
        tail = "" if eta is None else f"  ETA {int(eta) // 60}m{int(eta) % 60:02d}s"
        return f"  seen {self.pct:5.1f} %{flown}{tail}"


def _coverage(client: httpx.Client, mission_id: str) -> dict[str, Any] | None:
    """The mission's coverage answer with a seen share, or None (no survey area, or a daemon
    without the coverage map)."""
    try:
        response = client.get(f"/api/v1/missions/{mission_id}/coverage")
    except httpx.HTTPError:
        return None
    if response.status_code != 200:
        return None
    body: dict[str, Any] = response.json()
    return body if isinstance(body.get("covered_pct"), int | float) else None


def follow(client: httpx.Client, mission_id: str, timeout_s: float, quiet: bool = False) -> dict[str, Any]:
    """Poll the mission until it ends (or ``timeout_s``); prints one line per change of step or seen %."""
    deadline = time.monotonic() + timeout_s
    last_key: tuple[str, int] = ("", -1)
    progress: dict[str, Any] = {}
    seen = SeenProgress()
    next_coverage = time.monotonic()
    while time.monotonic() < deadline:
        response = client.get(f"/api/v1/missions/{mission_id}")
        response.raise_for_status()
        progress = response.json()
        now = time.monotonic()
        if now >= next_coverage or progress["state"] in TERMINAL:
            next_coverage = now + COVERAGE_POLL_S
            body = _coverage(client, mission_id)
            if body is not None:
                seen.add(now, float(body["covered_pct"]), body)
        line = render_progress(progress)
        key = (line, -1 if seen.pct is None else int(seen.pct))
        if key != last_key and not quiet:
            print(line + seen.text(), flush=True)
            last_key = key
        if progress["state"] in TERMINAL:
            if seen.pct is not None:
                progress["seen_pct"] = seen.pct
            if seen.flown_m is not None:
                progress["flown_m"] = seen.flown_m
            return progress
        time.sleep(0.5)
    return progress


def run(args: argparse.Namespace) -> int:
    path = Path(args.taskfile)
    try:
        if is_mission_path(path):
            task = load_mission_files(path, agent=args.agent, allow_airborne_end=args.allow_airborne_end)
        elif args.agent is not None:
            raise TaskFileError("--agent is for a QGC .plan or Mission Planner .waypoints file")
        else:
            task = load_task_text(
                path.read_text(), allow_airborne_end=args.allow_airborne_end, gcj02=args.gcj02
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
    seen_pct = progress.get("seen_pct")
    flown = progress.get("flown_m")
    seen_text = "" if seen_pct is None else f" ({seen_pct:.1f} % of the area seen"
    seen_text += "" if seen_pct is None else (")" if flown is None else f", {flown:.0f} m flown)")
    print(f"mission {mission_id}: {state} - {progress.get('result')}{seen_text}")
    return 0 if state == "completed" else 1


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("run", help="submit a task file to a running daemon and follow it")
    parser.add_argument(
        "taskfile",
        help="fleetgcs or CoUAS task file (JSON), or one drone's QGC .plan / Mission Planner .waypoints "
        "(flown by the drone its file name names), or a folder of those (one file per drone)",
    )
    parser.add_argument(
        "--agent", help="the drone to fly a single .plan/.waypoints file (default: its file name)"
    )
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

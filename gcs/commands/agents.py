"""`gcs agents`: the fleet as the daemon sees it."""

from __future__ import annotations

import argparse

import httpx

from gcs.commands.run import api_arguments


def run(args: argparse.Namespace) -> int:
    response = httpx.get(f"{args.api}/api/v1/agents", timeout=10.0)
    response.raise_for_status()
    print(f"{'cid':>4} {'identity':16} {'link':5} {'mode':9} {'armed':5} {'batt%':>5} {'alt':>6} {'step':>4}")
    for agent in response.json():
        status = agent.get("status") or {}
        link = "up" if agent["connected"] else ("lost" if agent["lost"] else "down")
        battery = (status.get("battery") or {}).get("pct")
        print(
            f"{agent['cid']:>4} {agent['identity']:16} {link:5} {status.get('mode', '-'):9} "
            f"{status.get('armed', False)!s:5} {battery if battery is not None else '-':>5} "
            f"{(status.get('position') or {}).get('alt_rel', 0.0):6.1f} {status.get('step', -1):>4}"
        )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("agents", help="list agents and their latest status")
    api_arguments(parser)
    parser.set_defaults(run=run)

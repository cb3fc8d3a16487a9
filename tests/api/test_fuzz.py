"""Schema-driven fuzz of the published OpenAPI spec (schemathesis): no request may cause a 500.

The daemon (with two memory agents, so fleet commands and missions have someone to talk to)
runs on its own event loop in a thread, and every generated request goes over real HTTP with
the token, so the handlers behind the authentication are fuzzed too. Examples are bounded.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from hypothesis import HealthCheck, given, settings

schemathesis = pytest.importorskip("schemathesis")

from tests.api.fleet import running_fleet  # noqa: E402

TOKEN = "test-token"
EXAMPLES = 25


@pytest.fixture(scope="module")
def live_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    ready = threading.Event()
    stop: list[asyncio.Event] = []
    url: list[str] = []
    failure: list[BaseException] = []
    loops: list[asyncio.AbstractEventLoop] = []

    async def main(path: Path) -> None:
        async with running_fleet(path, drones=2, speedup=20.0) as fleet:
            url.append(fleet.base_url)
            stop.append(asyncio.Event())
            loops.append(asyncio.get_running_loop())
            ready.set()
            await stop[0].wait()

    def run() -> None:
        loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(main(tmp_path_factory.mktemp("fuzz")))
        except BaseException as exc:  # surfaced to the test thread below
            failure.append(exc)
            ready.set()
        finally:
            loop.close()

    thread = threading.Thread(target=run, name="fuzz-daemon", daemon=True)
    thread.start()
    assert ready.wait(30), "daemon did not start"
    if failure:
        raise failure[0]
    yield url[0]
    loops[0].call_soon_threadsafe(stop[0].set)
    thread.join(30)


def test_no_request_causes_a_server_error(live_api: str) -> None:
    """Every operation of the published spec, a bounded number of generated requests each."""
    spec = httpx.get(f"{live_api}/openapi.json", timeout=10).json()
    schema = schemathesis.openapi.from_dict(spec)
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 20
    failures: list[str] = []
    calls: dict[str, int] = {}
    for operation in operations:

        @settings(
            max_examples=EXAMPLES,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        @given(case=operation.as_strategy())
        def check(case: Any) -> None:
            calls[case.operation.label] = calls.get(case.operation.label, 0) + 1
            response = case.call(base_url=live_api, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=60)
            if response.status_code >= 500:
                failures.append(
                    f"{case.method} {case.formatted_path} -> {response.status_code}: {response.text[:300]}"
                )
            elif response.status_code >= 400 and "problem+json" not in str(
                response.headers.get("content-type")
            ):
                failures.append(
                    f"{case.method} {case.formatted_path}: {response.status_code} not problem+json"
                )

        check()
    assert failures == [], "\n".join(failures[:10])
    assert len(calls) == len(operations) and sum(calls.values()) >= 5 * len(operations), calls

"""Browser fixtures: Debian's chromium driven by Playwright (never a downloaded browser build).

`scripts/test` installs chromium through `scripts/bootstrap --with-browser`; these tests skip
(with the reason) only when no chromium can be found or started.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def chromium_path() -> str | None:
    for candidate in (os.environ.get("FLEETGCS_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium")):
        if candidate and Path(candidate).exists():
            return candidate
    return None


@pytest.fixture
async def browser() -> AsyncIterator[Any]:
    playwright_api = pytest.importorskip(
        "playwright.async_api", reason="the playwright package is not installed"
    )
    executable = chromium_path()
    if executable is None:
        pytest.skip(
            "no chromium found (scripts/bootstrap --with-browser installs it: apt-get install chromium)"
        )
    async with playwright_api.async_playwright() as p:
        try:
            instance = await p.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS, timeout=30_000)
        except Exception as exc:  # pragma: no cover - depends on the machine
            pytest.skip(f"chromium at {executable} does not start: {exc}")
        try:
            yield instance
        finally:
            await instance.close()


@pytest.fixture
def artifacts() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS

"""Where the checkout and the test data are, for tests that read files or run tools from the repo root."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MISSIONS = ROOT / "tests" / "data" / "missions"
"""QGroundControl .plan / Mission Planner .waypoints files an operator uploads (CLI and dashboard tests)."""

"""Drone labels on the dashboard map never overlap, however close the drones (real Chromium).

Five drones 5 m apart, zoomed out until their markers are a few pixels apart (a survey's
zoom): every label box drawn on the map is clear of every other label and of the other
markers, and a label that had to move is joined to its marker by a leader line.
"""

from __future__ import annotations

import math
from itertools import combinations, pairwise
from pathlib import Path
from typing import Any

from tests.api.fleet import running_fleet
from tests.support.polling import wait_until
from tests.web.dashboard import marker_positions, open_dashboard

DRONES = 5


def _overlap(a: dict[str, float], b: dict[str, float]) -> bool:
    return (
        a["x"] < b["x"] + b["w"]
        and b["x"] < a["x"] + a["w"]
        and a["y"] < b["y"] + b["h"]
        and b["y"] < a["y"] + a["h"]
    )


async def test_labels_of_drones_5_m_apart_do_not_overlap(
    tmp_path: Path, browser: Any, artifacts: Path
) -> None:
    async with running_fleet(tmp_path, drones=DRONES, speedup=5.0, spacing_m=5.0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await wait_until(lambda: _labels(page, DRONES), 10, "five drone labels on the map")
        for _ in range(10):  # zoom out until neighbours are closer than a label is wide
            markers = await marker_positions(page)
            xy = sorted(markers.values())
            nearest = min(math.dist(a, b) for a, b in pairwise(xy))
            if nearest < 12.0:
                break
            await page.click("#btn-zoom-out")
        assert nearest < 12.0, nearest
        await page.wait_for_timeout(300)  # a frame or two after the last zoom
        boxes = await page.evaluate("window.fleetgcs.labelBoxes")
        assert sorted(b["identity"] for b in boxes) == [f"drone-{i + 1}" for i in range(DRONES)]
        widest = max(b["w"] for b in boxes)
        assert widest > 2 * nearest, "the labels are wider than the drones are apart: the case under test"
        for a, b in combinations(boxes, 2):
            assert not _overlap(a, b), f"labels overlap: {a} and {b}"
        markers = await marker_positions(page)
        for box in boxes:
            for name, (x, y) in markers.items():
                if name != box["identity"]:
                    mark = {"x": x - 9, "y": y - 9, "w": 18, "h": 18}
                    assert not _overlap(box, mark), f"{box['identity']}'s label covers {name}'s marker"
        await page.screenshot(path=str(artifacts / "dashboard-labels-5m.png"))
        assert page.errors == []


async def _labels(page: Any, count: int) -> bool:
    return bool(await page.evaluate(f"(window.fleetgcs.labelBoxes || []).length === {count}"))

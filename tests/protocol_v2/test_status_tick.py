"""The status tick as columns: every service reading a tick sees what a report per row would say,
and the state-change hook gets exactly the reports whose flags, steps, mode or mission changed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.link.agents_table import StatusTable, StatusTick
from gcs.link.status_limits import UNBOUNDED
from gcs.observe.telemetry import TickRows, status_row
from protocol.packets import StatusReport
from tests.backbone.helpers import new_key, running_daemon
from tests.support.polling import wait_for
from tests.support.status_reports import join, report_at, reports
from tests.support.status_table import stored_like_ingest


def _same(a: tuple[object, ...], b: tuple[object, ...]) -> bool:
    return all(x == y or (x != x and y != y) for x, y in zip(a, b, strict=True))  # NaN == NaN here


@settings(max_examples=200, deadline=None)
@given(st.lists(reports, min_size=1, max_size=6))
def test_a_tick_gives_the_reports_and_telemetry_rows_of_its_rows(batch: list[StatusReport]) -> None:
    table = StatusTable(capacity=2, limits=UNBOUNDED)  # random values
    owners = [type("Owner", (), {"identity": f"a-{i}"})() for i in range(len(batch))]
    rows = [table.attach(owner) for owner in owners]
    for row, report in zip(rows, batch, strict=True):
        stored_like_ingest(table, row, report)
    dirty = table.take_dirty()
    cols = table.columns(dirty)
    assert table.check(cols).all() or any(table.objects[r] is not None for r in dirty.tolist())
    tick = StatusTick(
        [owners[rows.index(r)] for r in dirty.tolist()],
        cols,
        table.arrivals(dirty),
        [table.objects[r] for r in dirty.tolist()],
    )
    expected = [batch[rows.index(r)] for r in dirty.tolist()]
    for i, report in enumerate(expected):
        assert tick.report(i) == report
        assert tick.mode_mission(i) == (report.mode, report.mission_id)
    got = list(TickRows(tick, 5.0).rows())
    block = TickRows(tick, 5.0)  # what the recorder queues; the writer thread makes its tuples later
    for row in rows:  # the table moves on before the writer gets to the block
        stored_like_ingest(table, row, report_at(1.0, armed=True))
    assert len(block) == len(got) and all(_same(g, w) for g, w in zip(block.rows(), got, strict=True))
    want = [status_row(o.identity, r, 5.0) for o, r in zip(tick.owners, expected, strict=True) if r.position]
    assert len(got) == len(want) and all(_same(g, w) for g, w in zip(got, want, strict=True))
    again = StatusTick.of_reports(list(zip(tick.owners, expected, strict=True)), 5.0)
    assert [again.report(i) for i in range(len(again))] == expected
    assert _same(tuple(TickRows(again, 5.0).rows()), tuple(got))


def test_changed_rows_are_found_by_their_state_bytes() -> None:
    table = StatusTable()
    row = table.attach(object())
    states = [
        (report_at(47.0), True),  # the first report of a row is a change
        (report_at(47.1), False),  # only the position moved
        (report_at(47.2, armed=True), True),
        (report_at(47.3, armed=True), False),
        (report_at(47.3, armed=True, mode="AUTO"), True),
        (report_at(47.3, armed=True, mode="AUTO", mission_id="m", step=2), True),
        (report_at(47.4, armed=True, mode="AUTO", mission_id="m", step=2, completed_step=1), True),
        (report_at(47.5, armed=True, mode="AUTO", mission_id="m", step=2, completed_step=1), False),
        (
            report_at(
                47.5, armed=True, mode="AUTO", mission_id="m", step=2, completed_step=1, waiting_sync=2
            ),
            True,
        ),
    ]
    for report, changed in states:
        stored_like_ingest(table, row, report)
        dirty = table.take_dirty()
        assert table.changed(dirty).tolist() == [changed], report
    assert not table.changed(np.array([row], dtype=np.intp)).any()  # nothing new since
    table.unsee(row)  # handed over outside a tick: the next report counts as a change
    assert table.changed(np.array([row], dtype=np.intp)).all()


def _count(sessions: dict[str, Any]) -> int:
    session = sessions.get("c-1")
    return -1 if session is None else int(session.status_count)


async def test_the_changes_hook_sees_state_changes_and_the_tick_hook_every_report(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        changes: list[StatusReport] = []
        ticked: list[float] = []

        async def on_change(_: object, status: StatusReport) -> None:
            changes.append(status)

        async def on_tick(tick: StatusTick) -> None:
            ticked.extend(tick.cols["lat"].tolist())

        daemon.agents.on_status_changes.append(on_change)
        daemon.agents.on_status_tick.append(on_tick)
        stream = await join(daemon.listen_port, key, "c-1", v1=False)
        try:
            lats = [47.0 + k / 1000 for k in range(6)]
            for k, lat in enumerate(lats):
                fields: dict[str, Any] = {"mode": "AUTO"} if k == 3 else {}
                await stream.send(report_at(lat, armed=True, landed=False, **fields))
                await wait_for(lambda n=k + 1: _count(daemon.agents.sessions) == n, 10, "the report")
                assert await daemon.agents.drain_hooks()
            assert ticked == lats  # every report as columns (one per tick here)
            assert [(c.position.lat, c.mode) for c in changes if c.position] == [  # type: ignore[union-attr]
                (lats[0], "GUIDED"),
                (lats[3], "AUTO"),
                (lats[4], "GUIDED"),
            ]
            assert daemon.agents.sessions["c-1"].status.position.lat == lats[-1]  # type: ignore[union-attr]
            changes.clear()
            for k, lat in enumerate(lats[:2]):  # landed and disarmed: every report (authority drops holds)
                await stream.send(report_at(lat, armed=False, landed=True))
                await wait_for(lambda n=k + 7: _count(daemon.agents.sessions) == n, 10, "the report")
                assert await daemon.agents.drain_hooks()
            assert [c.position.lat for c in changes if c.position] == lats[:2]
        finally:
            await stream.close()

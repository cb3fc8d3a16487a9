"""The daemon's fleet status table: the same reports as the JSON and binary decoders, v1 and compact
agents side by side, and safety news that does not wait for the status tick."""

from __future__ import annotations

import math
from pathlib import Path

import httpx
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.link.agents_table import StatusTable
from gcs.link.status_limits import UNBOUNDED
from protocol import status_binary
from protocol.packets import PacketType, StatusReport
from protocol.wire import decode_body
from tests.backbone.helpers import new_key, running_daemon
from tests.support.polling import wait_for
from tests.support.status_reports import FIELDS, RAW_BODY, join, report_at, reports
from tests.support.status_table import stored_like_ingest


@settings(max_examples=300, deadline=None)
@given(st.lists(reports, min_size=1, max_size=5))
def test_table_rows_give_the_report_that_json_and_binary_bodies_give(batch: list[StatusReport]) -> None:
    table = StatusTable(capacity=2, limits=UNBOUNDED)  # grows while the rows are filled; any values
    rows = [table.attach(object()) for _ in batch]
    for row, report in zip(rows, batch, strict=True):
        stored_like_ingest(table, row, report)
    dirty = table.take_dirty()
    assert dirty.tolist() == sorted(rows)
    decoded = table.reports(dirty)
    for row, report in zip(rows, batch, strict=True):
        from_json = decode_body(PacketType.STATUS, report.model_dump_json(exclude_none=True).encode())
        got = decoded[dirty.tolist().index(row)]
        assert got == from_json == report
        assert got.model_dump() == report.model_dump()  # type: ignore[union-attr]
    columns = table.columns(dirty)
    assert columns["time"].tolist() == [batch[rows.index(r)].time for r in dirty.tolist()]
    assert not len(table.take_dirty())  # marks cleared


@settings(max_examples=400, deadline=None)
@given(
    **RAW_BODY,
    layout=st.sampled_from([1, 1, 1, 2]),
    mode=st.binary(max_size=40),
)
def test_the_column_checks_accept_exactly_what_the_decoder_accepts(
    floats: list[float], fix: int, ints: tuple[int, int, int], position: bool, layout: int, mode: bytes
) -> None:
    assert len(FIELDS) == 13
    flags = status_binary.AUTOPILOT_LINK | (status_binary.HAS_POSITION if position else 0)
    fixed = status_binary.FIXED.pack(layout, flags, fix, 0, *floats, ints[0], ints[1], 0, ints[2])
    body = fixed + bytes((len(mode),)) + mode + b"\x00"
    table = StatusTable(limits=UNBOUNDED)  # the schema's ranges only (plausibility: test_status_validation)
    row = table.attach(object())
    try:  # a body whose layout is not sound never gets into a row
        table.put(row, body, 1.0)
        (got,) = table.reports(table.take_dirty())
    except status_binary.StatusBodyError as exc:
        got = exc
    try:
        expected: StatusReport | None = status_binary.decode(body)
    except status_binary.StatusBodyError:
        expected = None
    if expected is None:
        assert isinstance(got, status_binary.StatusBodyError)
    else:
        assert got == expected


async def test_a_v1_and_a_compact_agent_share_the_table_and_the_api(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, http_host="127.0.0.1", http_port=0, api_token="t") as daemon:
        old = await join(daemon.listen_port, key, "old-1", v1=True)
        new = await join(daemon.listen_port, key, "new-1", v1=False)
        try:
            await old.send(report_at(47.1, armed=True))  # JSON body (v1: no compact)
            await new.send(report_at(47.2, mission_id="m-1", step=4))  # compact body
            manager = daemon.agents
            await wait_for(lambda: manager.sessions["new-1"].status_count == 1, 10, "the compact report")
            await wait_for(lambda: manager.sessions["old-1"].status_count == 1, 10, "the JSON report")
            assert await manager.drain_hooks()
            rows = {name: manager.sessions[name].row for name in ("old-1", "new-1")}
            columns = manager.table.columns(np.array([rows["old-1"], rows["new-1"]]))
            assert columns["lat"].tolist() == [47.1, 47.2]
            assert columns["step"].tolist() == [-1, 4]
            assert bool(columns["flags"][0] & status_binary.ARMED) and not columns["flags"][1] & 1
            async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{daemon.http_port}") as http:
                listed = {a["identity"]: a for a in (await http.get("/api/v1/agents")).json()}
            assert listed["old-1"]["status"]["position"]["lat"] == 47.1
            assert listed["old-1"]["status"]["armed"] is True
            assert listed["new-1"]["status"]["position"]["lat"] == 47.2
            assert listed["new-1"]["status"]["mission_id"] == "m-1"
            assert listed["new-1"]["status_count"] == listed["old-1"]["status_count"] == 1
        finally:
            await old.close()
            await new.close()


async def test_a_failsafe_in_a_compact_status_reaches_the_authority_without_waiting_for_a_tick(
    tmp_path: Path,
) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        seen: list[StatusReport] = []

        async def hook(_: object, status: StatusReport) -> None:
            seen.append(status)

        async def also(_: object, status: StatusReport) -> None:
            pass

        daemon.agents.on_status_changes.append(hook)  # every change, and every report handed over at once
        daemon.agents.on_status.append(also)  # (reports built for it must not all count as changes)
        stream = await join(daemon.listen_port, key, "fs-1", v1=False)
        try:
            await stream.send(report_at(47.3))
            await wait_for(lambda: len(seen) == 1, 10, "the first report (the first tick runs at once)")
            daemon.agents.status_tick_s = 3600.0  # from here on a plain report waits an hour for its tick
            await stream.send(report_at(47.31))
            await stream.send(report_at(47.32, failsafe="battery"))
            await wait_for(lambda: len(seen) == 3, 10, "the failsafe report, without a tick")
            assert [s.position.lat for s in seen if s.position] == [47.3, 47.31, 47.32]  # in order
            assert seen[-1].failsafe == "battery"
            await wait_for(
                lambda: daemon.authority.failsafe("fs-1") == "battery",
                10,
                "the authority to see the failsafe",
            )
            assert not daemon.authority.may_command("fs-1", "mission")  # the vehicle's own failsafe rules
            assert math.isclose(daemon.agents.sessions["fs-1"].status.position.lat, 47.32)  # type: ignore[union-attr]
            session = daemon.agents.sessions["fs-1"]
            await stream.send(report_at(47.33))  # the failsafe is over; nothing else changed since 47.3
            await wait_for(lambda: session.status_count == 4, 10, "the report after the failsafe")
            daemon.agents.tick()  # (the tick still scheduled is an hour away)
            await wait_for(
                lambda: daemon.authority.failsafe("fs-1") is None, 5, "the authority to see it cleared"
            )
        finally:
            await stream.close()

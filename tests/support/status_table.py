"""The daemon's ingest rule for a status-table row, for table tests that fill rows without a socket.

Apart from tests/support/status_reports.py because it imports `gcs`: the protocol tests also run in the
agent-only venv (tests/packaging), where `gcs` is not installed."""

from __future__ import annotations

from gcs.link.agents_table import MAX_BODY, StatusTable
from protocol import status_binary
from protocol.packets import StatusReport
from protocol.wire import STATUS_COMPACT, decode_body


def stored_like_ingest(table: StatusTable, row: int, report: StatusReport) -> None:
    """What the daemon's ingest does: the compact body as it is if it can, else the decoded report."""
    body = status_binary.encode(report)
    if len(body) <= MAX_BODY and not body[1] & (status_binary.HAS_TAIL | status_binary.BUFFERED):
        table.put(row, body, 1.0)
    else:
        table.put_report(row, decode_body(STATUS_COMPACT, body), 1.0)  # type: ignore[arg-type]

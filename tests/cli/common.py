"""Run the command-line tools as separate processes, as an operator would."""

from __future__ import annotations

import asyncio
import signal
from pathlib import Path

from tests.support.processes import BIN


async def run_tool(*argv: str | Path, timeout: float = 60.0) -> tuple[int, str, str]:
    """Run ``argv`` while this event loop keeps serving an in-process daemon."""
    proc = await asyncio.create_subprocess_exec(
        *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    try:
        out, err = await asyncio.wait_for(proc.communicate(), timeout)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


async def gcs(*args: str | Path) -> tuple[int, str, str]:
    return await run_tool(BIN / "gcs", *args)


async def interrupt_after(
    argv: list[str | Path], ready_text: str, timeout: float = 30.0
) -> tuple[int, str, str]:
    """Start ``argv``, wait until its stdout shows ``ready_text``, then Ctrl-C it (SIGINT)."""
    proc = await asyncio.create_subprocess_exec(
        *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stderr is not None
    seen = b""
    try:
        async with asyncio.timeout(timeout):
            while ready_text.encode() not in seen:
                line = await proc.stdout.readline()
                if not line:
                    break
                seen += line
        proc.send_signal(signal.SIGINT)
        out, err = await asyncio.wait_for(proc.communicate(), timeout)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode is not None
    return proc.returncode, (seen + out).decode(), err.decode()


def one_line(err: str) -> str:
    """The error output, asserted to be a single line with no traceback."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]

"""gcs/observe/memory.py: freed memory of a thread's allocations goes back to the system on a trim."""

from __future__ import annotations

import os
import threading

import pytest

from gcs.observe.memory import release_free_memory


def _rss_bytes() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="needs Linux /proc")
def test_a_trim_returns_what_a_thread_freed() -> None:
    kept: list[list[int]] = []

    def churn() -> None:  # blocks of C-allocated buffers (a list's storage above 512 B), then dropped
        for _ in range(20):
            block = [[0] * 200 for _ in range(2_000)]  # ~3.5 MB
            kept.append(block[-1])  # a survivor per block: the arena cannot shrink from its top alone
            del block

    worker = threading.Thread(target=churn)
    worker.start()
    worker.join(60)
    before = _rss_bytes()
    assert release_free_memory(), "glibc's malloc_trim not found on this Linux"
    after = _rss_bytes()
    assert before - after > 1 << 20, f"RSS {before} -> {after}: less than 1 MiB given back"
    assert len(kept) == 20

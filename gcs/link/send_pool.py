"""One frame to many agents at once (a barrier release): the sends of a burst on two threads.

Why: a release to N agents is N ``send`` system calls, ~6 us each on this VM (over loopback each
also runs the receiving socket's side of the stack), and the daemon's Python between them is
under a microsecond; at 1,000 agents the send loop is the release (docs/performance.md, "Issue
29"). ``socket.send`` releases the GIL for the system call, so a helper thread beside the event
loop's thread takes chunks of the same burst and the two run their system calls on both cores.

Safety of the hand-off: only plain TCP sockets whose transport holds nothing are sent to this way
(the caller checks, ``Outbox.take_direct``), the event loop's thread is inside the burst until
every chunk is done (nothing else touches those sockets meanwhile), and every result (bytes taken,
or the error) goes back to the loop's thread, which writes a remainder through the transport or
cuts the peer off as a single send would. Small bursts run on the caller's thread alone: waking
the helper costs more than it saves below :data:`POOL_MIN` sockets.

With :meth:`SendPool.take_and_send`, a job is taken by the thread that sends it: the frame
stamped with its peer's sequence number and the socket found (``Outbox.take_direct``) right before
its ``send``, so that Python runs while the other thread is in a system call instead of before
the first send (issue 29: at 1,000 agents that preparation was 2.5 ms of a 10 ms burst, all on
the loop's thread ahead of every send). Each job is still one peer's, handled by one thread; the
loop's thread is inside the burst throughout, so nothing else touches the peers' state meanwhile.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
from collections.abc import Callable
from typing import Any

log = logging.getLogger("gcs.link.send_pool")

POOL_MIN = 256
"""Sockets in a burst from which the helper thread takes part (measured: at 100 a wake-up of the
helper cost more than the sends it took; at 1,000 the burst's p50 fell by a quarter)."""
CHUNK = 32
"""Sends a thread claims at a time: the lock is taken once per chunk, not per socket."""
WAIT_LOG_S = 1.0
"""A helper's chunk still running this long after the caller's part is logged (non-blocking
sends never block; only a starved machine gets here)."""

SendJob = tuple[socket.socket, bytearray]
SendResult = int | OSError | None
"""Bytes the kernel took (0: its buffer was full), or the error the send raised; None: ``take``
found no job (the caller sends that one its own way)."""
Take = Callable[..., SendJob | None]
"""Called with a job's items (``take(*job)``): the socket and bytes to send, or None."""


class _Burst:
    """One burst's shared state: the next chunk to claim and how many chunks are being sent."""

    __slots__ = ("active", "closed", "idle", "jobs", "lock", "next", "results", "take", "taken")

    def __init__(self, jobs: list[Any], take: Take | None) -> None:
        self.jobs = jobs
        self.take = take
        self.results: list[SendResult] = [0] * len(jobs)
        self.taken: list[SendJob | None] = jobs if take is None else [None] * len(jobs)
        self.next = 0
        self.active = 0
        self.closed = False
        self.lock = threading.Lock()
        self.idle = threading.Event()

    def run(self) -> None:
        """Claim chunks and send them until none is left (either thread)."""
        jobs, results, taken, take, lock = self.jobs, self.results, self.taken, self.take, self.lock
        count = len(jobs)
        for _ in range(count // CHUNK + 1):
            with lock:
                start = self.next
                if start >= count:
                    return
                self.next = start + CHUNK
                self.active += 1
            try:
                for index in range(start, min(start + CHUNK, count)):
                    if take is None:
                        sock, data = jobs[index]
                    else:
                        job = taken[index] = take(*jobs[index])
                        if job is None:
                            results[index] = None
                            continue
                        sock, data = job
                    try:
                        results[index] = sock.send(data)
                    except (BlockingIOError, InterruptedError):
                        results[index] = 0  # the kernel's buffer is full: the transport takes it all
                    except OSError as exc:
                        results[index] = exc
            finally:
                with lock:
                    self.active -= 1
                    if self.closed and not self.active:
                        self.idle.set()


class SendPool:
    """A helper thread that sends chunks of large bursts beside the caller (see the module doc)."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[_Burst | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def send_all(self, jobs: list[SendJob]) -> list[SendResult]:
        """Send each job's bytes to its socket once; each result in the jobs' order."""
        return self._run(_Burst(jobs, None))

    def take_and_send(self, jobs: list[Any], take: Take) -> tuple[list[SendJob | None], list[SendResult]]:
        """``take(*job)`` then send what it gave, for each job, by the thread that sends it (see the
        module doc); what each ``take`` gave (None: nothing sent) and each result, in the jobs' order."""
        burst = _Burst(jobs, take)
        return burst.taken, self._run(burst)

    def _run(self, burst: _Burst) -> list[SendResult]:
        jobs = burst.jobs
        if len(jobs) >= POOL_MIN:
            if self._thread is None:
                self._thread = threading.Thread(target=self._helper, name="gcs-send-pool", daemon=True)
                self._thread.start()
            self._queue.put(burst)
        burst.run()
        with burst.lock:
            burst.closed = True  # a helper that wakes from now on finds nothing left to claim
            busy = burst.active > 0
        if busy and not burst.idle.wait(WAIT_LOG_S):
            log.warning("a release burst waited %.1f s for its sending thread", WAIT_LOG_S)
            burst.idle.wait()  # its chunk is non-blocking sends: it ends; the sockets are not ours before
        return burst.results

    def _helper(self) -> None:
        for _ in iter(int, 1):  # until close() (a None); each burst is bounded by its jobs
            burst = self._queue.get()
            if burst is None:
                return
            try:
                burst.run()
            except Exception:  # a bug in a take: the loop's thread sends what is left of the burst
                log.exception("the send pool's thread failed in a burst")

    def close(self) -> None:
        """Stop the helper thread (the daemon stops); a later large burst starts it again."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._queue.put(None)
            thread.join(timeout=2.0)


__all__ = ["POOL_MIN", "SendJob", "SendPool", "SendResult", "Take"]

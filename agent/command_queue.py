"""The agent's FIFO command queue: one action at a time, sync waits, replace/append semantics.

After an action with ``sync`` the queue reports "finished step k" through ``on_finished`` and
blocks until :meth:`release` is called for k (the daemon's type-5 release). A ``replace``
cancels whatever runs or waits and starts the new list; an exception reaction uses
:meth:`interrupt` to empty the queue so the vehicle is not sent on by stale commands.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from agent.executor import ActionExecutor, ActionFailed
from agent.limits import Refusal
from agent.tasks import cancel_and_wait
from protocol.actions import Action

log = logging.getLogger("agent.queue")

FinishedHook = Callable[[str, int], Awaitable[None]]


@dataclass(frozen=True)
class _BarrierWait:
    """Queue entry of a barrier the agent finished before it lost its queue (rejoin)."""

    step: int
    sync: bool = True


@dataclass(frozen=True)
class _RefusedAt:
    """Queue entry where the agent's limits cut a batch: reaching it refuses the rest (agent/limits.py)."""

    refusal: Refusal

    @property
    def step(self) -> int:
        return self.refusal.step


FailedHook = Callable[[Action, str], Awaitable[None]]
RefusedHook = Callable[[Refusal], Awaitable[None]]
Vet = Callable[[Action], Refusal | None]


class CommandQueue:
    """``vet`` checks each action against the agent's limits from the actual position just before
    it starts; a refusal there, or a :class:`_RefusedAt` entry reached, empties the queue and calls
    ``on_refused`` (as a failed action calls ``on_failed``)."""

    def __init__(
        self,
        executor: ActionExecutor,
        on_finished: FinishedHook,
        on_failed: FailedHook,
        on_refused: RefusedHook | None = None,
        vet: Vet | None = None,
    ) -> None:
        self._executor = executor
        self._on_finished = on_finished
        self._on_failed = on_failed
        self._on_refused = on_refused
        self._vet = vet
        self._pending: deque[Action | _BarrierWait | _RefusedAt] = deque()
        self._wakeup = asyncio.Event()
        self._releases: set[int] = set()
        self._release_event = asyncio.Event()
        self._current: asyncio.Task[None] | None = None
        self._runner: asyncio.Task[None] | None = None
        self.mission_id: str | None = None
        self.current_step = -1
        self.completed_step = -1
        self.waiting_sync: int | None = None
        self.paused = False
        self.pause_reason: str | None = None
        self._resumed = asyncio.Event()
        self._resumed.set()

    @property
    def depth(self) -> int:
        """Actions not yet started (the running one excluded)."""
        return len(self._pending)

    def planned(self) -> list[Action]:
        """The actions still to fly, in order: what is left of the running one, then the queue.

        Where they lead is where a new appended batch starts from (agent/limits.py ``project``).
        """
        ahead: list[Action] = []
        current, left = self._current, self._executor.continuation
        if current is not None and not current.done() and self.waiting_sync is None and left is not None:
            ahead.append(left)
        ahead.extend(a for a in self._pending if not isinstance(a, (_BarrierWait, _RefusedAt)))
        return ahead

    @property
    def busy(self) -> bool:
        return self.current_step >= 0

    def start(self) -> None:
        self._runner = asyncio.create_task(self._run(), name="command-queue")

    async def stop(self) -> None:
        await cancel_and_wait([t for t in (self._current, self._runner) if t is not None])

    async def submit(
        self,
        mission_id: str,
        actions: list[Action],
        replace: bool,
        await_release: int | None = None,
        refusal: Refusal | None = None,
    ) -> None:
        """Add ``actions`` (type 4). ``replace`` empties the queue and cancels the running action.

        ``await_release`` (a rejoin at an unreleased barrier): wait for the release of that step
        before running ``actions``, exactly as if the barrier action had just finished here.
        ``refusal``: the batch was cut there by the agent's limits; reaching it refuses the rest.
        """
        if replace or mission_id != self.mission_id:
            await self.interrupt()
            self.mission_id = mission_id
            self.completed_step = -1
            self._releases.clear()
        if await_release is not None:
            self.completed_step = max(self.completed_step, await_release)
            self._pending.append(_BarrierWait(step=await_release))
        self._pending.extend(actions)
        if refusal is not None:
            self._pending.append(_RefusedAt(refusal))
        self._wakeup.set()

    async def interrupt(self) -> None:
        """Empty the queue and cancel the running action or sync wait."""
        self._pending.clear()
        self._executor.forget_anchor()
        current = self._current
        if current is not None and not current.done():
            current.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await current
        self.waiting_sync = None
        self.current_step = -1
        self.resume()  # new orders (replace, or an exception reaction) override a pause

    async def pause(self, reason: str | None) -> None:
        """Stop where we are and keep the queue; the interrupted action resumes where it left off."""
        self.pause_reason = reason
        if self.paused:
            return
        self.paused = True
        self._resumed.clear()
        current = self._current
        if current is not None and not current.done() and self.waiting_sync is None:
            remaining = self._executor.continuation
            current.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await current
            if remaining is not None:
                self._pending.appendleft(remaining)
        await self._executor.hold_vehicle()

    def resume(self) -> None:
        self.paused = False
        self.pause_reason = None
        self._resumed.set()

    def release(self, mission_id: str, step: int) -> None:
        """The daemon released ``step`` (type 5); a release for a barrier not reached is ignored."""
        if mission_id != self.mission_id:
            log.warning(
                "release of step %d for mission %s, but running %s", step, mission_id, self.mission_id
            )
            return
        if step != self.waiting_sync and step > self.completed_step:
            log.warning("release of step %d ignored: not reached (completed %d)", step, self.completed_step)
            return
        self._releases.add(step)
        self._release_event.set()

    def awaits_release(self, mission_id: str, step: int) -> bool:
        """True when the queue waits for the release of ``step``, which it has not had yet.

        That is the barrier it waits at, or the last step it completed (a rejoin's barrier before
        its wait starts): at most two steps at any time. The release beacon (agent/beacon.py)
        checks this before it spends any hashing on a datagram.
        """
        return (
            mission_id == self.mission_id
            and step not in self._releases
            and (step == self.waiting_sync or step == self.completed_step)
        )

    def released(self, mission_id: str, step: int) -> bool:
        """True when ``step`` of the current mission was released already (by TCP or a beacon)."""
        return mission_id == self.mission_id and step in self._releases

    async def _run(self) -> None:
        while True:
            while not self._pending or self.paused:
                self._wakeup.clear()
                if self.paused:
                    await self._resumed.wait()
                else:
                    await self._wakeup.wait()
            action = self._pending.popleft()
            self.current_step = action.step
            self._current = asyncio.create_task(self._perform(action), name=f"action-{action.step}")
            try:
                await self._current
            except asyncio.CancelledError:
                me = asyncio.current_task()
                if me is not None and me.cancelling():
                    raise  # the queue itself is stopping; only an interrupted action is swallowed
            self._current = None
            self.current_step = -1

    async def _perform(self, action: Action | _BarrierWait | _RefusedAt) -> None:
        mission_id = self.mission_id or ""
        if isinstance(action, _BarrierWait):
            await self._wait_release(mission_id, action.step)
            return
        refusal = (
            action.refusal if isinstance(action, _RefusedAt) else self._vet(action) if self._vet else None
        )
        if refusal is not None:
            self._pending.clear()
            self._executor.forget_anchor()
            if self._on_refused is not None:
                await self._on_refused(refusal)
            return
        assert not isinstance(action, _RefusedAt)
        try:
            await self._executor.run(action)
        except ActionFailed as exc:
            self._pending.clear()
            await self._on_failed(action, str(exc))
            return
        self.completed_step = max(self.completed_step, action.step)
        if action.sync:
            await self._wait_release(mission_id, action.step)

    async def _wait_release(self, mission_id: str, step: int) -> None:
        self.waiting_sync = step
        await self._on_finished(mission_id, step)
        while step not in self._releases:
            self._release_event.clear()
            await self._release_event.wait()
        self.waiting_sync = None
        await self._resumed.wait()  # a pause during the barrier wait holds past the release

"""In-process extensions: user modules that watch the fleet and act, loaded from the configuration.

In the spirit of CoUAS user modules (seed 004, Fig. 6: applications on top of the message center)
and Skybrush extensions, an extension is a :class:`gcs.core.context.Service` that subclasses
:class:`Extension` and overrides the hooks it needs:

* ``on_status(agent, status)``: every status report, in order per agent (the newest of each
  agent per status tick, gcs/link/status_tick.py ``STATUS_TICK_S``; it runs in this
  extension's own hook consumer, gcs/link/dispatch.py: a slow hook delays only this extension;
  schedule slow work with :meth:`Extension.spawn`);
* ``on_event(event)``: every fleet event (agent_joined, mission_completed, ...);
* ``on_join(agent)`` / ``on_leave(agent, why)``: an agent connected / was lost or disconnected;
* ``setup()`` / ``teardown()``: after start / before stop.

and uses the helpers: :meth:`every` / :meth:`after` (scheduled actions), :meth:`send` /
:meth:`send_all` (a geofence or parameters to one or all agents, through the command port),
:meth:`command` (rtl, land, hold, resume), :meth:`publish` (an event), :attr:`statuses` (latest
status per agent).

A hook that raises is logged and counted; it never costs an agent its connection.

Configuration (``[daemon] extensions = ["gcs.extensions.builtin.geofence_alarm"]`` and
``[daemon.extension_options."gcs.extensions.builtin.geofence_alarm"]``): each entry is
``package.module`` (the module's ``create_extension(options)`` builds it) or
``package.module:name`` (``name(options)`` builds it: a class or a factory function).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, Literal

from gcs.observe.events import Event, Severity
from protocol.actions import Hold
from protocol.packets import Body, PerformActions, Resume, SetParameters, StatusReport

if TYPE_CHECKING:
    from gcs.core.config import DaemonConfig
    from gcs.core.context import Service, ServiceContext
    from gcs.link.session import AgentSession
    from gcs.link.status_bus import Subscriptions

log = logging.getLogger("gcs.extensions")

Command = Literal["rtl", "land", "hold", "resume"]


class ExtensionError(RuntimeError):
    """An extension that cannot be loaded; the message names it."""


class Extension:
    """Base class of extensions; subclass it and override the hooks you need."""

    name = "extension"

    def __init__(self, options: dict[str, Any] | None = None) -> None:
        self.options: dict[str, Any] = dict(options or {})
        self.context: ServiceContext | None = None
        self.hook_errors = 0
        self._tasks: set[asyncio.Task[Any]] = set()
        self._events: asyncio.Queue[Event] | None = None
        self._subscriptions: Subscriptions | None = None

    # --- hooks (override) ---------------------------------------------------------------------------

    async def setup(self) -> None:
        """Called once the extension is attached to the running daemon."""

    async def teardown(self) -> None:
        """Called before the daemon stops."""

    async def on_status(self, agent: str, status: StatusReport) -> None:
        """Every status report of every agent."""

    async def on_event(self, event: Event) -> None:
        """Every fleet event."""

    async def on_join(self, agent: str) -> None:
        """An agent completed its handshake."""

    async def on_leave(self, agent: str, why: str) -> None:
        """An agent was lost (silent) or its connection ended."""

    # --- Service protocol -----------------------------------------------------------------------------

    async def start(self, ctx: ServiceContext) -> None:
        self.context = ctx
        self._subscriptions = ctx.agents.subscriptions()  # its hooks on the status bus, ended in stop()
        if type(self).on_status is not Extension.on_status:  # objects are built per report only for it
            self._subscriptions.subscribe("status", self._status_hook)
        self._subscriptions.subscribe("join", self._join_hook)
        self._events = ctx.events.subscribe()
        self.spawn(self._pump())
        await self._guard("setup", self.setup())

    async def stop(self) -> None:
        await self._guard("teardown", self.teardown())
        if self._subscriptions is not None:
            self._subscriptions.close()
        if self.context is not None and self._events is not None:
            self.context.events.unsubscribe(self._events)
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

    # --- helpers --------------------------------------------------------------------------------------

    @property
    def statuses(self) -> dict[str, StatusReport]:
        """Latest status of every connected agent."""
        assert self.context is not None, "extension not started"
        return {s.identity: s.status for s in self.context.agents.connected() if s.status is not None}

    def spawn(self, coroutine: Awaitable[Any]) -> asyncio.Task[Any]:
        """Run a coroutine in the background; cancelled when the extension stops."""
        task = asyncio.ensure_future(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def every(self, seconds: float, callback: Callable[[], Awaitable[None]]) -> asyncio.Task[Any]:
        """Call ``callback`` every ``seconds`` until the extension stops."""

        async def loop() -> None:
            while True:
                await asyncio.sleep(seconds)
                await self._guard("every", callback())

        return self.spawn(loop())

    def after(self, seconds: float, callback: Callable[[], Awaitable[None]]) -> asyncio.Task[Any]:
        """Call ``callback`` once, ``seconds`` from now."""

        async def once() -> None:
            await asyncio.sleep(seconds)
            await self._guard("after", callback())

        return self.spawn(once())

    async def send(self, agent: str, body: Body) -> bool:
        """Queue one type-3 body (a geofence, parameters) for one agent; False if not connected.

        Through the daemon's command port (gcs/control/command_port.py), so a geofence sent here is the
        fence the emergency monitor checks. Type-4 commands (which move a drone) go through
        :meth:`command`, i.e. the vehicle authority at extension priority; a barrier release is
        the mission runner's: any other body is refused here with :class:`ExtensionError`.
        """
        assert self.context is not None, "extension not started"
        if isinstance(body, PerformActions):
            raise ExtensionError("type-4 commands go through Extension.command (the vehicle authority)")
        if not isinstance(body, SetParameters):
            raise ExtensionError(
                f"extensions send geofences and parameters (SetParameters), not {type(body).__name__}"
            )
        return self.context.commands.configure(agent, body)

    async def send_all(self, body: Body) -> list[str]:
        """Send one body to every connected agent; returns who got it."""
        assert self.context is not None, "extension not started"
        names = [s.identity for s in self.context.agents.connected()]
        sent = [await self.send(n, body) for n in names]
        return [n for n, ok in zip(names, sent, strict=True) if ok]

    async def command(self, agent: str, command: Command, reason: str = "") -> bool:
        """rtl / land (deconflicted return, out of its mission), hold / resume (keep the queue).

        Goes through the vehicle authority at ``extension`` priority (docs/cooperation.md): True
        when accepted, False when the drone is not connected or a higher source controls it.
        """
        ctx = self.context
        assert ctx is not None, "extension not started"
        if ctx.agents.session(agent) is None:
            return False
        why = f"{self.name}: {reason}" if reason else self.name
        if command == "hold":
            return ctx.authority.hold(agent, "extension", why)[0]
        if command == "resume":
            return ctx.authority.release(agent, "extension", why)[0]
        descent = await ctx.bring_down([agent], command, "extension", why)
        return agent in descent.delivered

    def publish(
        self,
        kind: str,
        message: str,
        *,
        severity: Severity = "info",
        agent: str | None = None,
        data: dict[str, Any] | None = None,
    ) -> Event:
        assert self.context is not None, "extension not started"
        return self.context.events.publish(
            kind, message, severity=severity, agent=agent, data={"extension": self.name, **(data or {})}
        )

    # --- plumbing -------------------------------------------------------------------------------------

    async def _guard(self, what: str, coroutine: Awaitable[None]) -> None:
        try:
            await coroutine
        except asyncio.CancelledError:
            raise
        except Exception:
            self.hook_errors += 1
            log.exception("extension %s: %s failed", self.name, what)

    async def _status_hook(self, session: AgentSession, status: StatusReport) -> None:
        await self._guard("on_status", self.on_status(session.identity, status))

    async def _join_hook(self, session: AgentSession, resume: Resume | None) -> None:
        await self._guard("on_join", self.on_join(session.identity))

    async def _pump(self) -> None:
        assert self._events is not None
        while True:
            event = await self._events.get()
            if event.agent and event.kind in ("agent_lost", "agent_disconnected"):
                await self._guard("on_leave", self.on_leave(event.agent, event.kind))
            await self._guard("on_event", self.on_event(event))


# re-exported for extension authors: the actions an extension may queue
__all__ = ["Command", "Extension", "ExtensionError", "Hold", "load_extension", "load_extensions"]


def load_extension(path: str, options: dict[str, Any] | None = None) -> Service:
    """Import ``package.module[:name]`` and build the extension with ``options``."""
    module_name, _, attr = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ExtensionError(f"extension {path!r}: cannot import {module_name!r}: {exc}") from None
    factory = getattr(module, attr or "create_extension", None)
    if not callable(factory):
        raise ExtensionError(
            f"extension {path!r}: {module_name} has no {'callable ' + attr if attr else 'create_extension()'}"
        )
    service = factory(dict(options or {}))
    if not all(hasattr(service, a) for a in ("name", "start", "stop")):
        raise ExtensionError(f"extension {path!r} did not build a service (name, start, stop)")
    return service


def load_extensions(config: DaemonConfig) -> list[Service]:
    """Every extension the configuration lists, in order."""
    return [load_extension(p, config.extension_options.get(p)) for p in config.extensions]

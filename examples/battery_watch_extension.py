"""An in-process extension: hold the whole fleet when any drone's battery drops below a limit.

Load it into the daemon (gcs.toml):

    [daemon]
    extensions = ["examples.battery_watch_extension:BatteryWatch"]
    [daemon.extension_options."examples.battery_watch_extension:BatteryWatch"]
    hold_below_pct = 35

(run `gcs serve` from the repository root so `examples` is importable, or copy the module into
your own package). See docs/api.md#extensions for the hook API.
"""

from __future__ import annotations

from typing import Any

from gcs.extensions import Extension
from protocol.packets import StatusReport


class BatteryWatch(Extension):
    name = "battery-watch"

    def __init__(self, options: dict[str, Any] | None = None) -> None:
        super().__init__(options)
        self.limit = float(self.options.get("hold_below_pct", 30.0))
        self.tripped = False

    async def setup(self) -> None:
        self.every(10.0, self.report)  # a scheduled action

    async def report(self) -> None:
        low = {n: s.battery.pct for n, s in self.statuses.items() if s.battery.pct is not None}
        if low:
            self.publish("battery_summary", f"lowest battery {min(low.values()):.0f} %", data=low)

    async def on_status(self, agent: str, status: StatusReport) -> None:
        pct = status.battery.pct
        if self.tripped or pct is None or pct >= self.limit or status.landed:
            return
        self.tripped = True
        self.publish(
            "battery_hold", f"{agent} at {pct:.0f} %: holding the fleet", severity="warning", agent=agent
        )
        for name in self.statuses:
            await self.command(name, "hold", f"{agent} battery {pct:.0f} %")

    async def on_join(self, agent: str) -> None:
        self.publish("battery_watch_hello", f"watching {agent}", agent=agent)

"""A demo's progress: one line each time a machine's run moves to another pose or state, read
from the daemon's own HMI status (what an operator's page shows), so a slow run shows it moves."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Mapping
from typing import Any


class RunProgress:
    """Prints a line per pose and state change of each machine's run (``update``)."""

    def __init__(self, t0: float | None = None, out: Callable[[str], None] = print) -> None:
        self.t0 = time.monotonic() if t0 is None else t0
        self.out = out
        self._last: dict[str, tuple] = {}

    def update(self, name: str, st: Mapping[str, Any]) -> None:
        """One machine's HMI status (``/api/status``); a line when its run, state or pose
        changed since the last one."""
        if not st.get("run_id"):
            return
        pose = (st.get("probing") or {}).get("pose") if st.get("busy") else None
        key = (st["run_id"], st.get("state"), pose)
        if self._last.get(name) == key:
            return
        self._last[name] = key
        parts = [f"{name}: {st.get('state')}"]
        if pose is not None:
            parts.append(f"pose {pose}")
        if st.get("total"):
            parts.append(f"{st.get('done', 0)}/{st['total']} touches")
        if st.get("eta_s"):
            parts.append(f"about {st['eta_s']:.0f} s left")
        self.out(f"  [{time.monotonic() - self.t0:6.1f} s] " + ", ".join(parts))


async def watch(hmis: Mapping[str, str], token: str, progress: RunProgress,
                period_s: float = 0.25) -> None:
    """Poll each machine's HMI status and feed ``progress`` until cancelled (a status that
    cannot be read is skipped: the demo's own wait decides what is a failure)."""
    import aiohttp

    async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as http:
        while True:
            for name, url in hmis.items():
                try:
                    async with http.get(url + "api/status") as r:
                        progress.update(name, (await r.json())[name])
                except (aiohttp.ClientError, KeyError, ValueError):
                    pass
            await asyncio.sleep(period_s)

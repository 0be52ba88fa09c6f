"""``rumba verify --map``: the map job's operator prompts on the terminal — each shown once, the
Enter key answering it (the HMI's Continue), Ctrl-C aborting the run as ever — and the map run's
end as its exit code."""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import Awaitable, Callable
from typing import Any

from rich.console import Console


class Prompts:
    """Answers the prompts a run's statuses show, one Enter each, through ``go_on``."""

    def __init__(self, console: Console, go_on: Callable[[], Awaitable[None]]) -> None:
        self.console = console
        self.go_on = go_on
        self.answered: set[int] = set()
        self.task: asyncio.Task | None = None

    def see(self, st: dict[str, Any]) -> None:
        p = st.get("prompt")
        if not p or p["placement"] in self.answered or not st.get("busy"):
            return
        self.answered.add(p["placement"])
        self.console.print(f"[bold]{p['text']}[/]: press Enter to continue (Ctrl-C aborts)",
                           markup=True, highlight=False)
        self.task = asyncio.create_task(self._answer())

    async def _answer(self) -> None:
        if not await _enter():
            self.console.print("standard input closed: answer the prompt on the HMI "
                               "(Continue) or Ctrl-C to abort")
            return
        await self.go_on()

    def close(self) -> None:
        if self.task is not None:
            self.task.cancel()


async def _enter() -> bool:
    """Wait for a line on standard input without a thread (a thread blocked in ``input()``
    would hold the process after an abort); False at end of input."""
    loop = asyncio.get_running_loop()
    fut: asyncio.Future[bool] = loop.create_future()
    fd = sys.stdin.fileno()

    def ready() -> None:
        line = sys.stdin.readline()
        if not fut.done():
            fut.set_result(bool(line))

    loop.add_reader(fd, ready)
    try:
        return await fut
    finally:
        with contextlib.suppress(Exception):
            loop.remove_reader(fd)


def map_exit(run_id: str, st: dict[str, Any], console: Console) -> int:
    """0 when the map is done (1 when its volumetric figure FAILs its limit), 2 otherwise."""
    if st["state"] != "IDLE" or not st.get("map"):
        console.print(f"[bold magenta]ERROR[/] map run {run_id} {st['state']}: {st['reason']}")
        return 2
    console.print(f"map run {run_id}: {st['reason']}", markup=False)
    print(f"map (JSON): {st['map']['json']}")
    return 1 if st["map"].get("status") == "FAIL" else 0

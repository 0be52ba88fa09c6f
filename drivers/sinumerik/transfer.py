"""A reviewed part program (a compensation's ``$TC_CARR`` program) into the control's "Part
Programs" folder over its OPC UA file system — written, not selected, not started: a person
selects it at the machine and presses NC start, as the compensation's review requires."""

from __future__ import annotations

import asyncio
import concurrent.futures

from contracts.sinumerik_space import FILE_SYSTEM, PROGRAM_FOLDERS, PROGRAM_NAME, file_name
from drivers.base import LinkError
from drivers.retry import with_backoff
from drivers.sinumerik.client import SinumerikSession
from drivers.sinumerik.schema import SinumerikLinkConfig

COMPENSATION_PROGRAM = "RUMBA_CARR"
"""The control's name of the compensation program (each confirmed change replaces it)."""


async def send_part_program(cfg: SinumerikLinkConfig, name: str, text: str) -> str:
    """Write ``text`` as ``<name>.MPF`` into "Part Programs"; the file's name on the control.
    ``LinkError`` naming the cause when the control cannot be reached or refuses."""
    if not PROGRAM_NAME.fullmatch(name):
        raise LinkError(f"part-program name {name!r}: upper-case letters, digits and '_'")
    session = SinumerikSession(cfg)
    await with_backoff(session.open, what=f"sinumerik {cfg.url}",
                       timeout_s=cfg.connect_timeout_s, refused_is_final=True)
    try:
        folder = await session.browse(*FILE_SYSTEM, PROGRAM_FOLDERS[0])
        await session.upload(folder, file_name(name), text)
    finally:
        await session.close()
    return file_name(name)


def send_part_program_blocking(cfg: SinumerikLinkConfig, name: str, text: str,
                               timeout_s: float = 60.0) -> str:
    """``send_part_program`` from synchronous code (the compensation's writer runs in a worker
    thread or inside a run's task): on an event loop of its own, in a thread of its own."""
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        future = pool.submit(asyncio.run, send_part_program(cfg, name, text))
        try:
            return future.result(timeout=timeout_s)
        except concurrent.futures.TimeoutError:
            raise LinkError(f"sinumerik {cfg.url}: {name} not written within "
                            f"{timeout_s:g} s") from None

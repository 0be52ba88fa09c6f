"""Controller dialects: one module per dialect, found by name here."""

from __future__ import annotations

from contracts.result_lines import DIALECT_NAMES
from programs.dialects.base import Block, BoundDialect, Dialect, safe_text
from programs.dialects.fanuc import Fanuc
from programs.dialects.heidenhain import Heidenhain
from programs.dialects.linuxcnc import LinuxCNC
from programs.dialects.siemens import Siemens
from programs.geometry import ProgramError

# Haas is the fanuc dialect reading rotary skips by letter: a variant, not a class of its own.
DIALECTS: dict[str, type[Dialect]] = {
    cls.name: cls for cls in (Fanuc, Siemens, Heidenhain, LinuxCNC)}
assert set(DIALECTS) | {"haas"} == set(DIALECT_NAMES), "a dialect without a class (or a name)"


def get_dialect(name: str) -> Dialect:
    """A dialect by name (``haas`` is the fanuc dialect reading rotary skips by letter)."""
    if name == "haas":
        return Fanuc(haas=True)
    if name not in DIALECTS:
        raise ProgramError(f"unknown dialect {name!r} (known: {', '.join(sorted(DIALECTS))}, haas)")
    return DIALECTS[name]()


__all__ = ["DIALECTS", "Block", "BoundDialect", "Dialect", "Fanuc", "Heidenhain", "LinuxCNC",
           "Siemens", "get_dialect", "safe_text"]

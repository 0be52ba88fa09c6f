"""Controller dialects: one module per dialect family, found through the dialect records
(``contracts.dialects``)."""

from __future__ import annotations

from contracts.dialects import DIALECTS as RECORDS
from contracts.dialects import dialect, load
from programs.dialects.base import Block, BoundDialect, Dialect, safe_text
from programs.dialects.fanuc import Fanuc
from programs.dialects.heidenhain import Heidenhain
from programs.dialects.linuxcnc import LinuxCNC
from programs.dialects.siemens import Siemens
from programs.geometry import ProgramError

# the program writer of each family (Haas is the fanuc family reading rotary skips by letter:
# a variant, not a class of its own)
DIALECTS: dict[str, type[Dialect]] = {
    cls.name: cls for cls in (Fanuc, Siemens, Heidenhain, LinuxCNC)}


def get_dialect(name: str) -> Dialect:
    """The program writer of dialect ``name`` (its record's class and options)."""
    try:
        rec = dialect(name)
    except ValueError:
        raise ProgramError(f"unknown dialect {name!r} (known: {', '.join(RECORDS)})") from None
    d: Dialect = load(rec.program)(**dict(rec.program_options))
    if d.label != rec.name:
        d.record_name = rec.name
    return d


__all__ = ["DIALECTS", "Block", "BoundDialect", "Dialect", "Fanuc", "Heidenhain", "LinuxCNC",
           "Siemens", "get_dialect", "safe_text"]

"""G-code executor of the simulated controller: one interpreter core, one module per dialect,
found through the dialect records (``contracts.dialects``)."""

from __future__ import annotations

from typing import Any

from contracts.dialects import DIALECTS, dialect, load
from simulators.gcode.core import Alarm, BlockQueue, MachineIO, ProbeOutcome, run


def make_interpreter(dialect_name: str, io: MachineIO, variables: dict | None = None,
                     **options: Any) -> Any:
    """An interpreter for ``dialect_name`` (one of ``DIALECTS``) driving ``io``; ``options``
    are the settings its record's ``interpreter_options`` names (others are not passed)."""
    try:
        rec = dialect(dialect_name)
    except ValueError:
        raise ValueError(f"unknown dialect {dialect_name!r}; expected one of "
                         f"{', '.join(DIALECTS)}") from None
    variables = {} if variables is None else variables
    for name, value in rec.interpreter_variables:
        variables.setdefault(name, value)
    opts = {k: v for k, v in options.items() if k in rec.interpreter_options}
    return load(rec.interpreter)(io, variables, name=rec.name, **opts)


__all__ = ["DIALECTS", "Alarm", "BlockQueue", "MachineIO", "ProbeOutcome", "make_interpreter",
           "run"]

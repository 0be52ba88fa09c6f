"""The simulated control's own kinematic values: what compensation writes, never truth.

A ``KinematicsStore`` holds ``{address: value}`` of the machine file's ``controller_kinematics``
section (each parameter's address and, for a Siemens pivot, its closing vector component), in the
control's unit (mm; a Fanuc/Heidenhain orientation in deg of the held link, a Siemens axis-vector
component unit-less, as ``programs.compensation`` writes them). Writes reach it from the
interpreters (Fanuc/Haas ``G10 L52`` and declared macro variables, Siemens ``$TC_CARR``), from
``VirtualController.halcmd_setp`` (LinuxCNC: halcmd is not G-code) and from
``VirtualController.operator_entry`` (Haas settings and the Heidenhain kinematics table: those
controls take these values by hand, there is no program write). Only declared addresses exist:
anything else is refused (``KeyError``), as a control rejects a parameter it does not hold.
The truth model is not touched: a compensated machine measures better only because the
identification runs against the controller model these values describe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from contracts.controller_kinematics import ControllerKinematics
from contracts.dialects import dialect
from contracts.setup_files import load_controller_kinematics


@dataclass(frozen=True)
class KinematicsWrite:
    """One audited write: address, value before, value after, who wrote it."""

    address: str
    old: float
    new: float
    source: str


@dataclass
class KinematicsStore:
    """The control's kinematic values by address, with an audit of every write."""

    family: str
    initial: dict[str, float]
    current: dict[str, float] = field(default_factory=dict)
    audit: list[KinematicsWrite] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.current:
            self.current = dict(self.initial)

    @classmethod
    def from_spec(cls, spec: ControllerKinematics) -> KinematicsStore:
        """The section's current values in the control's units (every address it declares)."""
        values: dict[str, float] = {}
        for p in spec.params:
            if p.kind == "pivot":
                values[p.address] = float(p.value)
                if p.closing is not None:
                    values[p.closing] = float(p.closing_value or 0.0)
            elif dialect(spec.family).carrier:  # Siemens: the axis-vector components the tilt moves
                values.update(p.vector_values(p.value * 1e-6))
            else:  # Fanuc parameter / Heidenhain SPA-SPC: the held link in degrees
                values[p.address] = math.degrees(p.value * 1e-6)
        return cls(spec.family, values)

    @classmethod
    def from_machine_file(cls, path: Path | str) -> KinematicsStore | None:
        """The store of a machine file's section (None when the file has none)."""
        _, spec = load_controller_kinematics(path)
        return None if spec is None else cls.from_spec(spec)

    def holds(self, address: str) -> bool:
        return address in self.current

    def read(self, address: str) -> float:
        if address not in self.current:
            raise KeyError(f"{address} is not a kinematic value of this control")
        return self.current[address]

    def write(self, address: str, value: float, source: str) -> None:
        """Set ``address`` (declared only; finite values only) and audit it."""
        if address not in self.current:
            raise KeyError(f"{address} is not a kinematic value of this control "
                           f"(held: {', '.join(self.current)})")
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"{address}: {value!r} is not a finite number")
        self.audit.append(KinematicsWrite(address, self.current[address], v, source))
        self.current[address] = v

    def values(self) -> dict[str, float]:
        return dict(self.current)


__all__ = ["KinematicsStore", "KinematicsWrite"]

"""Compensation write-back: the identified correction in each control's own form."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from contracts.controller_kinematics import ControllerKinematics
from programs.compensation import fanuc, haas, heidenhain, linuxcnc, siemens
from programs.compensation.common import (
    CompensationError,
    CompensationOutput,
    Listed,
    Value,
    fixed,
    fmt_value,
)
from programs.compensation.linuxcnc import patch_hal_file

if TYPE_CHECKING:
    from identification.compensation import ParamChange

Writer = Callable[..., CompensationOutput]
WRITERS: dict[str, Writer] = {"linuxcnc": linuxcnc.render, "fanuc": fanuc.render,
                              "haas": haas.render, "siemens": siemens.render,
                              "heidenhain": heidenhain.render}


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """The writer of ``spec.family``."""
    if spec.family not in WRITERS:
        raise CompensationError(f"no compensation writer for family {spec.family!r}")
    return WRITERS[spec.family](spec, changes, run_id=run_id, machine=machine,
                                rollback=rollback)


__all__ = ["WRITERS", "CompensationError", "CompensationOutput", "Listed", "Value", "fixed",
           "fmt_value", "patch_hal_file", "render"]

"""Compensation write-back: the identified correction in each control's own form."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from contracts.controller_kinematics import ControllerKinematics
from contracts.dialects import DIALECTS, load
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


def writer(family: str) -> Writer:
    """The compensation writer of dialect ``family`` (its record's ``compensation_writer``)."""
    if family not in DIALECTS:
        raise CompensationError(f"no compensation writer for family {family!r}")
    return load(DIALECTS[family].compensation_writer)


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """The writer of ``spec.family``."""
    return writer(spec.family)(spec, changes, run_id=run_id, machine=machine, rollback=rollback)


__all__ = ["CompensationError", "CompensationOutput", "Listed", "Value", "fixed",
           "fmt_value", "patch_hal_file", "render", "writer"]

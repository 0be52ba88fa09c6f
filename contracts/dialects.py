"""One record per controller dialect, read by name by every layer (programs, simulator,
temperatures, controller kinematics, compensation writers, schemas)."""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass
from typing import Annotated, Any

from pydantic import AfterValidator, WithJsonSchema

KINEMATICS_ADDRESSES = ("hal_pin", "parameter_or_macro", "setting", "carrier", "table_row")
"""How a control keeps its kinematics values (``contracts.controller_kinematics`` checks each):
a LinuxCNC HAL pin, a Fanuc parameter number or macro variable, a Haas setting number, a
Sinumerik ``$TC_CARR`` carrier entry (offset vectors with a closing vector, axis vectors), a
Heidenhain kinematics-table row/column."""


@dataclass(frozen=True)
class DialectRecord:
    """What each layer needs to know of one dialect; adding a dialect adds one of these (and its
    template folder, program writer, interpreter, compensation writer and goldens).

    Dotted paths (``module:attribute``) are imported by the layer that uses them, so a
    contracts-level record never imports programs or simulators (the dependency arrow)."""

    name: str
    """As the user names it: daemon.yaml ``dialect:``, ``--dialect``, a controller-kinematics
    ``family:``, the program's header."""
    family: str
    """The template folder ``gcode_templates/<family>/`` and the program writer's family (Haas
    writes Fanuc macro B)."""
    program: str
    """``module:Class`` of the program writer (a ``programs.dialects.Dialect``)."""
    interpreter: str
    """``module:Class`` of the simulator's G-code interpreter (``simulators.gcode``)."""
    compensation_writer: str
    """``module:function`` writing a compensation program or file for this control."""
    kinematics_address: str
    """One of ``KINEMATICS_ADDRESSES``: the form of a controller-kinematics address."""
    verdict_variable: str
    """Where the verdict program writes the verdict code (``result_lines.VERDICT_VARIABLES``)."""
    result_counter: str
    """The variable the program sets to a touch's seq (``result_lines.RESULT_COUNTERS``)."""
    handshake_variables: tuple[str, str] | None = None
    """(ack, stop) when a link reads the results from the controller's variables
    (``result_lines.HANDSHAKE_VARIABLES``)."""
    stop_program: tuple[str, str] | None = None
    """(program, variable) of the called stop program when the link writes files, not variables
    (``result_lines.STOP_PROGRAMS``)."""
    kinematics_orientation: bool = True
    """Does the control hold orientation (angle) parameters, not only pivot positions?"""
    program_options: tuple[tuple[str, Any], ...] = ()
    """Keyword arguments of the program writer's class (Haas: ``haas=True``)."""
    interpreter_variables: tuple[tuple[str, float], ...] = ()
    """Variables the simulated control starts a program with (LinuxCNC: ``#<_task>`` = 1, a
    real execution rather than a preview)."""
    interpreter_options: tuple[str, ...] = ()
    """The simulated controller's settings the interpreter takes (Heidenhain: the files
    ``CALL PGM`` reaches, the TCH PROBE cycle's measuring path, feed and stylus radius)."""
    temperature_variable: str | None = None
    """Regular expression of a macro variable a DNC program may print as a temperature (the
    controls' user ranges minus rumba's own); ``None``: the programs print none."""
    temperature_form: str = ""
    """What ``temperature_variable`` accepts, in words, for an error message."""
    temperature_refusal: str = ""
    """Why the dialect prints no temperature over DNC, when it prints none (an error message)."""

    @property
    def carrier(self) -> bool:
        """Siemens-style kinematics: offset vectors closed by a closing vector, axis vectors."""
        return self.kinematics_address == "carrier"

    def prints_temperature(self, variable: str) -> bool:
        """May a program of this dialect print ``variable`` as a temperature?"""
        return (self.temperature_variable is not None
                and re.fullmatch(self.temperature_variable, variable) is not None)


# Fanuc/Haas common variables #100-#199, #500-#597, #700-#999 (DPRNT; #598-#699 are rumba's
# verdict, counter and result ring); Sinumerik R parameters R5-R98 (WRITE like the result
# lines; R4 verdict, R99 counter, R100-R187 ring); Heidenhain Q0-Q99, the TNC's "freely usable"
# range (FN 16: F-PRINT like the result lines; Q100-Q199 are the TNC's, Q1575-Q1599 rumba's).
# A PMC ladder, a PLC or a synchronous action copies the sensor there.
_FANUC_VARIABLE = r"^#(1[0-9]{2}|5[0-8][0-9]|59[0-7]|[7-9][0-9]{2})$"
_FANUC_FORM = "a Fanuc common variable #100-#199, #500-#597 or #700-#999"

DIALECTS: dict[str, DialectRecord] = {r.name: r for r in (
    DialectRecord(
        name="fanuc", family="fanuc", program="programs.dialects.fanuc:Fanuc",
        interpreter="simulators.gcode.fanuc:FanucInterpreter",
        compensation_writer="programs.compensation.fanuc:render",
        kinematics_address="parameter_or_macro",
        verdict_variable="#598", result_counter="#599", handshake_variables=("#688", "#689"),
        temperature_variable=_FANUC_VARIABLE, temperature_form=_FANUC_FORM),
    DialectRecord(
        name="haas", family="fanuc", program="programs.dialects.fanuc:Fanuc",
        program_options=(("haas", True),),
        interpreter="simulators.gcode.haas:HaasInterpreter",
        compensation_writer="programs.compensation.haas:render",
        kinematics_address="setting", kinematics_orientation=False,
        verdict_variable="#598", result_counter="#599", handshake_variables=("#688", "#689"),
        temperature_variable=_FANUC_VARIABLE, temperature_form=_FANUC_FORM),
    DialectRecord(
        name="siemens", family="siemens", program="programs.dialects.siemens:Siemens",
        interpreter="simulators.gcode.siemens:SiemensInterpreter",
        compensation_writer="programs.compensation.siemens:render",
        kinematics_address="carrier",
        verdict_variable="R4", result_counter="R99", handshake_variables=("R188", "R189"),
        temperature_variable=r"^R([5-9]|[1-8][0-9]|9[0-8])$",
        temperature_form="a Sinumerik R parameter R5-R98"),
    DialectRecord(
        name="heidenhain", family="heidenhain", program="programs.dialects.heidenhain:Heidenhain",
        interpreter="simulators.gcode.heidenhain:HeidenhainInterpreter",
        interpreter_options=("files", "measuring_path_mm", "probe_feed_mm_min",
                             "stylus_radius_mm"),
        compensation_writer="programs.compensation.heidenhain:render",
        kinematics_address="table_row",
        verdict_variable="Q1598", result_counter="Q1599", stop_program=("RUMBASTP.H", "Q1689"),
        temperature_variable=r"^Q([0-9]|[1-9][0-9])$",
        temperature_form="a Heidenhain Q parameter Q0-Q99"),
    DialectRecord(
        name="linuxcnc", family="linuxcnc", program="programs.dialects.linuxcnc:LinuxCNC",
        interpreter="simulators.gcode.linuxcnc:LinuxcncInterpreter",
        interpreter_variables=(("#<_task>", 1.0),),
        compensation_writer="programs.compensation.linuxcnc:render",
        kinematics_address="hal_pin",
        verdict_variable="#3998", result_counter="#3999",
        # (PRINT,…)/(DEBUG,…) go to stderr or the GUI, (LOG,…) to a file
        temperature_refusal="LinuxCNC prints nothing on a serial line ((PRINT,…) and "
                            "(DEBUG,…) go to its stderr or GUI, (LOG,…) to a file): read the "
                            "channel as a HAL pin over the linuxcnc transport, or use source: "
                            "transmitter"),
)}
"""Every dialect by name, in the order they are listed everywhere."""


def _choices(names: list[str]) -> str:
    quoted = [f"'{n}'" for n in names]
    return quoted[0] if len(quoted) == 1 else f"{', '.join(quoted[:-1])} or {quoted[-1]}"


def dialect(name: str) -> DialectRecord:
    """The record of dialect ``name``; ``ValueError`` naming the known dialects otherwise."""
    rec = DIALECTS.get(name) if isinstance(name, str) else None
    if rec is None:
        raise ValueError(f"unknown dialect {name!r} (known: {', '.join(DIALECTS)})")
    return rec


def check_dialect_name(name: str) -> str:
    """A schema's dialect value: one of the registered dialects (read when validating, so a
    record added at run time is accepted)."""
    if name not in DIALECTS:
        raise ValueError(f"Input should be {_choices(list(DIALECTS))}")
    return name


DialectName = Annotated[str, AfterValidator(check_dialect_name),
                        WithJsonSchema({"type": "string", "enum": list(DIALECTS)})]
"""A dialect name in a pydantic schema, checked against ``DIALECTS`` when validating (the JSON
schema, for the docs, lists those registered at import)."""


def load(path: str) -> Any:
    """The object a record's ``module:attribute`` path names (imported on first use)."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


__all__ = ["DIALECTS", "KINEMATICS_ADDRESSES", "DialectName", "DialectRecord",
           "check_dialect_name", "dialect", "load"]

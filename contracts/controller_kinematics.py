"""The machine file's ``controller_kinematics`` section: schema, per-control checks, dataclasses.

What the control keeps of its kinematic model and where: each parameter names what it
moves in our model (``kind: pivot``: the rotary axes whose ``point_mm[component]`` it moves;
``kind: orientation``: the ISO 230-1 location error it holds, e.g. ``EA0C``), the control's
``address`` of it and its current ``value``: mm for a pivot, µrad of the held link for an
orientation (default 0; the writers of ``programs.compensation`` convert to the control's unit).

Addresses per family:

* ``linuxcnc``: a HAL pin (``xyzbc-trt-kins.x-offset``); an orientation a pin holding the link
  in degrees (``xyzbc-head-kins.ea0b-deg`` of config/linuxcnc/xyzbc_head_kins.comp; the shipped
  trt kins have none).
* ``fanuc``: a parameter number (``19700``, real type, mm / deg) or a macro variable (``#500``).
* ``haas``: a setting number (``255``); no orientation parameters (MRZP settings are positions).
* ``siemens``: ``$TC_CARR<n>[<k>]`` of tool carrier ``k``: a pivot an offset-vector component
  (l1 ``n`` = 1-3, l2 4-6, l3 15-17, l4 18-20) of its own component, with ``closing`` (and
  ``closing_value``) naming the vector component that keeps the chain closed (it receives the
  opposite change, Siemens: "I4 = −(I2 + I3)"); an orientation a rotary-axis vector component
  (v1 ``n`` = 7-9, v2 10-12) with ``vector``, the control's nominal vector of that axis (a table
  axis' vector is reversed on Siemens), the component being the one the tilt moves. An inclined
  axis (the nutating B ``[0, 0.7071, 0.7071]``) has its tilts in its own frame R0
  (``identification.kinematics.axis_frame``): a tilt about R0·x can move two or three components
  of the vector, the others named in ``also``; each is written as its nominal value plus the
  first-order change (``ControllerParamSpec.vector_values``).
* ``heidenhain``: kinematics-table ``row/column``: a pivot column X/Y/Z (its component), an
  orientation SPA/SPB/SPC (the error's rotation: EA… → SPA).

The control's machine frame is taken as parallel to the model's (the machine files choose axis
directions and ``sign`` so that it is).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import Field, field_validator

from contracts.dialects import DialectName, dialect
from contracts.setup_types import Bounded, Vec3, safe_name
from contracts.siemens_carrier import (
    carr_component,
    check_carr,
    check_vector,
    siemens_tilt,
    tilt_components,
)
from contracts.yaml_files import ConfigError, StrictModel
from identification.kinematics import Machine

if TYPE_CHECKING:
    from identification.compensation import ControllerParam

_HAL_PIN = re.compile(r"\A[A-Za-z0-9_][A-Za-z0-9_.-]{0,46}\Z")  # HAL_NAME_LEN 47
_NUMBER = re.compile(r"\A[1-9][0-9]{0,4}\Z")
_MACRO = re.compile(r"\A#[1-9][0-9]{0,4}\Z")
_HEIDENHAIN = re.compile(r"\A(0|[1-9][0-9]{0,3})/(X|Y|Z|SPA|SPB|SPC)\Z")
_ORIENTATION = re.compile(r"\AE([ABC])0([ABCXYZ])\Z")
_COMPONENTS = "xyz"


class GuardsFile(StrictModel):
    """Write-back guards (KinematicsOpt: 0.05 mm maximum modification, operator confirmation)."""

    max_change_um: float = Field(50.0, gt=0, le=1000)
    max_change_urad: float = Field(100.0, gt=0, le=10000)
    max_total_um: float = Field(100.0, gt=0, le=10000)
    # the sum of the changes of one value since the last verified baseline: two
    # changes each under max_change must not walk a value away; default: max_change_*
    max_cumulative_um: float | None = Field(None, gt=0, le=10000)
    max_cumulative_urad: float | None = Field(None, gt=0, le=100000)
    unattended: bool = False
    # the worth rule (identification/worth.py): a change must move a probed ball centre by at
    # least this, and the changes together lower the max link-caused distortion by as much
    min_effect_um: float = Field(2.0, ge=0, le=1000)


class ParamFile(StrictModel):
    name: str
    kind: Literal["pivot", "orientation"]
    axes: Annotated[list[Literal["A", "B", "C"]], Field(min_length=1, max_length=2)] | None = None
    component: str
    address: Annotated[str, Field(min_length=1, max_length=48)]
    value: Bounded | None = None
    closing: Annotated[str, Field(min_length=1, max_length=48)] | None = None
    closing_value: Bounded | None = None
    vector: Vec3 | None = None
    # Siemens orientation of an inclined axis: the other axis-vector components the tilt moves
    also: Annotated[list[Annotated[str, Field(min_length=1, max_length=48)]],
                    Field(min_length=1, max_length=2)] | None = None
    _n = field_validator("name")(safe_name)


class ControllerKinematicsFile(StrictModel):
    family: DialectName
    guards: GuardsFile = GuardsFile()
    params: list[ParamFile] = Field(min_length=1, max_length=32)
    # LinuxCNC on this PC: must the live pins be readable before identifying and writing?
    # ``when_written`` (default): only once rumba has written to this controller (before that
    # the machine file's values are the model); ``required``: always
    read_back: Literal["required", "when_written"] = "when_written"


@dataclass(frozen=True)
class ControllerParamSpec:
    """One control value: what it moves in the model, where the control keeps it, its value
    (mm for a pivot, µrad for an orientation), and the Siemens extras (closing vector, nominal
    axis vector) when used."""

    name: str
    kind: str
    axes: tuple[str, ...]
    component: str
    address: str
    value: float
    closing: str | None = None
    closing_value: float | None = None
    vector: tuple[float, float, float] | None = None
    also: tuple[str, ...] = ()
    # Siemens orientation: the link's rotation axis in the machine frame (R0·e_i of an inclined
    # axis, e_i of a principal one); None: e_i
    tilt_axis: tuple[float, float, float] | None = None

    def vector_values(self, rad: float) -> list[tuple[str, float]]:
        """Siemens orientation: (address, value) of each axis-vector component it writes, the
        nominal ``vector`` tilted by the held link ``rad`` to first order, v + θ·(t × v)."""
        if self.vector is None:
            raise ValueError(f"{self.name}: no axis vector (not a Siemens orientation)")
        moved = dict(tilt_components(self.component, self.vector, self.tilt_axis))
        out = []
        for address in (self.address, *self.also):
            j = carr_component(address)
            out.append((address, self.vector[j] + moved.get(j, 0.0) * rad))
        return out

    def held_rad(self, value: float) -> float:
        """Siemens orientation: the held link (rad) a value of ``address`` stands for (the
        inverse of ``vector_values`` on its first component)."""
        if self.vector is None:
            raise ValueError(f"{self.name}: no axis vector (not a Siemens orientation)")
        j = carr_component(self.address)
        factor = dict(tilt_components(self.component, self.vector, self.tilt_axis))[j]
        return (value - self.vector[j]) / factor

    def to_math(self) -> ControllerParam:
        from identification.compensation import ControllerParam  # the math's own type

        return ControllerParam(self.name, self.kind, self.axes, self.component)


@dataclass(frozen=True)
class ControllerKinematics:
    """The validated section: family, guards and parameters."""

    family: str
    max_change_um: float
    max_change_urad: float
    max_total_um: float
    unattended: bool
    params: tuple[ControllerParamSpec, ...]
    max_cumulative_um: float | None = None  # None: max_change_um
    max_cumulative_urad: float | None = None  # None: max_change_urad
    read_back: str = "when_written"
    min_effect_um: float = 2.0  # guards.min_effect_um: the worth rule's threshold

    def to_math(self) -> list[ControllerParam]:
        """The parameters as ``identification.compensation`` sees them."""
        return [p.to_math() for p in self.params]

    def param(self, name: str) -> ControllerParamSpec:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)


def _check_address(family: str, p: ParamFile, address: str, what: str) -> None:
    """Refuse an address this family cannot hold; ``what`` names the key in the message."""
    style = dialect(family).kinematics_address
    if style == "hal_pin":
        if not _HAL_PIN.fullmatch(address):
            raise ValueError(f"{what}: {address!r} is not a HAL pin name (letters, digits, "
                             "'_', '.', '-', at most 47)")
    elif style == "parameter_or_macro":
        if not (_NUMBER.fullmatch(address) or _MACRO.fullmatch(address)):
            raise ValueError(f"{what}: {address!r} is neither a parameter number (e.g. 19700) "
                             "nor a macro variable (e.g. #500)")
    elif style == "setting":
        if not _NUMBER.fullmatch(address):
            raise ValueError(f"{what}: {address!r} is not a setting number (e.g. 255)")
    elif style == "carrier":
        check_carr(p, address, what)
    else:  # table_row
        m = _HEIDENHAIN.fullmatch(address)
        if not m:
            raise ValueError(f"{what}: {address!r} is not a kinematics-table row/column "
                             "(e.g. 3/X; columns X Y Z SPA SPB SPC)")
        col = m.group(2)
        want = p.component.upper() if p.kind == "pivot" else "SP" + p.component[1]
        if col != want:
            raise ValueError(f"{what}: column {col} does not hold {p.component} (use {want})")


def _param(family: str, machine: Machine, p: ParamFile, key: str) -> ControllerParamSpec:
    rec = dialect(family)
    rotary = machine.rotary_axes
    tilt_axis: tuple[float, float, float] | None = None
    if p.kind == "pivot":
        if p.component not in _COMPONENTS:
            raise ValueError(f"{key}.component: a pivot moves x, y or z, got {p.component!r}")
        if p.axes is None:
            raise ValueError(f"{key}.axes: a pivot names the rotary axes it moves, e.g. [B]")
        if p.value is None:
            raise ValueError(f"{key}.value: a pivot needs the control's current value (mm)")
        if p.vector is not None:
            raise ValueError(f"{key}.vector: only an orientation takes an axis vector")
        axes = tuple(p.axes)
        if len(set(axes)) != len(axes):
            raise ValueError(f"{key}.axes: {list(axes)} names an axis twice")
        if rec.carrier and p.closing is None:
            raise ValueError(f"{key}.closing: a Siemens offset vector needs the vector that "
                             "closes the chain (e.g. $TC_CARR18[1])")
    else:
        m = _ORIENTATION.fullmatch(p.component)
        if m is None or p.component not in machine.location_error_names():
            raise ValueError(f"{key}.component: {p.component!r} is not an orientation error of "
                             f"this machine (one of {_tilts(machine)})")
        if not rec.kinematics_orientation:
            raise ValueError(f"{key}.kind: a {family} control has no orientation parameter "
                             "(its kinematics holds pivot positions only)")
        axes = (m.group(2),)
        if p.axes is not None and tuple(p.axes) != axes:
            raise ValueError(f"{key}.axes: {p.component} belongs to axis {axes[0]}, not {p.axes}")
        if p.closing is not None or p.closing_value is not None:
            raise ValueError(f"{key}.closing: only a Siemens pivot takes a closing vector")
        if rec.carrier:
            if p.vector is None:
                raise ValueError(f"{key}.vector: the control's nominal vector of axis "
                                 f"{axes[0]} is needed, e.g. [0, 0, -1]")
            if axes[0] not in rotary:
                raise ValueError(f"{key}.axes: {axes[0]} is not a rotary axis of this machine "
                                 f"{rotary}")
            tilt_axis = check_vector(p, key, machine, axes[0])
        elif p.vector is not None:
            raise ValueError(f"{key}.vector: only a Siemens orientation takes an axis vector")
    if p.also is not None and not (rec.carrier and p.kind == "orientation"):
        raise ValueError(f"{key}.also: only a Siemens orientation (inclined axis) takes "
                         "further vector components")
    for a in axes:
        if a not in rotary:
            raise ValueError(f"{key}.axes: {a} is not a rotary axis of this machine {rotary}")
    if p.closing is not None:
        if not rec.carrier:
            raise ValueError(f"{key}.closing: only a Siemens pivot takes a closing vector")
        if p.closing_value is None:
            raise ValueError(f"{key}.closing_value: the control's current value of "
                             f"{p.closing} is needed (mm)")
        _check_address(family, p, p.closing, f"{key}.closing")
        if p.closing == p.address:
            raise ValueError(f"{key}.closing: the closing vector cannot be the address itself")
    elif p.closing_value is not None:
        raise ValueError(f"{key}.closing_value: given without closing")
    _check_address(family, p, p.address, f"{key}.address")
    value = p.value if p.value is not None else 0.0
    return ControllerParamSpec(p.name, p.kind, axes, p.component, p.address, value, p.closing,
                               p.closing_value, tuple(p.vector) if p.vector else None,
                               tuple(p.also or ()), tilt_axis)


def _tilts(machine: Machine) -> list[str]:
    return [n for n in machine.location_error_names() if _ORIENTATION.fullmatch(n)]


def controller_kinematics(section: ControllerKinematicsFile, machine: Machine,
                          path: Path | str = "<machine>") -> ControllerKinematics:
    """The section checked against the machine and its family; ``ConfigError`` naming the file
    and the key (``controller_kinematics.params.2.address: …``)."""
    key = "controller_kinematics.params"
    params = []
    seen: dict[str, str] = {}
    values: dict[str, tuple[float, str]] = {}
    try:
        for i, p in enumerate(section.params):
            spec = _param(section.family, machine, p, f"{key}.{i}")
            if p.name in seen:
                raise ValueError(f"{key}.{i}.name: {p.name!r} is used twice")
            seen[p.name] = p.address
            pairs = [(spec.address, spec.value, f"{key}.{i}.address"),
                     *((a, spec.value, f"{key}.{i}.also.{k} address")
                       for k, a in enumerate(spec.also))]
            if spec.closing is not None:
                pairs.append((spec.closing, spec.closing_value or 0.0, f"{key}.{i}.closing"))
            for address, value, where in pairs:
                if address in values and (where.endswith("address")
                                          or values[address][1].endswith("address")):
                    raise ValueError(f"{where}: {address} is already held by "
                                     f"{values[address][1]}")
                if address in values and values[address][0] != value:
                    raise ValueError(f"{where}: {address} has value {value} here and "
                                     f"{values[address][0]} at {values[address][1]}")
                values.setdefault(address, (value, where))
            params.append(spec)
    except ValueError as e:
        raise ConfigError(f"{path}: {e}") from None
    g = section.guards
    return ControllerKinematics(section.family, g.max_change_um, g.max_change_urad,
                                g.max_total_um, g.unattended, tuple(params),
                                g.max_cumulative_um or g.max_change_um,
                                g.max_cumulative_urad or g.max_change_urad, section.read_back,
                                g.min_effect_um)


__all__ = ["ControllerKinematics", "ControllerKinematicsFile", "ControllerParamSpec",
           "GuardsFile", "ParamFile", "carr_component", "controller_kinematics", "siemens_tilt",
           "tilt_components"]

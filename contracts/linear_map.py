"""The map of the linear axes as a file (``rumba map --json``): a versioned schema the report,
the write-back and ``rumba map --map`` read, and the ``MapModel`` it rebuilds for predictions.

Units: report units (µm, µrad, controller mm) everywhere except ``parameters``, which holds the
estimate in the model's internal units (mm, rad; links first, then the map's Legendre
coefficients) with its full covariance, so that a prediction and its uncertainty can be
recomputed from the file alone (``map_model``).

Conventions (stated in the file too): each motion error e(x) = Σ_k c_k P_k(u) of the axis'
CONTROLLER position x, u = (2x − lo − hi)/(hi − lo) over the covered range [lo, hi]; components
in the machine's axis frame (ISO 230-1 names); degree 0 never a term (a setup or a link); a
linear straightness is a squareness (a link, in ``links``). The volumetric error is the tool
tip's actual minus nominal position relative to the workpiece, in the workpiece frame, rotary
axes at zero, minus its best rigid-body motion over the covered box (``rigid_convention``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from contracts.input_files import read_bounded
from contracts.yaml_files import ConfigError, format_validation
from identification.kinematics import Machine
from identification.linmap.field import MapModel
from identification.linmap.terms import MapBasis, MapTerm

SCHEMA = "rumba-linear-map/1"
MAX_MAP_BYTES = 64 * 2**20


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Value(_Model):
    value: float
    std: float
    unit: str


class Term(_Model):
    name: str  # EYX_P2
    degree: int
    value: float  # µm or µrad
    std: float


class Function(_Model):
    """One motion error over its axis' covered range: terms, samples, and what it lacks."""

    name: str  # ISO 230-1: EXX, EYX …
    axis: str
    kind: Literal["positioning", "straightness", "angular"]
    unit: Literal["um", "urad"]
    terms: list[Term]
    x_mm: list[float]  # controller positions of the samples
    value: list[float]
    u: list[float]  # standard uncertainty of each sample
    absorbed: dict[str, str] = {}  # term (EYX_P1) → what holds it instead


class AxisBasis(_Model):
    axis: str
    range_mm: list[float]  # covered controller range [lo, hi]
    degree: int  # the highest degree of this axis' terms (0: none)
    sign: int  # model joint value = sign · controller value


class Basis(_Model):
    kind: Literal["legendre"] = "legendre"
    argument: str
    axes: list[AxisBasis]


class Parameters(_Model):
    names: list[str]  # links (ISO), then map terms (EYX_P2)
    values: list[float]  # mm / rad
    covariance: list[list[float]]
    units: str = "mm for translations and map terms of EX/EY/EZ, rad for rotations"


class Observability(_Model):
    scale_observable: bool
    unobservable: dict[str, str]  # direction or term → what absorbs it
    kept_terms: list[str]
    note: str


class OrderChoice(_Model):
    method: str
    max_degree: int
    degrees: dict[str, int]
    best: list[dict[str, Any]]  # the best-scoring combinations: degrees, held-out RMS


class Fit(_Model):
    residual_rms_um: float
    sigma_um: list[float]
    sigma_from: str
    sigma_dof: float | None  # None: σ given (infinite dof)
    iterations: int
    converged: bool
    condition_number: float | None
    prior: dict[str, Any]
    visit_scatter: dict[str, list[float | None]] | None  # component → [σ, u(σ), p]; null: NaN
    refit: str


class Placement(_Model):
    name: str
    log: str
    artefact: str
    run_id: str | None
    centres: int
    poses: int
    residual_rms_um: float
    balls_um: dict[str, dict[str, list[float]]]  # ball → {value: [x,y,z], std: [...]}
    covered_mm: dict[str, list[float]]


class Figure(_Model):
    value_um: float
    u_um: float | None
    at_mm: list[float] | None
    status: str | None  # PASS / WARN / FAIL against the limit, None without one
    limit: str | None
    source: str | None = None


class Figures(_Model):
    volumetric_max_um: Figure
    volumetric_rms_um: float
    points: int
    grid: str


class Holdout(_Model):
    log: str
    artefact: str
    centres: int
    rms_before_um: float
    rms_after_um: float
    max_before_um: float
    max_after_um: float
    explained_fraction_rms: float
    method: str


class OperatorStep(_Model):
    placement: str  # the placement the operator moved the artefact to
    prompted_at: float  # Unix time the prompt was shown
    continued_at: float  # Unix time of the Continue
    continued_by: str  # who pressed it (the HMI account, the script's operator)


class JobRecord(_Model):
    """The daemon's map job the map came from (``contracts.map_job``)."""

    name: str
    run_id: str
    file: str
    operator_steps: list[OperatorStep] = []


class LinearMapFile(_Model):
    schema_: Literal["rumba-linear-map/1"]
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)
    created_utc: str
    machine: dict[str, Any]  # name, topology, file, tool_tip_mm
    placements: list[Placement]
    basis: Basis
    functions: list[Function]
    links: dict[str, Value]
    probe_um: dict[str, list[float]]
    parameters: Parameters
    observability: Observability
    order: OrderChoice | None
    fit: Fit
    rigid_convention: str
    figures: Figures
    holdout: Holdout | None = None
    warnings: list[str] = []
    job: JobRecord | None = None  # a map fitted by the daemon's map job: the job and its steps

    def to_json(self) -> dict[str, Any]:
        d = self.model_dump(by_alias=False)
        d = {"schema": d.pop("schema_"), **d}
        return _finite(d)


def _finite(x: Any) -> Any:
    """JSON has no NaN/inf: such a number (a σ with no dof) is written as null."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x


def load_map(path: Path | str) -> LinearMapFile:
    """Read a map file; one ``ConfigError`` line naming the file and key when it is not one."""
    raw = read_bounded(path, ConfigError, MAX_MAP_BYTES, "map file")
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise ConfigError(f"{path}: not a JSON map file: {str(e)[:120]}") from None
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        got = data.get("schema") if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{path}: schema: expected {SCHEMA!r}, got {got!r}")
    data = {"schema_": data.pop("schema"), **data}
    try:
        return LinearMapFile.model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_validation(path, e).replace("schema_", "schema")) from None


def map_model(machine: Machine, doc: LinearMapFile, where: str = "<map>") -> MapModel:
    """The prediction model of a map file on ``machine`` (checked to be the file's)."""
    if doc.machine.get("topology", "").upper() != machine.topology.upper():
        raise ConfigError(f"{where}: machine: the map is of a {doc.machine.get('topology')} "
                          f"machine ({doc.machine.get('name')}), the machine file is "
                          f"{machine.topology} ({machine.name})")
    names = doc.parameters.names
    links = tuple(n for n in names if "_P" not in n)
    terms = []
    for n in names[len(links):]:
        comp, deg = n.split("_P")
        if len(comp) != 3 or comp[2] not in "XYZ" or comp[1] not in "XYZABC" or not deg.isdigit():
            raise ConfigError(f"{where}: parameters.names: {n!r} is not a map term (EYX_P2)")
        terms.append(MapTerm(comp[2], "XYZABC".index(comp[1]), int(deg)))
    bad = [n for n in links if n not in machine.location_error_names()]
    if bad:
        raise ConfigError(f"{where}: parameters.names: {bad} are not location errors of "
                          f"{machine.topology}")
    ranges, box = {}, {}
    for ax in doc.basis.axes:
        lo, hi = ax.range_mm
        s = machine.axes[ax.axis].sign
        box[ax.axis] = (float(lo), float(hi))
        ranges[ax.axis] = (min(lo * s, hi * s), max(lo * s, hi * s))
    values = np.array(doc.parameters.values, float)
    cov = np.array(doc.parameters.covariance, float)
    if values.shape != (len(names),) or cov.shape != (len(names), len(names)):
        raise ConfigError(f"{where}: parameters: {len(names)} names, {values.shape[0]} values "
                          f"and a {cov.shape} covariance do not agree")
    if not (np.all(np.isfinite(values)) and np.all(np.isfinite(cov))):
        raise ConfigError(f"{where}: parameters: values and covariance must be finite")
    try:
        basis = MapBasis(ranges, tuple(terms))
    except (ValueError, KeyError) as e:
        raise ConfigError(f"{where}: basis: {e}") from None
    return MapModel(machine, links, basis, values, cov, box)

"""The typed analysis result (``Analysis`` and its parts) and its JSON form, the file format."""

from __future__ import annotations

import functools
import types
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar, Union, get_args, get_origin, get_type_hints

Vec = tuple[float | None, ...]  # a rounded vector; None where the number was NaN or inf


_OMIT = {"omit_none": True}  # the JSON leaves the field out while None (only some analyses)


class _Json:
    """``to_json``: the fields in declaration order (that order is the file format);
    ``from_json``: the inverse, for what the journal and report files hold."""

    def to_json(self) -> dict[str, Any]:
        return _dump(self)

    @classmethod
    def from_json(cls: type[_T], data: dict[str, Any]) -> _T:
        return _load(cls, data)


_T = TypeVar("_T", bound=_Json)


@dataclass(frozen=True)
class LinkError(_Json):
    """One identified ISO 230-1 location error: µm or µrad (``unit`` "um" / "urad")."""

    value: float
    std: float | None = None
    unit: str = ""
    thesis_name: str = ""


@dataclass(frozen=True)
class Offset(_Json):
    value: Vec = ()  # µm
    std: Vec = ()


@dataclass(frozen=True)
class Setup(_Json):
    """Probe offset in the last tool frame, ball offsets in the last workpiece frame, µm."""

    probe: Offset = Offset()
    balls: dict[str, Offset] = field(default_factory=dict)


@dataclass(frozen=True)
class IndexScatter(_Json):
    """One rotary axis' index repeatability behind the links' u (µrad 1σ per indexation,
    identification/estimate_scatter.py): the run's REML estimate, the machine file's stated
    value (Type B) and which of the two the links' u rests on."""

    axis: str
    estimated_urad: float | None = None
    std_urad: float | None = None
    p_value: float | None = None  # boundary likelihood-ratio test of σ = 0
    stated_urad: float | None = None
    p_stated: float | None = None  # one-sided likelihood-ratio test of σ = stated vs free
    used: str = "estimated"  # "estimated" | "stated"
    # indexations the estimate saw (visits of a pose: repeats and revisits count); absent in
    # analyses written before it was recorded
    visits: int | None = field(default=None, metadata=_OMIT)


@dataclass(frozen=True)
class SphereFrame(_Json):
    """The ball centres fitted in the frame the estimate corrects (identification/
    touch_frame.py): passes of estimate and refit, the largest centre change from the fit in
    controller axes (µm), a note when the fits stayed in controller axes or did not settle."""

    passes: int = 0
    max_shift_um: float | None = None
    note: str = ""


@dataclass(frozen=True)
class Estimation(_Json):
    status: str = ""
    iterations: int = 0
    centres: int = 0
    sigma_um: Vec = ()
    sigma_from: str = ""  # "given" | "residuals"
    sigma_dof: float | None = None  # None when σ is given: infinite degrees of freedom
    fixed_radius: bool = False
    index_scatter: tuple[IndexScatter, ...] | None = field(default=None, metadata=_OMIT)
    # centres from touches only (none from an instrument's centres)
    sphere_frame: SphereFrame | None = field(default=None, metadata=_OMIT)


@dataclass(frozen=True)
class VolumetricPoint(_Json):
    """Measured − predicted centre of one ball at one pose and repeat, controller X Y Z, µm."""

    pose: int
    repeat: int = 0
    b_deg: float = 0.0
    c_deg: float = 0.0
    ball: str = ""
    role: str = "estimate"  # "estimate" | "validate"
    held_out: bool = False
    error_um: Vec | None = None
    error_after_links_um: Vec | None = None


@dataclass(frozen=True)
class VolumetricMax(_Json):
    before_links: float | None = None
    after_links: float | None = None


@dataclass(frozen=True)
class Cluster(_Json):
    """Rigid relocalisation of one pose's balls and what remains (local distortion)."""

    pose: int
    repeat: int = 0
    b_deg: float = 0.0
    c_deg: float = 0.0
    linear_um: Vec | None = None
    angular_urad: Vec | None = None
    local_um: dict[str, Vec] = field(default_factory=dict)
    note: str = ""


@dataclass(frozen=True)
class Distance(_Json):
    pose: int
    balls: tuple[str, ...]
    distance_mm: float | None = None
    deviation_um: float | None = None


@dataclass(frozen=True)
class Health(_Json):
    """Sphere fit of one ball-pose: radius − run median and form residual RMS, µm."""

    pose: int
    repeat: int = 0
    ball: str = ""
    radius_dev_um: float | None = None
    form_rms_um: float | None = None


@dataclass(frozen=True)
class Where(_Json):
    pose: int
    ball: str


@dataclass(frozen=True)
class Revisit(_Json):
    pose: int
    ball: str
    repeats: tuple[int, ...] = ()
    dt_min: float | None = None
    shift_um: Vec = ()
    norm_um: float | None = None


@dataclass(frozen=True)
class Stability(_Json):
    """Ball-centre shifts between visits of one pose during the run (thermal drift …)."""

    convention: str
    max_shift_um: float
    worst: Where
    span_min: float | None = None
    revisits: tuple[Revisit, ...] = ()


@dataclass(frozen=True)
class Scale(_Json):
    value: float | None = None  # µm/m
    std: float | None = None


@dataclass(frozen=True)
class Validation(_Json):
    """Prediction of the held-out poses (thesis annex B §B.5), µm."""

    poses: tuple[int, ...] = ()
    rms_before_um: float | None = None
    rms_after_um: float | None = None
    max_before_um: float | None = None
    max_after_um: float | None = None
    explained_fraction: float | None = None
    explained_fraction_rms: float | None = None


@dataclass(frozen=True)
class DriftAxis(_Json):
    value: float | None = None  # µm over the run
    std: float | None = None


@dataclass(frozen=True)
class Thermal(_Json):
    """A TCP drift during the run (a warming machine; ``identification.drift``):
    fitted with the links when the plan's timing separates it and BIC selects it, or why not.
    ``over_run_um``: the drift at the end of the run relative to its start, controller X Y Z."""

    status: str = ""  # selected | not_separable
    message: str = ""
    shape: str | None = None  # linear | exponential
    span_min: float | None = None
    over_run_um: dict[str, DriftAxis] = field(default_factory=dict)
    tau_min: float | None = None
    tau_std_min: float | None = None
    tau_bounded: str | None = None
    bic_gain: float | None = None
    link_inflation: float | None = None  # largest u(link) with the drift / without
    revisit_residual_um: float | None = None  # largest revisit shift the drift leaves
    inseparable: tuple[str, ...] = ()


@dataclass(frozen=True)
class InstrumentFrame(_Json):
    """Centres given in an instrument's frame: instrument ← machine rigid motion, m = R·q + t,
    estimated with the setup; ``std`` per direction (µm, µrad), None where held (``held``:
    the direction the setup absorbs)."""

    rotation: tuple[Vec, ...] = ()
    rotation_vector_deg: Vec = ()
    translation_mm: Vec = ()
    std: dict[str, float | None] = field(default_factory=dict)
    held: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Outlier(_Json):
    """A ball visit whose touches depart from the run's own statistics (a chip, dirt, a
    coolant drop, a bad trigger; ``identification.outliers``): the touch at fault, by how much
    (µm, + outside the ball: an early switch) and what became of it — ``repaired`` (a re-probe
    of the ball, logged as repeat ``replaced_by_repeat``, is used instead), ``unrepaired``
    (left out of the estimate; the measurement is not trusted) or ``not used`` (a faulty
    re-probe of a clean visit)."""

    pose: int
    ball: str = ""
    repeat: int = 0
    touch: int = 0
    size_um: float | None = None
    score: float | None = None
    stage: str = ""  # "sphere" (radius/form of its own fit) | "centre" (vs model and pose)
    status: str = ""
    replaced_by_repeat: int | None = None


@dataclass(frozen=True)
class OutlierTest(_Json):
    """How the visits were screened: robust scales of the run (µm), thresholds, visits."""

    method: str = ""
    visits: int = 0
    sphere_z: float | None = None
    centre_z: float | None = None
    min_size_um: float | None = None
    radius_scale_um: float | None = None
    form_scale_um: float | None = None
    centre_scale_um: float | None = None
    note: str = ""


@dataclass(frozen=True)
class Analysis(_Json):
    """One analysis (``rumba analyze``, a daemon run, a report): the field order is the JSON
    key order. ``log`` is set by ``rumba analyze``; ``run_id``, ``plan``, ``touches`` and
    ``reference_run`` (the drift reference, None when there was none) by a journaled run."""

    log: str | None = field(default=None, metadata=_OMIT)
    run_id: str | None = field(default=None, metadata=_OMIT)
    machine: str = ""
    plan: str | None = field(default=None, metadata=_OMIT)
    topology: str = ""
    artefact: str = ""
    links: dict[str, LinkError] = field(default_factory=dict)
    setup: Setup | None = field(default=None, metadata=_OMIT)
    residual_rms_um: float | None = None
    condition_number: float | None = None
    unobservable: tuple[str, ...] = ()
    unobservable_absorbed_by: dict[str, str] = field(default_factory=dict)
    estimation: Estimation | None = field(default=None, metadata=_OMIT)
    volumetric: tuple[VolumetricPoint, ...] = ()
    volumetric_max_um: VolumetricMax | None = field(default=None, metadata=_OMIT)
    cluster: tuple[Cluster, ...] = ()
    distances: tuple[Distance, ...] = ()
    health: tuple[Health, ...] = ()
    warnings: tuple[str, ...] = ()
    conventions: dict[str, str] = field(default_factory=dict)
    stability: Stability | None = field(default=None, metadata=_OMIT)
    scale_um_per_m: Scale | None = field(default=None, metadata=_OMIT)
    validation: Validation | None = field(default=None, metadata=_OMIT)
    thermal: Thermal | None = field(default=None, metadata=_OMIT)
    # temperature channels of a journaled run (contracts.temperatures.summarise), per name
    temperatures: dict[str, Any] | None = field(default=None, metadata=_OMIT)
    # centres input (``rumba analyze --centres``): the file's frame, instrument and source
    measured_by: str | None = field(default=None, metadata=_OMIT)
    instrument_frame: InstrumentFrame | None = field(default=None, metadata=_OMIT)
    # the outlier test of the ball visits (absent from analyses stored before it existed)
    outlier_test: OutlierTest | None = field(default=None, metadata=_OMIT)
    outliers: tuple[Outlier, ...] | None = field(default=None, metadata=_OMIT)
    touches: int | None = field(default=None, metadata=_OMIT)
    # a journaled run states its reference, null when it had none: emitted with run_id
    reference_run: str | None = field(default=None, metadata={"with": "run_id"})


def _dump(obj: Any) -> Any:
    if isinstance(obj, _Json):
        out = {}
        for f in fields(obj):  # type: ignore[arg-type]
            v = getattr(obj, f.name)
            if v is None and f.metadata.get("omit_none"):
                continue
            if "with" in f.metadata and getattr(obj, f.metadata["with"]) is None:
                continue
            out[f.name] = _dump(v)
        return out
    if isinstance(obj, dict):
        return {k: _dump(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_dump(v) for v in obj]
    return obj


def _load(tp: Any, data: Any) -> Any:
    if data is None:
        return None
    origin, args = get_origin(tp), get_args(tp)
    if origin in (Union, types.UnionType):
        return _load(next(a for a in args if a is not type(None)), data)
    if isinstance(tp, type) and issubclass(tp, _Json):
        if not isinstance(data, dict):
            raise ValueError(f"analysis JSON: {tp.__name__} must be an object, got {data!r}")
        hints = _hints(tp)
        return tp(**{f.name: _load(hints[f.name], data[f.name])
                     for f in fields(tp) if f.name in data})
    if origin is dict:
        return {k: _load(args[1], v) for k, v in data.items()}
    if origin is tuple:
        return tuple(_load(args[0], v) for v in data)
    return data


@functools.cache
def _hints(tp: type) -> dict[str, Any]:
    return get_type_hints(tp)

"""The map-job file: the placements of one map of the linear axes, each a plan and the artefact
file of where the balls stand, run as one job with an operator prompt between placements
(written by ``rumba plan --map``, run by the daemon, read by ``rumba map --job``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pydantic import Field, field_validator

from contracts.plan_files import Plan, check_touch_count, load_plan
from contracts.setup_files import load_artefact_file
from contracts.setup_types import safe_name
from contracts.yaml_files import ConfigError, StrictModel, read_yaml, validate_file
from identification.model import Artefact

MAX_PLACEMENTS = 8


class PlacementFile(StrictModel):
    name: str  # the placement's name in prompts, the journal and the map (P1, P2 …)
    plan: str  # the plan file, relative to the job file's folder
    artefact: str  # the artefact file of this placement, relative to the job file's folder
    # what the operator is told to do before this placement (shown with the Continue prompt)
    instruction: str | None = Field(None, min_length=3, max_length=300)
    _n = field_validator("name")(safe_name)

    @field_validator("instruction")
    @classmethod
    def _one_line(cls, v: str | None) -> str | None:
        if v is not None and any(ord(c) < 32 for c in v):
            raise ValueError("one line of text, without control characters")
        return v


class MapJobFile(StrictModel):
    name: str
    placements: list[PlacementFile] = Field(min_length=1, max_length=MAX_PLACEMENTS)
    _n = field_validator("name")(safe_name)

    @field_validator("placements")
    @classmethod
    def _unique(cls, v: list[PlacementFile]) -> list[PlacementFile]:
        names = [p.name for p in v]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicated placement names {dup}")
        return v


@dataclass(frozen=True)
class JobPlacement:
    """One placement, loaded: its plan and artefact, with the files they came from."""

    name: str
    plan: Plan
    artefact: Artefact
    plan_file: Path
    artefact_file: Path
    instruction: str | None = None

    def prompt(self, index: int, total: int) -> str:
        """The operator's prompt before this placement (``index`` 0-based)."""
        what = self.instruction or (f"set the balls as artefact file {self.artefact_file.name} "
                                    f"({self.artefact.name}) says")
        return (f"move the artefact to placement {index + 1} of {total} ({self.name}): {what}; "
                "then Continue")


@dataclass(frozen=True)
class MapJob:
    name: str
    placements: tuple[JobPlacement, ...]
    path: Path


def load_map_job(path: Path | str) -> MapJob:
    """A map-job file, each placement's plan and artefact loaded and their touch counts
    checked; a ``ConfigError`` names the file and the key."""
    path = Path(path)
    f = validate_file(MapJobFile, path, read_yaml(path))
    out = []
    for i, p in enumerate(f.placements):
        key = f"{path}: placements.{i}"
        files = {}
        for k in ("plan", "artefact"):
            q = Path(getattr(p, k))
            q = q if q.is_absolute() else path.parent / q
            if not q.is_file():
                raise ConfigError(f"{key}.{k}: file {str(q)!r} not found")
            files[k] = q
        plan = load_plan(files["plan"])
        artefact, _ = load_artefact_file(files["artefact"])
        check_touch_count(plan, artefact, f"{key}.plan")
        out.append(JobPlacement(p.name, plan, artefact, files["plan"], files["artefact"],
                                p.instruction))
    return MapJob(f.name, tuple(out), path)

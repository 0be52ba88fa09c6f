"""The machine files and section builders shared by the controller_kinematics section tests
and the compensation writer tests (tests/test_compensation_section.py, _writers.py)."""

from __future__ import annotations

from pathlib import Path

import yaml

from contracts.controller_kinematics import ControllerKinematics, ControllerKinematicsFile
from contracts.controller_kinematics import controller_kinematics as build
from contracts.setup_files import load_machine

ROOT = Path(__file__).resolve().parents[1]
MACHINES = ROOT / "config" / "machines"
HAL = ROOT / "config" / "linuxcnc" / "rumba_xyzbc.hal"
LCNC = MACHINES / "linuxcnc_xyzbc.yaml"
THESIS = MACHINES / "thesis_wcbxfzyt.yaml"
VERTICAL = MACHINES / "vertical_wcayfxzt.yaml"


def read_doc(path: Path) -> dict:
    """A machine file as its YAML document (to edit before machine_from_dict)."""
    return yaml.safe_load(path.read_text(encoding="utf-8"))


def section_of(path: Path, family: str, params: list[dict]) -> ControllerKinematics:
    """A controller_kinematics section of ``family`` with ``params``, checked against the
    machine of ``path``."""
    machine, _ = load_machine(path)
    sec = ControllerKinematicsFile.model_validate({"family": family, "params": params})
    return build(sec, machine, "m.yaml")


def pivot(name: str, address: str, value: float, axes=("B", "C"), comp="x", **kw) -> dict:
    """A pivot parameter entry of the section."""
    return {"name": name, "kind": "pivot", "axes": list(axes), "component": comp,
            "address": address, "value": value, **kw}


def tilt(name: str, address: str, link: str, value: float = 0.0, **kw) -> dict:
    """An orientation parameter entry of the section."""
    return {"name": name, "kind": "orientation", "component": link, "address": address,
            "value": value, **kw}

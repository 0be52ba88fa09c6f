"""A CNC that warms up (simulators/thermal.py) and the daemon configuration that reads its
temperatures: the truth, the controller's own Z sensor per transport, a machine entry with
temperature channels, the expected sensor reading at a time."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from benchmarks.rigs.daemon_helpers import CONFIG
from benchmarks.rigs.e2e_run import PLAN
from benchmarks.rigs.rig_helpers import ERRORS
from simulators import thermal
from simulators.errors_schema import errors_from_dict
from simulators.truth import TruthModel

WARMUP = {"axes": {"Z": {"amplitude_um": 6.0, "tau_s": 300.0, "rise_c": 8.0},
                   "X": {"amplitude_um": 0.0, "tau_s": 600.0, "rise_c": 3.0}},
          "start_state": 0.0, "ambient_c": 20.5}
# the controller's own sensor of Z, per transport, where the simulator exposes it
SPINDLE = {"opcua": {"address": thermal.OPCUA_PATH.format(axis="Z")},
           "modbus": {"address": f"holding:{thermal.MODBUS_ADDRESS['Z']}",
                      "scale": thermal.MODBUS_SCALE_C},
           # the R parameter the PLC copies the sensor into, read as the control's R node
           "sinumerik": {"address": "/Channel/Parameter/R[u1,"
                                    f"{thermal.SIEMENS_VARIABLE['Z'][1:]}]"}}
DIALECT = {"sinumerik": "siemens"}


def warm_truth() -> TruthModel:
    errors = yaml.safe_load(ERRORS.read_text())
    errors["thermal"] = WARMUP
    truth = TruthModel.from_files(CONFIG / "machines/thesis_wcbxfzyt.yaml",
                                  CONFIG / "artefacts/thesis_4ball.yaml", ERRORS)
    return TruthModel.build(truth.machine, truth.machine_file, truth.artefact,
                            errors_from_dict(errors))


def machine_entry(link: dict[str, Any], channels: list[dict[str, Any]],
                  temp_limits: dict[str, Any]) -> dict[str, Any]:
    return {"name": "mill1", "machine": str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
            "artefact": str(CONFIG / "artefacts/thesis_4ball.yaml"),
            "plan": str(CONFIG / f"plans/{PLAN}.yaml"),
            "dialect": DIALECT.get(link["transport"], "fanuc"), "link": link,
            "touch_timeout_s": 30, "temperatures": channels,
            "tolerances": {"default_rotation_urad": {"warn": 40, "fail": 80},
                           "default_translation_um": {"warn": 150, "fail": 300},
                           "temperatures": temp_limits}}


def write_config(tmp: Path, entry: dict[str, Any]) -> Path:
    doc = {"store": {"path": str(tmp / "journal.sqlite")}, "reports_dir": str(tmp / "reports"),
           "hmi": {"enabled": False}, "machines": [entry]}
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc, allow_unicode=True), encoding="utf-8")
    return path


def sensor(axis: str, t_s: float) -> float:
    w = WARMUP["axes"][axis]
    return thermal.ThermalState({axis: thermal.AxisWarmup(w["amplitude_um"], w["tau_s"],
                                                          w["rise_c"])},
                                ambient_c=WARMUP["ambient_c"]).temperatures_c(t_s)[axis]

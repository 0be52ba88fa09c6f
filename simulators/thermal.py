"""The simulated machine's thermal state during a run: a first-order warm-up per axis.

ISO 230-3 describes the warm-up of a machine tool as the thermal distortion of its structure
following its heat sources with a time constant: here each controller axis X Y Z has a state
s(t) = 1 − (1 − s0)·e^(−t/τ) (0 cold, 1 in its warm equilibrium; s0 when the simulated machine
started, t its machine time since, on across programs: VirtualController.thermal_time_s), the
tool centre point drifts by A·(s(t) − s0) along that axis (so δ(0) = 0 and, from cold,
δ(t) = A·(1 − e^(−t/τ)): the model the estimator and the gap diagnosis fit), and a structure
temperature sensor on that axis reads ambient + rise·s(t) — drift and readings come from the
same state, so they agree. Errors file section ``thermal`` (simulators/errors_schema.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

AXES = "XYZ"

# Where the simulator's front-ends expose the sensor readings (a daemon.yaml
# temperature channel points there): OPC UA Double nodes (°C), Modbus registers (int16, 0.01 °C
# per count, holding and input) on the controller, a transmitter's input registers (int16,
# 0.1 °C per count, simulators/frontends/transmitter.py), LinuxCNC HAL pins (float, °C).
OPCUA_PATH = "/Channel/Temperatures/{axis}"
MODBUS_ADDRESS = {"X": 180, "Y": 181, "Z": 182}
MODBUS_SCALE_C = 0.01
TRANSMITTER_ADDRESS = {"X": 0, "Y": 1, "Z": 2}
TRANSMITTER_SCALE_C = 0.1
HAL_PIN = "rumba-probe.temp-{axis}"  # lower-case axis letter
FANUC_VARIABLE = {"X": "#591", "Y": "#592", "Z": "#593"}  # common variables a DNC program prints
SIEMENS_VARIABLE = {"X": "R91", "Y": "R92", "Z": "R93"}  # R parameters a DNC program prints
HEIDENHAIN_VARIABLE = {"X": "Q91", "Y": "Q92", "Z": "Q93"}  # Q parameters a DNC program prints
PRINTED_VARIABLES = (FANUC_VARIABLE, SIEMENS_VARIABLE, HEIDENHAIN_VARIABLE)


def counts(value_c: float, scale_c: float) -> int:
    """A reading as an int16 register (two's complement) at ``scale_c`` °C per count."""
    return round(value_c / scale_c) & 0xFFFF


@dataclass(frozen=True)
class AxisWarmup:
    """One axis: drift amplitude when fully warm (µm), time constant (s), sensor rise (°C)."""

    amplitude_um: float
    tau_s: float
    rise_c: float = 0.0


@dataclass(frozen=True)
class ThermalState:
    """Warm-up of every axis from the state ``start_state`` at t = 0 (the machine's start, s)."""

    axes: dict[str, AxisWarmup]
    start_state: float = 0.0
    ambient_c: float = 20.0

    @classmethod
    def from_file(cls, spec: Any) -> ThermalState:
        """From the validated errors-file section (``errors_schema.ThermalFile``)."""
        return cls({a: AxisWarmup(w.amplitude_um, w.tau_s, w.rise_c)
                    for a, w in spec.axes.items()}, spec.start_state, spec.ambient_c)

    def state(self, axis: str, t_s: float | np.ndarray) -> np.ndarray:
        """s(t) of ``axis``: 0 cold … 1 warm."""
        w = self.axes[axis]
        t = np.maximum(np.asarray(t_s, float), 0.0)
        return 1.0 - (1.0 - self.start_state) * np.exp(-t / w.tau_s)

    def drift_mm(self, t_s: float) -> np.ndarray:
        """(3,) TCP drift at machine time ``t_s`` (controller X Y Z, mm), zero at t = 0."""
        out = np.zeros(3)
        for a, w in self.axes.items():
            out[AXES.index(a)] = w.amplitude_um * 1e-3 * float(self.state(a, t_s)
                                                               - self.start_state)
        return out

    def temperatures_c(self, t_s: float) -> dict[str, float]:
        """Structure temperature per axis (°C) a sensor on it reads at ``t_s``."""
        return {a: self.ambient_c + w.rise_c * float(self.state(a, t_s))
                for a, w in self.axes.items()}

    def over_run_um(self, t0_s: float, t1_s: float) -> dict[str, float]:
        """Drift between two instants per axis (µm): what the estimator reports."""
        return {a: float((self.drift_mm(t1_s) - self.drift_mm(t0_s))[AXES.index(a)] * 1e3)
                for a in self.axes}

    @staticmethod
    def amplitude_for(over_run_um: float, span_s: float, tau_s: float) -> float:
        """The amplitude A whose warm-up from cold moves ``over_run_um`` in ``span_s``."""
        return over_run_um / -math.expm1(-span_s / tau_s)

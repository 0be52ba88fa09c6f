"""The truth's motion errors of the linear axes: the errors file's ``motion_errors`` (Legendre
series over an interval of each axis, a random smooth draw) turned into the chain's functions.

Each error is e(x) = Σ_k a_k P_k(u) of the controller position x, u = (2x − lo − hi)/(hi − lo)
over the axis' ``range_mm`` (default its travel), continued beyond it as the tangent line
(``identification.linmap.basis.legendre_function``); µm for EXX … EZZ, µrad for EAX … ECZ. They
act in the axis frame just after its motion (``kinematics.ChainState.motion_errors``), so every
consumer of the truth's chain — probe contact, the G-code executor, every front-end on the
virtual controller — sees them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contracts.yaml_files import ConfigError
from identification.kinematics import Machine, MotionErrorFn
from identification.linmap.basis import (
    SmoothDraw,
    component_name,
    component_names,
    is_rotation,
    legendre_function,
    random_smooth,
)
from simulators.errors_schema import MotionErrorsFile

UM, URAD = 1e-3, 1e-6


@dataclass(frozen=True)
class MotionFunction:
    """One true motion error: Legendre coefficients (µm or µrad, P0 first) over [lo, hi],
    controller mm of its axis."""

    name: str
    lo_mm: float
    hi_mm: float
    legendre: tuple[float, ...]

    def __call__(self, x_ctrl_mm: np.ndarray) -> np.ndarray:
        """The error at controller positions, in µm or µrad."""
        return legendre_function(self.legendre, x_ctrl_mm, self.lo_mm, self.hi_mm)


def _interval(machine: Machine, letter: str, given: list[float] | None, where: str
              ) -> tuple[float, float]:
    if given is not None:
        return float(given[0]), float(given[1])
    lo, hi = machine.axes[letter].travel
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi - lo > 1e6:
        raise ConfigError(f"{where}: motion_errors.{letter}: the machine file gives no travel "
                          "for this axis; give range_mm")
    return float(lo), float(hi)


def motion_functions(machine: Machine, spec: MotionErrorsFile | None, where: str
                     ) -> dict[str, MotionFunction]:
    """Every true motion error by ISO name (those given and those drawn, summed)."""
    if spec is None:
        return {}
    out: dict[str, MotionFunction] = {}

    def add(fn: MotionFunction) -> None:
        old = out.get(fn.name)
        if old is not None:
            if (old.lo_mm, old.hi_mm) != (fn.lo_mm, fn.hi_mm):
                raise ConfigError(f"{where}: motion_errors: {fn.name} given over "
                                  f"[{old.lo_mm:g}, {old.hi_mm:g}] and drawn over "
                                  f"[{fn.lo_mm:g}, {fn.hi_mm:g}] mm: give one range_mm")
            n = max(len(old.legendre), len(fn.legendre))
            c = np.zeros(n)
            c[: len(old.legendre)] += old.legendre
            c[: len(fn.legendre)] += fn.legendre
            fn = MotionFunction(fn.name, fn.lo_mm, fn.hi_mm, tuple(float(x) for x in c))
        out[fn.name] = fn

    for letter in "XYZ":
        ax = getattr(spec, letter)
        if ax is None:
            continue
        lo, hi = _interval(machine, letter, ax.range_mm, where)
        for name, f in ax.functions().items():
            add(MotionFunction(name, lo, hi, tuple(float(x) for x in f.legendre)))
    rs = spec.random_smooth
    if rs is not None:
        rng = np.random.default_rng(rs.seed)
        draw = SmoothDraw(rs.amplitude(False), rs.amplitude(True), rs.order)
        for letter in rs.axes:
            given = rs.range_mm.get(letter)
            own = getattr(spec, letter)
            if given is None and own is not None:
                given = own.range_mm
            lo, hi = _interval(machine, letter, given, where)
            for slot in range(6):  # always all six, in order: the draw depends on the seed only
                c = random_smooth(rng, draw, slot)
                add(MotionFunction(component_name(slot, letter), lo, hi,
                                   tuple(float(x) for x in c)))
    return out


def chain_functions(machine: Machine, functions: dict[str, MotionFunction]
                    ) -> dict[str, MotionErrorFn]:
    """The chain's per-axis functions (model joint value mm → (N, 6) mm / rad)."""
    out: dict[str, MotionErrorFn] = {}
    for letter in "XYZ":
        mine = [(slot, functions[n]) for slot, n in enumerate(component_names(letter))
                if n in functions]
        if not mine:
            continue
        sign = machine.axes[letter].sign

        def fn(q: np.ndarray, mine: list = mine, sign: int = sign) -> np.ndarray:
            q = np.asarray(q, float).reshape(-1)
            x = q * sign  # model joint value → controller position (sign is ±1)
            e = np.zeros((q.shape[0], 6))
            for slot, f in mine:
                e[:, slot] = f(x) * (URAD if is_rotation(slot) else UM)
            return e

        out[letter] = fn
    return out

"""SINUMERIK tool-carrier addresses: which ``$TC_CARR`` vector component a value is, and tilts.

A carrier (``$TC_CARR<n>[<k>]`` of carrier ``k``) keeps the offset vectors l1 (``n`` 1-3), l2
(4-6), l3 (15-17), l4 (18-20) and the rotary-axis vectors v1 (7-9), v2 (10-12), x y z in that
order. A small tilt θ of a rotary axis about the unit vector t moves its axis vector v to
v + θ·(t × v) (first order): on a principal axis one component, on an inclined one (
the nutating B ``[0, 0.7071, 0.7071]``, whose tilts are about R0·x, R0·z of its own frame,
``identification.kinematics.axis_frame``) two or three.
"""

from __future__ import annotations

import re
from typing import Protocol

import numpy as np

from identification.kinematics import Machine, axis_frame


class ParamFile(Protocol):
    """What these checks read of a ``controller_kinematics.ParamFile`` entry."""

    kind: str
    component: str
    address: str
    vector: list[float] | None
    also: list[str] | None

CARR = re.compile(r"\A\$TC_CARR([1-9][0-9]?)\[([1-9][0-9]{0,2})\]\Z")
_ORIENTATION = re.compile(r"\AE([ABC])0([ABCXYZ])\Z")
_COMPONENTS = "xyz"
# first index n of the x component → vector name
CARR_VECTORS = {1: "l1", 4: "l2", 15: "l3", 18: "l4"}
CARR_AXES = {7: "v1", 10: "v2"}
_MOVED = 1e-9  # a component a tilt moves by less than this per rad stays (first order)


def _vector_of(address: str) -> tuple[int, int, int] | None:
    """(n, first n of its vector, carrier k) of a ``$TC_CARR`` vector component, else None."""
    m = CARR.fullmatch(address)
    if m is None:
        return None
    n = int(m.group(1))
    first = next((f for f in (*CARR_VECTORS, *CARR_AXES) if f <= n < f + 3), None)
    return None if first is None else (n, first, int(m.group(2)))


def carr_component(address: str) -> int:
    """Index (0 x, 1 y, 2 z) of the vector component a ``$TC_CARR<n>[<k>]`` address holds."""
    v = _vector_of(address)
    if v is None:
        raise ValueError(f"{address!r} is not a tool-carrier vector component $TC_CARR<n>[<k>]")
    return v[0] - v[1]


def check_carr(p: ParamFile, address: str, what: str) -> None:
    """Refuse an address that is not a vector component of the kind ``p`` writes."""
    m = CARR.fullmatch(address)
    if not m:
        raise ValueError(f"{what}: {address!r} is not a tool-carrier value $TC_CARR<n>[<k>]")
    n = int(m.group(1))
    table = CARR_VECTORS if p.kind == "pivot" else CARR_AXES
    first = next((f for f in table if f <= n < f + 3), None)
    if first is None:
        kinds = "offset vectors l1-l4 (n 1-6, 15-20)" if p.kind == "pivot" else \
            "rotary-axis vectors v1, v2 (n 7-12)"
        raise ValueError(f"{what}: $TC_CARR{n} is not one of the {kinds} a {p.kind} uses")
    comp = _COMPONENTS[n - first]
    if p.kind == "pivot" and comp != p.component:
        raise ValueError(f"{what}: $TC_CARR{n} is the {comp} component of {table[first]}, "
                         f"not {p.component}")


def tilt_components(link: str, vector: tuple[float, ...] | list[float],
                    tilt_axis: tuple[float, ...] | None = None) -> list[tuple[int, float]]:
    """(component index, factor) of every component of the axis vector ``vector`` that a small
    rotation θ about ``tilt_axis`` (default: the principal axis of ``link``'s rotation, e.g. x
    for EA0C) moves: v + θ·(t × v), that component changes by ``factor``·θ (rad)."""
    m = _ORIENTATION.fullmatch(link)
    if m is None:
        raise ValueError(f"{link!r} is not an orientation error name")
    t = np.zeros(3)
    if tilt_axis is None:
        t["ABC".index(m.group(1))] = 1.0
    else:
        t[:] = tilt_axis
    cross = np.cross(t, np.asarray(vector, float))
    return [(j, float(cross[j])) for j in range(3) if abs(cross[j]) > _MOVED]


def siemens_tilt(link: str, vector: tuple[float, ...] | list[float]) -> tuple[int, float]:
    """(component index, factor) of a principal axis vector's one component a tilt of ``link``
    moves (``tilt_components`` on a principal vector)."""
    moved = tilt_components(link, vector)
    if len(moved) != 1 or abs(moved[0][1]) < 0.5:
        raise ValueError(f"{link} does not tilt one component of the axis vector {list(vector)}")
    return moved[0]


def check_vector(p: ParamFile, key: str, machine: Machine, axis: str
                 ) -> tuple[float, float, float]:
    """A Siemens orientation's axis vector and addresses against the machine's axis: the
    vector a unit vector along the axis (either sense: a table axis' is reversed), ``address``
    and ``also`` exactly the components of one rotary-axis vector the tilt moves. Returns the
    tilt's rotation axis in the machine frame (R0·e_i of an inclined axis)."""
    assert p.vector is not None
    v = np.asarray(p.vector, float)
    d = np.asarray(machine.axes[axis].direction, float)
    d = d / np.linalg.norm(d)
    if abs(float(np.linalg.norm(v)) - 1.0) > 1e-6:
        raise ValueError(f"{key}.vector: expected a unit vector, got {list(p.vector)} "
                         f"(length {np.linalg.norm(v):.9f})")
    if abs(abs(float(v @ d)) - 1.0) > 1e-9:
        raise ValueError(f"{key}.vector: {list(p.vector)} is not along axis {axis} "
                         f"({[float(x) for x in d]})")
    r0 = axis_frame(machine.axes[axis])
    e = np.zeros(3)
    e["ABC".index(p.component[1])] = 1.0
    t = e if r0 is None else r0 @ e
    moved = {j for j, _ in tilt_components(p.component, p.vector, tuple(t))}
    names = ", ".join(_COMPONENTS[k] for k in sorted(moved))
    given: dict[int, str] = {}
    block = None
    for what, address in ((f"{key}.address", p.address),
                          *((f"{key}.also.{i}", a) for i, a in enumerate(p.also or []))):
        check_carr(p, address, what)
        n, first, k = _vector_of(address)  # type: ignore[misc]  # check_carr passed
        if block is not None and (first, k) != block:
            raise ValueError(f"{what}: {address} is not a component of the axis vector "
                             f"{p.address} belongs to")
        block = (first, k)
        j = n - first
        if j in given:
            raise ValueError(f"{what}: {address} names the {_COMPONENTS[j]} component twice")
        if j not in moved:
            raise ValueError(f"{what}: {p.component} tilts the {names} component of the axis "
                             f"vector {list(p.vector)}, {address} is its {_COMPONENTS[j]} "
                             "component")
        given[j] = address
    if set(given) != moved:
        missing = ", ".join(_COMPONENTS[k] for k in sorted(moved - set(given)))
        raise ValueError(f"{key}.also: {p.component} also moves the {missing} component of the "
                         f"axis vector {list(p.vector)} (an inclined axis): name its address")
    return float(t[0]), float(t[1]), float(t[2])


__all__ = ["CARR", "CARR_AXES", "CARR_VECTORS", "carr_component", "check_carr", "check_vector",
           "siemens_tilt", "tilt_components"]

"""The last map of the linear axes on the OPC UA results server: per machine a ``Map`` object
(rumba's namespace) beside ``Check``, whose variables (``contracts.opcua_space.MAP_VARIABLES``)
are the last journaled map result's figures (daemon/store/map_results.py), each length in µm
with its EngineeringUnits (EUInformation, UNECE 4H) as the results' content carries them.

Updated when the server starts, when a run ends (the daemon's map job is a run), and by a poll
of the source (a map journaled by ``rumba map --store`` beside the daemon, or by another daemon
into the fleet store): one indexed read per machine and interval. A machine without a map has
``LastMapId`` "" and NaN figures."""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import math
from typing import Any

from asyncua import ua

from contracts.opcua_space import MAP_VARIABLES
from daemon.opcua.results import eu_information, evaluation
from daemon.store.map_results import MapResult

log = logging.getLogger("rumba.opcua")
NO_TIME = dt.datetime(1601, 1, 1, tzinfo=dt.UTC)
POLL_S = 10.0
_VT = {"Double": ua.VariantType.Double, "Int32": ua.VariantType.Int32,
       "UInt32": ua.VariantType.UInt32, "String": ua.VariantType.String,
       "String[]": ua.VariantType.String, "DateTime": ua.VariantType.DateTime}
_EMPTY = {"Double": math.nan, "Int32": 0, "UInt32": 0, "String": "", "String[]": [],
          "DateTime": NO_TIME}
KINDS = {v.name: v.kind for v in MAP_VARIABLES}


class MapNodes:
    """One machine's ``Map`` object and what it last showed."""

    def __init__(self, machine: str) -> None:
        self.machine = machine
        self.vars: dict[str, Any] = {}
        self.shown: tuple[str, float] | None = None  # (id, created_at) on the nodes

    async def add(self, parent: Any, idx: int) -> None:
        """The ``Map`` object and its variables (contracts/opcua_space.py), empty."""
        name = self.machine
        obj = await parent.add_object(ua.NodeId(f"{name}.Map", idx), ua.QualifiedName("Map", idx))
        eu = eu_information("um")
        for v in MAP_VARIABLES:
            node = await obj.add_variable(ua.NodeId(f"{name}.Map.{v.name}", idx),
                                          ua.QualifiedName(v.name, idx),
                                          ua.Variant(_EMPTY[v.kind], _VT[v.kind]))
            if v.unit:  # OPC 10000-8 AnalogItem's property: the unit a client shows
                await node.add_property(ua.NodeId(f"{name}.Map.{v.name}.EngineeringUnits",
                                                  idx), ua.QualifiedName("EngineeringUnits", 0),
                                        ua.Variant(eu, ua.VariantType.ExtensionObject))
            self.vars[v.name] = node

    async def show(self, m: MapResult | None) -> None:
        """Write ``m``'s figures (nothing when it is what the nodes already show)."""
        key = None if m is None else (m.id, m.created_at)
        if key == self.shown or m is None:
            return
        f = m.figures
        pos = f.get("positioning_max_um", {})
        covered = ", ".join(f"{a} {lo:g}..{hi:g}" for a, (lo, hi) in
                            f.get("covered_mm", {}).items())
        values: dict[str, Any] = {
            "LastMapId": m.id, "LastMapTime": dt.datetime.fromtimestamp(m.created_at, dt.UTC),
            "LastMapVerdict": m.verdict or "not judged",
            "LastMapEvaluation": evaluation(m.verdict, [{"status": m.verdict,
                                                         "limit": m.limit_text}]),
            "Limit": m.limit_text, "VolumetricMax_um": m.volumetric_max_um,
            "VolumetricMaxU_um": m.volumetric_max_u_um,
            "VolumetricRms_um": m.volumetric_rms_um, "Placements": m.placements,
            "CoveredRange_mm": covered, "NotObservable": list(f.get("unobservable", {})),
            **{f"PositioningMax{n}_um": (pos.get(n) or {}).get("value_um")
               for n in ("EXX", "EYY", "EZZ")}}
        for name, value in values.items():
            kind = KINDS[name]
            if kind == "Double":
                value = math.nan if value is None else float(value)
            await self.vars[name].write_value(ua.Variant(value, _VT[kind]))
        self.shown = key


async def refresh(source: Any, nodes: MapNodes) -> None:
    """Show the machine's last map result (the source's ``last_map``)."""
    await nodes.show(await source.last_map(nodes.machine))


async def follow(source: Any, machines: list[MapNodes], interval_s: float | None = None
                 ) -> None:
    """Poll the source for new map results every ``interval_s`` (default ``POLL_S``),
    forever (a task of the server)."""
    while True:
        await asyncio.sleep(POLL_S if interval_s is None else interval_s)
        for nodes in machines:
            try:
                await refresh(source, nodes)
            except asyncio.CancelledError:
                raise
            except Exception as e:  # the store restarting: try again next round
                log.warning("%s: OPC UA map: reading the store failed: %s", nodes.machine, e)

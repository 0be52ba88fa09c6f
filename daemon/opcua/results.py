"""A journaled run as an OPC 40001-101 result: ResultMetaData (result id = run id, creation
time, ResultState, ResultEvaluation), ResultContent (the link errors and volumetric indicators
with their units and standard uncertainties) and the filter of GetResultIdListFiltered.

ResultEvaluation from the verdict (decision rule of daemon/analysis/judge.py): PASS → OK;
FAIL → NotOK; WARN → NotDecidable when a check warned because |value| + k·u reaches its fail
limit ("conformance not proven": the uncertainty straddles the limit, ISO 14253-1), else OK
(inside the fail limits, over a warning limit only); ERROR (measurement not trusted) and runs
without a verdict → Undefined."""

from __future__ import annotations

import asyncio
import datetime as dt
import math
from dataclasses import dataclass
from typing import Any

from asyncua import ua

from daemon.analysis.judge import volumetric_max_um
from daemon.analysis.result import Analysis
from daemon.opcua.filters import FilterError, compile_filter  # noqa: F401 (filtered_ids raises it)
from daemon.opcua.source import ResultSource
from daemon.store.journal import RunRow

NOT_PROVEN = "conformance not proven"
STATE = {"DONE": 1, "IMPORTED": 1, "ABORTED": 3, "INTERRUPTED": 3, "FAILED": 4}
"""ResultState (OPC 40001-101): 1 Completed, 2 Processing, 3 Aborted, 4 Failed."""
UNECE = "http://www.opcfoundation.org/UA/units/un/cefact"
EU = {"um": ("4H", "µm", "micrometre"), "urad": ("B97", "µrad", "microradian")}
ERR_UNKNOWN_ID = -1  # application-specific (negative) error codes of the methods
ERR_NO_RESULT = -2
ERR_FILTER = -3
MAX_RUNS = 100_000
"""Runs of one machine a filter looks through, newest first (years of daily checks)."""


def evaluation(verdict: str | None, checks: list[dict[str, Any]] | None) -> int:
    """ResultEvaluationEnum value: 0 Undefined, 1 OK, 2 NotOK, 3 NotDecidable."""
    if verdict == "PASS":
        return 1
    if verdict == "FAIL":
        return 2
    if verdict == "WARN":
        undecided = any(c.get("status") == "WARN" and NOT_PROVEN in str(c.get("limit", ""))
                        for c in checks or [])
        return 3 if undecided else 1
    return 0


def eu_information(unit: str) -> ua.EUInformation:
    """OPC 10000-8 EUInformation of a UNECE unit: UnitId from the common code's characters."""
    code, short, name = EU[unit]
    unit_id = 0
    for ch in code:
        unit_id = (unit_id << 8) | ord(ch)
    return ua.EUInformation(NamespaceUri=UNECE, UnitId=unit_id,
                            DisplayName=ua.LocalizedText(short, "en"),
                            Description=ua.LocalizedText(name, "en"))


@dataclass(frozen=True)
class Quantity:
    name: str
    value: float
    std: float | None
    unit: str  # "um" | "urad"


def quantities(a: Analysis) -> list[Quantity]:
    out = [Quantity(n, float(e.value), e.std, e.unit or ("urad" if n[1:2] in "ABC" else "um"))
           for n, e in sorted(a.links.items())]
    for name, after in (("VD_MAX", False), ("VD_MAX_RESIDUAL", True)):
        v = volumetric_max_um(a, after_links=after)
        if v is not None and math.isfinite(v):
            out.append(Quantity(name, v, None, "um"))
    return out


def content(a: Analysis | None, ns: int) -> list[ua.Variant]:
    """ResultContent: per quantity a KeyValuePair (Key = its name in rumba's namespace) whose
    value is [value, standard uncertainty (NaN when none), EUInformation]."""
    if a is None:
        return []
    out = []
    for q in quantities(a):
        value = ua.Variant([ua.Variant(q.value, ua.VariantType.Double),
                            ua.Variant(math.nan if q.std is None else float(q.std),
                                       ua.VariantType.Double),
                            ua.Variant(eu_information(q.unit), ua.VariantType.ExtensionObject)],
                           ua.VariantType.Variant)
        out.append(ua.Variant(ua.KeyValuePair(Key=ua.QualifiedName(q.name, ns), Value=value),
                              ua.VariantType.ExtensionObject))
    return out


def _utc(t: float | None) -> dt.datetime | None:
    return None if t is None else dt.datetime.fromtimestamp(t, dt.UTC)


def metadata(run: RunRow, checks: list[dict[str, Any]] | None, machine_uri: str,
             has_file: bool) -> Any:
    """ResultMetaDataType of one run (the optional fields rumba knows)."""
    times = ua.ProcessingTimesDataType(StartTime=_utc(run.started_at),
                                       EndTime=_utc(run.ended_at or run.started_at))
    ev = evaluation(run.verdict, checks)
    return ua.ResultMetaDataType(
        ResultId=run.id, HasTransferableDataOnFile=has_file, IsPartial=False,
        IsSimulated=False, ResultState=STATE.get(run.state, 2), PartId=run.artefact or None,
        ProductId=machine_uri, InternalRecipeId=run.plan or None, JobId=run.id,
        CreationTime=_utc(run.ended_at or run.started_at), ProcessingTimes=times,
        ResultEvaluation=ua.ResultEvaluationEnum(ev),
        ResultEvaluationDetails=ua.LocalizedText(run.summary or run.reason or run.state, "en"),
        FileFormat=["application/pdf", "text/html"] if has_file else None)


async def result(source: ResultSource, run: RunRow, machine_uri: str, ns: int) -> Any:
    """ResultDataType: metadata and content of ``run``."""
    v = await source.verdict(run.id)
    has_file = await source.report(run.id) is not None
    return ua.ResultDataType(ResultMetaData=metadata(run, v["checks"] if v else None,
                                                     machine_uri, has_file),
                             ResultContent=content(await source.analysis(run.id), ns))


# ------------------------------------------------------------------ GetResultIdListFiltered
def row_of(run: RunRow, checks: list[dict[str, Any]] | None) -> dict[str, Any]:
    return {"ResultId": run.id, "ResultState": STATE.get(run.state, 2),
            "ResultEvaluation": evaluation(run.verdict, checks),
            "CreationTime": _utc(run.ended_at or run.started_at), "PartId": run.artefact,
            "JobId": run.id}


async def filtered_ids(source: ResultSource, machine: str, flt: Any,
                       max_results: int) -> list[str]:
    """Result ids of ``machine`` (newest first) matching ``flt`` (an empty ContentFilter
    matches all); at most ``max_results`` (0: no limit). The filter is checked whole first
    (``FilterError``); the runs are read on the loop (the journal's verdicts only when the
    filter reads ResultEvaluation), the filter is evaluated on a worker thread."""
    compiled = compile_filter(flt)
    runs = await source.runs(machine, MAX_RUNS)
    if not compiled.elements:
        ids = [r.id for r in runs]
        return ids[:max_results] if max_results else ids
    rows = []
    for k, run in enumerate(runs):
        checks = None
        if "ResultEvaluation" in compiled.fields and run.verdict:
            v = await source.verdict(run.id)
            checks = v["checks"] if v else None
        rows.append(row_of(run, checks))
        if k % 200 == 199:
            await asyncio.sleep(0)  # a journal read does not yield by itself

    def match() -> list[str]:
        out = []
        for row in rows:
            if compiled.matches(row):
                out.append(row["ResultId"])
                if max_results and len(out) >= max_results:
                    break
        return out

    return await asyncio.to_thread(match)

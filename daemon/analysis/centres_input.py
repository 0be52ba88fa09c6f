"""Measured centres (a centres CSV or an instrument's file) → the analysis `rumba analyze` and
`rumba gap` run on them: read or import, one run, the balls measured, the uncertainties, the
frame; then the estimate (machine or instrument frame) or, at one indexation, what one
indexation supports (``daemon.analysis.centres_shape``)."""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from contracts.centres_file import CentreRow, CentresFile, write_centres
from contracts.importers import import_centres
from contracts.probing_log import LogRow, ProbeLogError, read_log
from daemon.analysis.centres_shape import OneIndexation, one_indexation
from daemon.analysis.identify import AnalysisError, analyse_centres
from daemon.analysis.result import Analysis, InstrumentFrame
from daemon.analysis.touch_centres import CentreData, columns, one_run_balls, rows_to_centres
from identification.frame import FRAME_NAMES, FrameFit, estimate_weighted
from identification.gap.centres_input import centre_groups, centre_touches, merge
from identification.gap.diagnose import Options, diagnose_groups
from identification.kinematics import Machine
from identification.model import Artefact, Centres

SIGMA_SOURCES = ("--repeatability-um", "u_um column", "repeatability_um key", "residuals")


@dataclass
class CentresInput:
    """A centres file ready for the analyses: the data, the artefact restricted to the balls
    measured, the centre uncertainties and where they come from, the frame."""

    file: CentresFile
    data: CentreData
    artefact: Artefact
    sigma_um: np.ndarray | None  # (3,) per axis or (K,) per centre, stated; None: a posteriori
    sigma_from: str  # one of SIGMA_SOURCES
    frame: str  # "machine" | "instrument"
    warnings: list[str]

    @property
    def indexations(self) -> np.ndarray:
        """The distinct (b, c) read at the centres (rounded to 1e-6°)."""
        c = self.data.centres
        return np.unique(np.round(np.c_[c.b_deg, c.c_deg], 6), axis=0)

    def described(self) -> str:
        f = self.file
        parts = [f"frame {self.frame}"]
        if f.instrument:
            parts.append(f"instrument: {f.instrument}")
        if f.source:
            parts.append(f"source: {f.source}")
        return "; ".join(parts)


def load(path: Path | str, fmt: str, machine: Machine, artefact: Artefact, *,
         ball: str | None = None, plan_poses: Sequence[tuple[float, float]] | None = None,
         frame: str | None = None, repeatability_um: Sequence[float] | None = None
         ) -> CentresInput:
    """Read ``path`` (``fmt``: auto | csv | kinopt | dmis) for ``machine`` and ``artefact``.
    ``frame`` overrides the file's; ``repeatability_um`` (x, y, z) overrides its uncertainties.
    Reader warnings (seq gaps) are kept in ``warnings``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cf = import_centres(path, fmt, balls=artefact.ids, rotary=machine.rotary_axes,
                            ball=ball, poses=plan_poses)
    notes = [str(w.message) for w in caught]
    col = {k: cf.column(k) for k in ("run_id", "ball")}
    one_run_balls(col, artefact, str(path), "analyse")  # one run, known balls: else an error
    present = set(col["ball"].tolist())
    used = artefact
    if present != set(artefact.ids):
        used = replace(artefact, balls=tuple(b for b in artefact.balls if b.id in present),
                       distances=tuple(d for d in artefact.distances
                                       if {d.ball_a, d.ball_b} <= present))
        notes.append(f"{path}: balls {sorted(set(artefact.ids) - present)} of artefact "
                     f"{artefact.name} are not in the file: left out of the analysis")
    index = {b: i for i, b in enumerate(used.ids)}
    ball_ix = np.array([index[b] for b in col["ball"]], int)
    rep, pose = cf.column("repeat"), cf.column("pose")
    order = np.lexsort((ball_ix, pose, rep))  # as the touch path: repeat, pose, ball
    xyz = np.stack([cf.column(k) for k in ("x_mm", "y_mm", "z_mm")], axis=1)[order]
    centres = Centres(pose[order].astype(int), ball_ix[order], cf.column("b_deg")[order],
                      cf.column("c_deg")[order], xyz, cf.column("t_s")[order])
    data = CentreData(centres, rep[order].astype(int), [], [])
    if repeatability_um is not None:
        sigma, source = np.asarray(repeatability_um, float), SIGMA_SOURCES[0]
    elif cf.u_stated:
        sigma, source = cf.column("u_um")[order], SIGMA_SOURCES[1]
    elif cf.repeatability_um is not None:
        sigma, source = np.asarray(cf.repeatability_um, float), SIGMA_SOURCES[2]
    else:
        sigma, source = None, SIGMA_SOURCES[3]
    return CentresInput(cf, data, used, sigma, source, frame or cf.frame, notes)


def _frame_json(fit: FrameFit) -> InstrumentFrame:
    std = {n: (None if not f else round(float(s), 4))
           for n, f, s in zip(FRAME_NAMES, fit.free, fit.std, strict=True)}
    return InstrumentFrame(
        rotation=tuple(tuple(round(float(x), 12) for x in row) for row in fit.rotation),
        rotation_vector_deg=tuple(round(float(x), 9) for x in fit.rotation_vector_deg()),
        translation_mm=tuple(round(float(x), 6) for x in fit.translation_mm),
        std=std, held=dict(fit.absorbed_by))


def analyse(machine: Machine, inp: CentresInput, *, validate_poses: Sequence[int] = (),
            links: Sequence[str] | None = None, source: str = "",
            rotary_repeatability_urad: Mapping[str, float] | None = None) -> Analysis:
    """The analysis of ``rumba analyze`` on centres (at least two indexations).

    Machine frame with one σ per axis (stated or a posteriori): exactly the touch path's
    estimate. A σ per centre or an instrument frame: ``identification.frame`` (weighted,
    with the six frame parameters), then the same analyses in controller X Y Z."""
    per_centre = inp.sigma_um is not None and inp.sigma_um.ndim == 1 and \
        inp.sigma_um.shape[0] == len(inp.data.centres) and inp.sigma_from == SIGMA_SOURCES[1]
    frame = inp.frame == "instrument"
    fit: list[FrameFit] = []
    estimator = None
    if per_centre or frame:
        held = np.isin(inp.data.centres.pose, list(validate_poses))

        def estimator(est_c: Centres):
            sigma = inp.sigma_um[~held] if per_centre else inp.sigma_um
            est, f = estimate_weighted(machine, inp.artefact, est_c, links, frame=frame,
                                       sigma_um=sigma)
            if f is not None:
                fit.append(f)
            return est, (f.to_machine if f is not None else None)

    sigma = None if per_centre else inp.sigma_um
    out = analyse_centres(machine, inp.artefact, inp.data, validate_poses=validate_poses,
                          links=links, repeatability_um=sigma, source=source,
                          estimator=estimator,
                          rotary_repeatability_urad=rotary_repeatability_urad)
    extra = {"measured_by": inp.described()}
    if fit:
        extra["instrument_frame"] = _frame_json(fit[0])
    if inp.sigma_from != SIGMA_SOURCES[3] and out.estimation is not None:
        extra["estimation"] = replace(out.estimation, sigma_from=f"given ({inp.sigma_from})")
    return replace(out, warnings=(*inp.warnings, *out.warnings), **extra)


def run(path: Path | str, machine: Machine, artefact: Artefact, *, fmt: str = "auto",
        frame: str | None = None, ball: str | None = None,
        plan_poses: Sequence[tuple[float, float]] | None = None,
        validate_poses: Sequence[int] = (), links: Sequence[str] | None = None,
        repeatability_um: Sequence[float] | None = None,
        rotary_repeatability_urad: Mapping[str, float] | None = None
        ) -> Analysis | OneIndexation:
    """`rumba analyze --centres`: the estimate, or at one indexation what one indexation
    supports (``daemon.analysis.centres_shape.OneIndexation``). Errors are ``ConfigError``s."""
    inp = load(path, fmt, machine, artefact, ball=ball, plan_poses=plan_poses, frame=frame,
               repeatability_um=repeatability_um)
    if len(inp.indexations) < 2:
        if validate_poses:
            raise AnalysisError(f"{path}: one indexation only: nothing to hold out for "
                                "validation")
        return one_indexation(machine, inp, str(path))
    out = analyse(machine, inp, validate_poses=validate_poses, links=links, source=str(path),
                  rotary_repeatability_urad=rotary_repeatability_urad)
    return replace(out, log=str(path))


def centre_rows(rows: Sequence[LogRow], data: CentreData, artefact: Artefact) -> list[CentreRow]:
    """The centres a probing log's touches gave (``touch_centres.rows_to_centres``) as rows of
    the centres CSV: commanded b/c from the log, read b/c and time the touches' means, ``seq``
    in measuring order, no stated uncertainty (the sphere fits' are not a centre's)."""
    col = columns(rows, ("run_id", "pose", "b_cmd_deg", "c_cmd_deg", "t_s"))
    cmd = {int(p): (float(b), float(c)) for p, b, c in
           zip(col["pose"], col["b_cmd_deg"], col["c_cmd_deg"], strict=True)}
    run = str(col["run_id"][0])
    c = data.centres
    order = np.argsort(c.t_s, kind="stable")
    return [CentreRow(run, i + 1, float(c.t_s[k]), int(data.repeat[k]), int(c.pose[k]),
                      *cmd[int(c.pose[k])], float(c.b_deg[k]), float(c.c_deg[k]),
                      artefact.ids[int(c.ball[k])], *(float(x) for x in c.xyz_mm[k]))
            for i, k in enumerate(order)]


def export_log_centres(log: Path | str, artefact: Artefact, stylus_radius_mm: float,
                       fixed_radius: bool, out: Path | str, data: CentreData | None = None
                       ) -> int:
    """`rumba analyze --log L --write-centres OUT`: the log's centres as a centres CSV (the
    same sphere fits as the analysis: ``data``, its centres in the estimate's frame; None:
    fitted here in controller axes); returns the number of centres written."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the analysis reports the reader's warnings
        rows = read_log(log, artefact)
        if data is None:
            data = rows_to_centres(rows, artefact, stylus_radius_mm, fixed_radius,
                                   source=str(log))
    out_rows = centre_rows(rows, data, artefact)
    try:
        write_centres(out, out_rows, source=f"sphere fits of the touches of {Path(log).name}",
                      instrument="touch probe (rumba probing log)")
    except OSError as e:
        raise ProbeLogError(f"--write-centres {out}: cannot write: {e.strerror}") from None
    return len(out_rows)


def _sigma3(inp: CentresInput) -> np.ndarray | None:
    """The stated centre uncertainties as (K, 3), None when the file states none."""
    if inp.sigma_um is None:
        return None
    k = len(inp.data.centres)
    s = np.asarray(inp.sigma_um, float)
    return np.repeat(s[:, None], 3, axis=1) if inp.sigma_from == SIGMA_SOURCES[1] else \
        np.broadcast_to(s, (k, 3)).copy()


def diagnose_gap(machine: Machine, train: CentresInput, holdout: CentresInput | None,
                 options: Options) -> dict:
    """`rumba gap --centres`: the gap diagnosis on centres (three observations per centre, the
    floor from their stated uncertainties or repeats; ``identification.gap.centres_input``)."""
    for inp in (train, holdout):
        if inp is not None and inp.frame != "machine":
            raise AnalysisError(f"{inp.file.name}: centres in an instrument frame: the gap twin "
                                "works in the machine's axes (rumba analyze estimates the frame)")
    a = train.artefact
    hold = None
    sig = [_sigma3(train)]
    if holdout is not None:
        index = {b: i for i, b in enumerate(a.ids)}
        ids = [holdout.artefact.ids[int(b)] for b in holdout.data.centres.ball]
        missing = sorted(set(ids) - set(index))
        if missing:
            raise AnalysisError(f"{holdout.file.name}: balls {missing} are not in "
                                f"{train.file.name}: the twin has no setup for them")
        hc = replace(holdout.data.centres, ball=np.array([index[b] for b in ids], int))
        hold = (hc, holdout.data.repeat)
        sig.append(_sigma3(holdout))
    if any(s is None for s in sig) and not all(s is None for s in sig):
        raise AnalysisError("state the centre uncertainty in both files or in neither (the "
                            "floor must come from one source)")
    sigma = None if sig[0] is None else np.vstack(sig)
    c, rep, is_ho = merge((train.data.centres, train.data.repeat), hold)
    try:
        groups, is_ho = centre_groups(c, rep, sigma, is_ho)
    except ValueError as e:
        raise AnalysisError(f"{train.file.name}: {e}") from None
    if sigma is not None:
        rms = np.sqrt(np.mean(sigma**2, axis=0))
        note = (f"centres: stated uncertainty ({train.sigma_from}), RMS "
                f"{'/'.join(f'{v:.3f}' for v in rms)} µm x/y/z")
    else:
        std = np.sqrt(np.diagonal(groups.centre_cov_um2[0]))
        note = (f"centres: scatter between repeats {'/'.join(f'{v:.3f}' for v in std)} µm "
                f"x/y/z ({groups.sigma_dof} dof)")
    note += "; no touches, so no form residual"
    data = centre_touches(groups.centres, groups.repeat)
    return diagnose_groups(machine, a, data, groups, is_ho, options, note)

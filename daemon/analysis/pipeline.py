"""The computing steps of a run, kept out of the state machine: the checked program (PREPARE)
and hits → centres → estimate → analyses (IDENTIFY), giving the typed analysis of
``daemon.analysis.result`` (the ``rumba analyze`` JSON once serialised).

Both are plain functions run in a worker thread; they raise ``PipelineError`` with a reason the
operator can act on (unsafe program, rank-deficient data, incomplete ball-poses).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from contracts.jobs import ProgramJob
from contracts.messages import ProbeHit
from contracts.probing_log import LogRow
from daemon.analysis import result as analysis_result
from daemon.analysis.identify import AnalysisError, analyse_centres
from daemon.analysis.touch_centres import rows_to_centres
from daemon.machines.setup import MachineSetup
from daemon.safepath import plain_name
from identification.kinematics import Machine


class PipelineError(Exception):
    """A run cannot go on (program refused by the safety check, data not identifiable …)."""


# ------------------------------------------------------------------------------------ PREPARE


@dataclass
class Prepared:
    job: ProgramJob
    estimated_s: float | None = None
    notes: list[str] = field(default_factory=list)

    def complete(self, hit: ProbeHit, t_s: float) -> ProbeHit:
        """Fill the fields a transport cannot know from the program's touch table."""
        return self.job.touches.fill(hit, **({"t_s": t_s} if hit.t_s == 0.0 else {}))

    def mismatch(self, hit: ProbeHit) -> str:
        """Why ``hit`` does not belong to this program ('' when it does): identities are
        carried through the program, never guessed."""
        return self.job.touches.mismatch(hit)


def targets_from(analysis: analysis_result.Analysis | None) -> Any:
    """Program targets: the setup estimated by the last good run when there is one (smaller
    standoffs, faster cycles), else nominal."""
    from programs.model import Targets

    if analysis is None or analysis.setup is None:
        return Targets()
    balls = {b: tuple(v * 1e-3 for v in d.value) for b, d in analysis.setup.balls.items()}
    tip = tuple(v * 1e-3 for v in analysis.setup.probe.value)
    return Targets("estimate", balls, tip)


def prepare(setup: MachineSetup, run_id: str,
            last_good: analysis_result.Analysis | None = None) -> Prepared:
    """Generate the program for ``setup``, check it against travel limits and keep-outs, and
    render it in the machine's dialect. Nothing leaves the daemon without passing here."""
    from programs.generate import generate
    from programs.geometry import ProgramError
    from programs.safety import SafetyError

    try:
        targets = targets_from(last_good if setup.program_targets == "last_good" else None)
        printed = tuple(ch.address for ch in setup.temperatures  # DNC prints them
                        if ch.source == "controller"
                        and getattr(setup.link, "transport", "") == "serial")
        from drivers.registry import HANDSHAKE  # the link reads the controller's variables

        g = generate(setup.machine, setup.machine_file, setup.artefact, setup.plan,
                     setup.dialect, targets, printed,
                     handshake=getattr(setup.link, "transport", "") in HANDSHAKE)
        for name in g.aux_files:  # they become files on the controller (and next to `gcode -o`)
            plain_name(name, f"{setup.dialect} auxiliary file")
    except SafetyError as e:
        raise PipelineError(f"program refused by the safety check: {e}") from None
    except (ProgramError, ValueError) as e:  # UnsafePathError is a ValueError too
        raise PipelineError(f"program not generated: {e}") from None
    touches = g.touch_table()
    job = ProgramJob(run_id=run_id, text=g.text, dialect=setup.dialect,
                     touch_count=len(touches), touches=touches, meta={"program": "rumba"},
                     files=dict(g.aux_files), codec=g.dialect)
    return Prepared(job, g.estimated_s, [f"safety: {g.safety.moves} moves checked, min slack "
                                         f"{g.safety.min_slack_mm:.2f} mm"])


# ----------------------------------------------------------------------------------- IDENTIFY


def _axis(axes: dict[str, float], keys: Sequence[str]) -> float:
    for k in keys:
        if k in axes:
            return float(axes[k])
    raise KeyError(keys[0])


def hit_to_row(run_id: str, hit: ProbeHit, machine: Machine) -> LogRow:
    """A journaled hit as a probing-log row (latched X Y Z and rotary axes, controller units)."""
    r1, r2 = machine.rotary_axes
    ax = hit.axes
    try:
        b = _axis(ax, (r1, r1.lower(), "b")) if any(k in ax for k in (r1, r1.lower(), "b")) \
            else hit.b_cmd_deg
        c = _axis(ax, (r2, r2.lower(), "c")) if any(k in ax for k in (r2, r2.lower(), "c")) \
            else hit.c_cmd_deg
        xyz = [_axis(ax, (k, k.lower())) for k in "XYZ"]
    except KeyError as e:
        raise PipelineError(f"touch seq {hit.seq}: latched axis {e.args[0]} missing "
                            f"(got {sorted(ax)})") from None
    return LogRow(run_id, hit.seq, hit.t_s, hit.repeat, hit.pose, hit.b_cmd_deg, hit.c_cmd_deg,
                  hit.ball, hit.touch, *map(float, hit.direction), *xyz, b, c, hit.feed_mm_min)


def row_to_hit(row: LogRow, machine: Machine) -> ProbeHit:
    r1, r2 = machine.rotary_axes
    return ProbeHit(seq=row.seq, pose=row.pose, ball=row.ball, touch=row.touch,
                    axes={"X": row.x_mm, "Y": row.y_mm, "Z": row.z_mm, r1: row.b_deg,
                          r2: row.c_deg}, triggered=True, t_s=row.t_s, repeat=row.repeat,
                    raw="imported", b_cmd_deg=row.b_cmd_deg, c_cmd_deg=row.c_cmd_deg,
                    direction=(row.dir_x, row.dir_y, row.dir_z), feed_mm_min=row.feed_mm_min)


@dataclass
class RunAnalysis:
    data: analysis_result.Analysis  # with the run's identity (run id, plan, touches)
    centre_rows: list[tuple]  # for the store: pose, ball, b, c, x, y, z, radius dev, form
    estimate: Any = None  # the Estimate behind ``data.links`` (the compensation view's)


def analyse(setup: MachineSetup, hits: Sequence[ProbeHit], run_id: str = "run",
            reference: tuple[str, analysis_result.Analysis] | None = None,
            controller: Machine | None = None) -> RunAnalysis:
    """Centres (sphere fit) → estimate (setup + identifiable links) → analyses, as the shared
    ``daemon.analysis.result.Analysis`` plus the run's identity and the reference run (the
    machine's baseline run the verdict's drift is judged against, None when there is none).
    ``controller``: the model the controller runs when compensations were written to it
    (``daemon.compensation.propose.controller_model``), else the machine file's."""
    rows = [hit_to_row(run_id, h, setup.machine) for h in hits if h.triggered]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            cd = rows_to_centres(rows, setup.artefact, setup.plan.stylus_radius_mm,
                                 source=f"run {run_id}")
        except ValueError as e:  # ProbeLogError, and any numerical failure of the fit
            raise PipelineError(str(e)) from None
    keep: dict[str, Any] = {}
    try:
        data = analyse_centres(controller or setup.machine, setup.artefact, cd,
                               validate_poses=setup.validate_poses, source=f"run {run_id}",
                               keep=keep, rotary_repeatability_urad=setup.machine_file
                               .rotary_repeatability_urad)
    except (AnalysisError, ValueError) as e:
        raise PipelineError(f"identification impossible: {e}") from None
    data = replace(data, run_id=run_id, machine=setup.name, plan=setup.plan.name,
                   touches=len(rows), reference_run=reference[0] if reference else None,
                   warnings=(*data.warnings, *(str(w.message) for w in caught
                                               if str(w.message) not in data.warnings)))
    cd = keep.get("touch_data", cd)  # the centres as the estimate used them (its frame)
    centres, ids = cd.centres, setup.artefact.ids
    health = {(h.pose, h.ball, h.repeat): h for h in cd.health}
    # The store keeps one centre per pose and ball: the first repeat's, or the re-probe that
    # replaced it; a visit left out as faulty has none.
    stands_for = {(o.pose, o.ball, o.replaced_by_repeat): o.repeat
                  for o in data.outliers or () if o.status == "repaired"}
    left_out = {(o.pose, o.ball, o.repeat) for o in data.outliers or ()}
    centre_rows = []
    for k in range(len(centres)):
        key = (int(centres.pose[k]), ids[int(centres.ball[k])], int(cd.repeat[k]))
        if stands_for.get(key, key[2]) != 0 or key in left_out:
            continue
        h = health[key]
        centre_rows.append((int(centres.pose[k]), ids[int(centres.ball[k])],
                            float(centres.b_deg[k]), float(centres.c_deg[k]),
                            *map(float, centres.xyz_mm[k]), h.radius_dev_um, h.form_rms_um))
    return RunAnalysis(data, centre_rows, keep.get("estimate"))


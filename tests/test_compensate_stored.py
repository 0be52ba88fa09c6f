"""The compensation view from the run's stored estimate: identified once, in the
run's worker thread, stored with its analysis (journal migration 6) and read by the unattended
path, `rumba compensate` and the HMI (tests/test_hmi_compensate.py) instead of identifying
again; equal to the re-identification to round-off; runs journaled before the migration (or
whose model changed since) are identified once on first use and stored. Real SQLite journals,
the state machine on a replayed log, the fake LinuxCNC HAL of test_compensate_transaction."""

from __future__ import annotations

import dataclasses
import json
import re
import sqlite3
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.compensation import identified
from daemon.compensation import journal as cj
from daemon.compensation.propose import (
    controller_model,
    journal_analyse,
    propose,
    reidentify,
    spec_of,
)
from daemon.config import load_daemon_config
from daemon.run.session import Session
from daemon.run.unattended import after_run
from daemon.store.journal import Store
from daemon.store.schema import MIGRATIONS
from identification.compensation import plan_compensation
from tests.cli_helpers import run_cli
from tests.test_compensate import LINKS, MACHINE, _world
from tests.test_compensate_transaction import X, _rows, fake_linuxcnc


def _counting(monkeypatch) -> list[str]:
    """Every identification of a compensation estimate: the name of the thread it ran in."""
    calls: list[str] = []
    real = identified.identify

    def identify(*a, **kw):
        calls.append(threading.current_thread().name)
        return real(*a, **kw)

    monkeypatch.setattr(identified, "identify", identify)
    return calls


def _same_view(setup, store: Store, run_id: str) -> None:
    """The view (estimate, plan, proposal) from the stored one equals the one computed now."""
    run = store.run(run_id)
    model = controller_model(setup, store, before=run.started_at, check_hal=False)
    params, k = spec_of(setup).to_math(), setup.tolerances.coverage_k
    got = identified.load(store, run_id, identified.model_key(setup, model, params, k))
    assert got is not None, f"run {run_id}: no stored view"
    stored, plan = got
    fresh, c = reidentify(setup, store, run_id, model)
    for name in ("p", "std", "cov"):
        assert np.allclose(getattr(stored, name), getattr(fresh, name), rtol=1e-12,
                           atol=1e-18), name
    assert stored.warnings == fresh.warnings and stored.status == fresh.status
    now = plan_compensation(model, setup.artefact, fresh, params, c.b_deg, c.c_deg,
                            coverage_k=k)
    for a, b in zip(plan.changes, now.changes, strict=True):
        assert (a.name, a.observable, a.note) == (b.name, b.observable, b.note)
        assert (a.delta, a.u_expanded) == pytest.approx((b.delta, b.u_expanded), rel=1e-9,
                                                        abs=1e-15), a.name
    assert plan.links_residual == pytest.approx(now.links_residual, rel=1e-9, abs=1e-15)
    assert plan.distortion_after_um == pytest.approx(now.distortion_after_um, rel=1e-9)
    p = propose(setup, store, run_id)
    for name, (value, std, unit) in fresh.links_si().items():
        assert p.links[name][2] == unit and p.links[name][:2] == pytest.approx(
            (value, std), rel=1e-9, abs=1e-9), name


async def test_the_unattended_path_reads_the_estimate_the_run_stored(tmp_path, capsys,
                                                                     monkeypatch):
    guards = {"max_change_um": 150, "max_change_urad": 100, "max_total_um": 200,
              "unattended": True}
    cfg = _world(tmp_path, capsys, host="127.0.0.1", guards=guards)
    pins, _ = fake_linuxcnc(tmp_path, monkeypatch)
    conf = load_daemon_config(cfg)
    setup = conf.machines["lcnc"]
    calls = _counting(monkeypatch)
    rows = _rows(LINKS, "live")
    store = Store(conf.store_path)
    try:
        session = Session(setup, ReplayLink(rows, setup.machine), store, conf.reports_dir,
                          prepare=prepare_from_rows(rows),
                          analyse=journal_analyse(conf.store_path), after_run=after_run)
        first = session.start("cnc")  # the controller's start of shift: unattended allowed
        # no deadline as the criterion: each step fails at once with its reason (the run's
        # own end state, the compensation journal when no verification run followed)
        await session.wait()
        assert store.run(first).state == "DONE", store.run(first)
        assert session.run_id != first, ("no verification run followed",
                                         [(r.state, r.reason) for r in cj.rows(store, "lcnc")])
        second = session.run_id
        await session.wait()  # the verification run, started by after_run in the first run
        assert not session.busy, session.status()
        assert store.run(first).state == "DONE" and store.run(second).state == "DONE"
        (row,) = [r for r in cj.rows(store, "lcnc") if r.state == "applied"]
        assert row.run_id == first and row.confirmed_by == "unattended"
        # never identified again at run end — the stored view is the run's own
        # estimate (the one its report shows), planned in the run's worker thread
        assert calls == [], calls
        stored = {r[0] for r in store.db.execute("SELECT run_id FROM link_estimates")}
        assert stored == {first, second}
        for run_id in (first, second):
            got = identified.load(store, run_id, identified.model_key(
                setup, controller_model(setup, store, before=store.run(run_id).started_at,
                                        check_hal=False), spec_of(setup).to_math(),
                setup.tolerances.coverage_k))
            assert got is not None
            a = store.analysis(run_id)
            for name, (value, std, _) in got[0].links_si().items():
                assert (value, std) == pytest.approx((a.links[name].value, a.links[name].std),
                                                     abs=1e-4), name
        _same_view(setup, store, first)
        _same_view(setup, store, second)
        assert len(calls) == 2  # only the two re-identifications of _same_view
        assert threading.main_thread().name in calls  # (the test's own, on its thread)
    finally:
        store.close()
    assert abs(json.loads(pins.read_text())["pins"][X] - row.values[0].new) < 1e-9


def test_a_run_journaled_before_the_migration_is_identified_once_and_stored(
        tmp_path, capsys, monkeypatch):
    cfg = _world(tmp_path, capsys)  # imported: no run-end identification
    conf = load_daemon_config(cfg)
    db = sqlite3.connect(conf.store_path)
    with db:  # the journal as rumba before migration 6 left it
        for step in reversed(MIGRATIONS[5:]):  # undo migration 6 and every later one
            for stmt in step:
                if m := re.match(r"\s*CREATE TABLE (\w+)", stmt):
                    db.execute(f"DROP TABLE {m[1]}")
                elif m := re.match(r"\s*ALTER TABLE (\w+) ADD COLUMN (\w+)", stmt):
                    db.execute(f"ALTER TABLE {m[1]} DROP COLUMN {m[2]}")
        db.execute("DELETE FROM schema_version WHERE version >= 6")
    db.close()
    calls = _counting(monkeypatch)
    code, first, _err = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 0 and len(calls) == 1, (first, _err)
    code, again, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 0 and len(calls) == 1  # the second one reads it
    # the same view, printed (up to the journal row each proposal adds)
    assert first.split("\nproposed (journal")[0] == again.split("\nproposed (journal")[0]
    store = Store(conf.store_path)
    try:
        assert store.schema_version() == len(MIGRATIONS)
        _same_view(conf.machines["lcnc"], store, "synth")
    finally:
        store.close()


def test_a_changed_machine_file_or_a_garbled_row_is_identified_again(tmp_path, capsys,
                                                                    monkeypatch):
    cfg = _world(tmp_path, capsys)
    conf = load_daemon_config(cfg)
    calls = _counting(monkeypatch)
    assert run_cli(["compensate", "--config", cfg, "synth"], capsys)[0] == 0
    store = Store(conf.store_path)
    try:
        store.db.execute("UPDATE link_estimates SET estimate='{\"format\": 1, \"p\": 3}'")
    finally:
        store.close()
    assert run_cli(["compensate", "--config", cfg, "synth"], capsys)[0] == 0
    assert len(calls) == 2  # the unreadable row was computed again, no traceback
    # the machine file edited (B's pivot 5 µm off): the stored estimate is for another model
    data = yaml.safe_load(Path(MACHINE).read_text())
    data["axes"]["B"]["point_mm"][0] += 0.005
    edited = tmp_path / "machine_edited.yaml"
    edited.write_text(yaml.safe_dump(data))
    Path(cfg).write_text(Path(cfg).read_text().replace(str(MACHINE), str(edited)))
    code, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 0 and len(calls) == 3, out
    store = Store(conf.store_path)
    try:
        _same_view(load_daemon_config(cfg).machines["lcnc"], store, "synth")
    finally:
        store.close()


def test_the_stored_form_reads_back_bit_for_bit(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    conf = load_daemon_config(cfg)
    setup = conf.machines["lcnc"]
    store = Store(conf.store_path)
    try:
        est, _ = reidentify(setup, store, "synth", setup.machine)
        back = identified.from_json(identified.to_json(est))
        for name in ("p", "std", "cov", "residual_mm", "sigma_um"):
            assert np.array_equal(getattr(est, name), getattr(back, name)), name
        assert (back.layout, back.ball_ids, back.sigma_dof, back.absorbed_by) == (
            est.layout, est.ball_ids, est.sigma_dof, est.absorbed_by)
        # the components' p-values are NaN for the untested centre ones (NaN ≠ NaN)
        np.testing.assert_equal(back.visit_scatter, est.visit_scatter)
        scattered = dataclasses.replace(est, visit_scatter={"B": (3.0, 0.5, 1e-4)})
        assert identified.from_json(identified.to_json(scattered)).visit_scatter == \
            {"B": (3.0, 0.5, 1e-4)}
        for bad in ("", "[]", '{"format": 1}', '{"format": 2}', "nan"):
            with pytest.raises(ValueError):
                identified.from_json(bad)
            with pytest.raises(ValueError):
                identified.plan_from_json(bad)
        c = identified.estimation_centres(setup, identified.run_centres(setup, store, "synth"))
        plan = plan_compensation(setup.machine, setup.artefact, est, spec_of(setup).to_math(),
                                 c.b_deg, c.c_deg)
        back = identified.plan_from_json(identified.plan_to_json(plan))
        assert back == plan
        assert np.array_equal(back.link_disp_mm, plan.link_disp_mm)
        assert back.change_disp_mm.keys() == plan.change_disp_mm.keys() and all(
            np.array_equal(back.change_disp_mm[k], v) for k, v in plan.change_disp_mm.items())
    finally:
        store.close()


async def test_a_view_that_cannot_be_computed_never_fails_the_run(tmp_path, capsys,
                                                                   monkeypatch):
    cfg = _world(tmp_path, capsys)
    conf = load_daemon_config(cfg)
    setup = conf.machines["lcnc"]
    rows = _rows(LINKS, "live")

    def broken(*a, **kw):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(identified, "plan_compensation", broken)
    store = Store(conf.store_path)
    try:
        session = Session(setup, ReplayLink(rows, setup.machine), store, conf.reports_dir,
                          prepare=prepare_from_rows(rows),
                          analyse=journal_analyse(conf.store_path))
        run_id = session.start("cli")
        await session.wait()  # the run's task ends on any end state: no deadline needed
        assert store.run(run_id).state == "DONE", store.run(run_id)
        assert store.db.execute("SELECT COUNT(*) FROM link_estimates").fetchone()[0] == 0
        monkeypatch.undo()  # the view is computed when asked, and stored then
        assert propose(setup, store, run_id).values
        assert store.db.execute("SELECT run_id FROM link_estimates").fetchall() == [(run_id,)]
    finally:
        store.close()

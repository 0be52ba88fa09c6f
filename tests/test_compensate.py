"""`rumba compensate`: proposal, guards, refusals, confirmation, rollback and the journal, on
runs imported into a real SQLite journal (no controller: the LinuxCNC machine file's section
with a remote link writes the reviewed program for the operator)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import yaml

from benchmarks.rigs.daemon_helpers import CONFIG, write_daemon_yaml
from contracts.probing_log import write_log
from daemon.analysis import pipeline
from daemon.compensation import journal as cj
from daemon.compensation.propose import ControllerModelError, controller_model, journal_analyse
from daemon.config import load_daemon_config
from daemon.store.journal import Store
from daemon.store.schema import MIGRATIONS, for_postgres
from drivers.linuxcnc import halkins
from simulators.exact_log import shipped_run_rows
from tests.cli_helpers import run_cli

LINKS = {"EA0B": 18, "EC0B": -23, "EX0C": -40, "EA0C": -19, "EB0C": 26, "EC0Y": 17,
         "EA0Z": -24, "EB0Z": -12}
MACHINE = CONFIG / "machines/linuxcnc_xyzbc.yaml"
PLAN = CONFIG / "plans/linuxcnc_7poses.yaml"


def _world(tmp: Path, capsys, links: dict[str, float] = LINKS, host: str = "192.0.2.1",
           run_ids: tuple[str, ...] = ("synth",), guards: dict | None = None) -> str:
    """daemon.yaml for machine lcnc (LinuxCNC machine file, linuxcncrsh at ``host``; its
    guards replaced by ``guards``) and the same exact synthetic run imported under each id
    (the machine does not change between)."""
    tmp.mkdir(exist_ok=True)
    machine = MACHINE
    if guards is not None:
        data = yaml.safe_load(MACHINE.read_text())
        data["controller_kinematics"]["guards"] = guards
        machine = tmp / "machine.yaml"
        machine.write_text(yaml.safe_dump(data))
    (tmp / "daemon.yaml").write_text(f"""
store: {{path: {tmp / 'journal.sqlite'}}}
reports_dir: {tmp / 'reports'}
hmi: {{enabled: false}}
machines:
  - name: lcnc
    machine: {machine}
    artefact: {CONFIG / 'artefacts/thesis_4ball.yaml'}
    plan: {PLAN}
    dialect: linuxcnc
    link: {{transport: linuxcnc, host: {host}, port: 5007}}
    tolerances:
      default_rotation_urad: {{warn: 100, fail: 200}}
      default_translation_um: {{warn: 300, fail: 500}}
""")
    cfg = str(tmp / "daemon.yaml")
    for run_id in run_ids:
        log = tmp / f"{run_id}.csv"
        write_log(log, shipped_run_rows(MACHINE, CONFIG / "artefacts/thesis_4ball.yaml", PLAN,
                                        links, run_id=run_id))
        code, _, err = run_cli(["history", "--config", cfg, "--import", str(log), "--machine",
                                "lcnc"], capsys)
        assert code == 0, err
    return cfg


def _journal(cfg: str) -> list[cj.CompensationRow]:
    store = Store(load_daemon_config(cfg).store_path)
    try:
        return cj.rows(store)
    finally:
        store.close()


def test_migration_is_portable():
    ddl = MIGRATIONS[3][0]  # migration 4; later ones alter it
    assert "CREATE TABLE compensations" in ddl
    pg = for_postgres(ddl)
    assert "BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY" in pg and "REAL" not in pg


def test_a_proposal_is_a_review_document_never_a_program(tmp_path, capsys):
    """Without --confirm nothing a control could load exists: no program in reports_dir, a
    review document (JSON) listing what a confirmation would write, address by address as the
    program will write it, and the journal row 'proposed' saying so; the confirmation writes
    the program, whose lines are that listing (the fingerprint the review printed)."""
    cfg = _world(tmp_path, capsys)
    code, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 0, out
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("x-offset"))
    assert "xyzbc-trt-kins.x-offset" in line and "12.5" in line and "apply" in line
    delta_um = float(line.split("µm")[0].split()[-1])
    assert abs(delta_um - 40.0) < 2.0  # EX0C −40 µm is held by x-offset +40 µm
    assert "skipped (not observable" in out  # the rot-points move every ball alike
    # named and defined figures; the link-caused distortion, never "compensable"
    assert "link-caused distortion max" in out and "predicted after compensation max" in out
    assert "compensable" not in out and "EX0C" in out
    reports = tmp_path / "reports"
    programs = [p.name for p in reports.iterdir() if p.suffix in (".hal", ".nc", ".mpf", ".txt")]
    assert programs == [], programs  # nothing a control could load
    review = Path(out.strip().splitlines()[-1].split("review: ")[1])
    assert review.parent == reports and review.name == "proposal-lcnc-synth.json"
    doc = json.loads(review.read_text())
    assert doc["state"] == "proposed" and "not a program" in doc["document"]
    assert "No program exists" in doc["nothing_written"]
    (w,) = doc["writes"]
    assert w["address"] == "xyzbc-trt-kins.x-offset" and w["was"] == "12.500000"
    assert abs(float(w["written"]) - 12.54) < 0.002
    # the terminal lists it as written too, and names the listing to confirm
    assert f"xyzbc-trt-kins.x-offset = {w['written']:>14}  (was 12.500000; mm" in out, out
    fp = doc["listing_fingerprint"]
    assert f"--listing {fp}" in out
    rows = _journal(cfg)
    assert [r.state for r in rows] == ["proposed"]
    assert "no program exists until a person confirms" in rows[0].reason
    (v,) = rows[0].values
    assert v.name == "x-offset" and v.old == 12.5 and v.new == float(w["written"])
    assert v.u_expanded > 0 and abs(v.delta) > v.u_expanded
    # a confirmation naming another listing is refused, nothing written
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by", "alice",
                            "--listing", "0123456789abcdef"], capsys)
    assert code == 2 and "not the ones reviewed" in out and fp in out, out
    assert not list(reports.glob("compensation-*"))
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by", "alice",
                            "--listing", fp], capsys)
    assert code == 0, out
    program = Path(out.strip().splitlines()[-1].split("program: ")[1])
    assert program.name == "compensation-lcnc-synth.hal"
    assert f"setp xyzbc-trt-kins.x-offset {w['written']}\n" in program.read_text()
    assert [r.state for r in _journal(cfg)] == ["proposed", "refused", "applied"]


def test_confirm_needs_an_operator(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    code, _, err = run_cli(["compensate", "--config", cfg, "--confirm", "synth"], capsys)
    assert code == 2 and "--confirm needs --by" in err
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by",
                            "unattended"], capsys)
    assert code == 2 and "unattended compensation is not allowed" in out
    assert [r.state for r in _journal(cfg)] == ["refused"]


def test_confirm_then_second_run_identifies_zero_then_rollback(tmp_path, capsys):
    cfg = _world(tmp_path, capsys, run_ids=("synth", "synth2"))
    conf = load_daemon_config(cfg)
    setup = conf.machines["lcnc"]
    # the second run was imported before the compensation: identified against the file
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by",
                            "alice"], capsys)
    assert code == 0 and "applied (journal #1, confirmed by alice)" in out
    assert "the operator loads/enters compensation-lcnc-synth.hal" in out
    (row,) = _journal(cfg)
    assert row.state == "applied" and row.confirmed_by == "alice" and row.applied_at
    store = Store(conf.store_path)
    try:
        model = controller_model(setup, store)
        shift = model.axes["B"].point_mm[0] - setup.machine.axes["B"].point_mm[0]
        assert abs(shift - row.values[0].delta) < 1e-12 and abs(shift - 0.04) < 0.002
        assert model.axes["C"].point_mm == setup.machine.axes["C"].point_mm
        hits = store.hits("synth2")
    finally:
        store.close()
    # a run after the compensation, identified against the controller model: EX0C ≈ 0
    after = journal_analyse(conf.store_path)(setup, hits, "synth2").data.links["EX0C"]
    before = pipeline.analyse(setup, hits, "synth2").data.links["EX0C"]
    assert abs(before.value + 40) < 2 and abs(after.value) < 2 * after.std + 1e-3
    # rollback: the applied row becomes rolled_back, a new row restores the old value
    code, out, _ = run_cli(["compensate", "--config", cfg, "--rollback", "--machine", "lcnc",
                            "--by", "bob"], capsys)
    assert code == 0 and "rolled back (journal #2)" in out
    assert "xyzbc-trt-kins.x-offset =      12.500000  (was 12.5" in out, out  # as written
    program = Path(out.strip().splitlines()[-1].split("program: ")[1])
    assert program.name == "rollback-lcnc-synth.hal"
    assert "setp xyzbc-trt-kins.x-offset 12.500000" in program.read_text()
    rows = _journal(cfg)
    assert [r.state for r in rows] == ["rolled_back", "rolled_back"]
    assert rows[1].confirmed_by == "bob" and rows[1].is_rollback
    assert rows[1].values[0].new == 12.5 and rows[1].values[0].old == rows[0].values[0].new
    store = Store(conf.store_path)
    try:
        assert controller_model(setup, store).axes == setup.machine.axes
    finally:
        store.close()
    code, out, _ = run_cli(["compensate", "--config", cfg, "--rollback", "--machine", "lcnc",
                            "--by", "bob"], capsys)
    assert code == 2 and "no applied compensation to roll back" in out


def test_second_run_after_compensation_proposes_nothing(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    assert run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by", "alice"],
                   capsys)[0] == 0
    log = tmp_path / "again.csv"
    log.write_text((tmp_path / "synth.csv").read_text().replace("synth,", "later,"))
    assert run_cli(["history", "--config", cfg, "--import", str(log), "--machine", "lcnc"],
                   capsys)[0] == 0
    code, out, _ = run_cli(["compensate", "--config", cfg, "later"], capsys)
    assert code == 0 and "nothing to change" in out, out
    assert "smaller than its own expanded uncertainty" in out
    rows = _journal(cfg)
    assert rows[0].verify_run_id == "later" and rows[-1].state == "proposed"
    # the import after the compensation was identified against the controller's model
    store = Store(load_daemon_config(cfg).store_path)
    try:
        before, after = (store.analysis(r).links["EX0C"] for r in ("synth", "later"))
    finally:
        store.close()
    assert abs(before.value + 40) < 2 and abs(after.value) < 2 * after.std + 1e-3
    # its report shows the compensation it verifies, before and after, and the journal links it
    doc = json.loads((tmp_path / "reports" / "later.json").read_text())
    comp = doc["compensation"]
    assert comp["source_run"] == "synth" and comp["confirmed_by"] == "alice"
    ex = next(v for v in comp["links"] if v["name"] == "EX0C")
    assert ex["before"] == pytest.approx(before.value) and ex["after"] == pytest.approx(after.value)
    assert [v["name"] for v in comp["values"]] == ["x-offset"]
    html = (tmp_path / "reports" / "later.html").read_text()
    assert "Compensation verified by this run" in html and "confirmed by alice" in html
    assert json.loads((tmp_path / "reports" / "synth.json").read_text())["compensation"] is None


def test_verify_follows_only_a_live_write(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    code, out, err = run_cli(["compensate", "--config", cfg, "synth", "--verify"], capsys)
    assert code == 2 and "--verify follows a write" in err
    # a remote LinuxCNC: the program is for the operator, who loads it before verifying
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by",
                            "alice", "--verify"], capsys)
    assert code == 0 and "verify: load the program on the control first" in out


def test_the_same_run_cannot_be_applied_twice(tmp_path, capsys):
    # a second --confirm of the same run would add its Δ to the values it already changed
    cfg = _world(tmp_path, capsys)
    assert run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by", "alice"],
                   capsys)[0] == 0
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by",
                            "alice"], capsys)
    assert code == 2 and "the controller's model changed after run synth started" in out
    assert [r.state for r in _journal(cfg)] == ["applied", "refused"]


def test_refused_when_over_the_guard(tmp_path, capsys):
    cfg = _world(tmp_path, capsys, links={**LINKS, "EX0C": -80},
                 guards={"max_change_um": 50, "max_total_um": 100})
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by",
                            "alice"], capsys)
    assert code == 2 and "over the limit 50.0 µm" in out
    (row,) = _journal(cfg)
    assert row.state == "refused" and "over the limit" in row.reason
    cfg = _world(tmp_path / "b", capsys, links={**LINKS, "EX0C": -80},
                 guards={"max_change_um": 90, "max_total_um": 60})
    code, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 2 and "total of the pivot changes" in out and "over the limit 60.0" in out


def test_refused_on_an_error_verdict(tmp_path, capsys):
    cfg = _world(tmp_path, capsys)
    store = Store(load_daemon_config(cfg).store_path)
    store.save_verdict("synth", "ERROR", ["residual too large"], [], "ERROR")
    store.close()
    code, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 2 and "verdict is ERROR" in out
    assert [r.state for r in _journal(cfg)] == ["refused"]


def test_refused_without_controller_kinematics(tmp_path, capsys):
    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup

    cfg = write_daemon_yaml(tmp_path)
    data = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())
    data.pop("controller_kinematics", None)
    (tmp_path / "bare.yaml").write_text(yaml.safe_dump(data))
    cfg.write_text(cfg.read_text().replace(str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
                                           str(tmp_path / "bare.yaml")))
    cfg = str(cfg)
    log = tmp_path / "in.csv"
    write_log(log, thesis_rows(thesis_setup()))
    assert run_cli(["history", "--config", cfg, "--import", str(log), "--machine", "mill1"],
                   capsys)[0] == 0
    code, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 2 and "no controller_kinematics section" in out
    (row,) = _journal(cfg)
    assert row.state == "refused" and row.machine == "mill1"


def test_local_linuxcnc_pins_must_agree_with_the_journal(tmp_path, capsys, monkeypatch):
    cfg = _world(tmp_path, capsys, host="127.0.0.1")  # loopback: LinuxCNC on this PC
    conf = load_daemon_config(cfg)
    pins = {"xyzbc-trt-kins.x-rot-point": 0.0, "xyzbc-trt-kins.y-rot-point": 0.0,
            "xyzbc-trt-kins.z-rot-point": 0.0, "xyzbc-trt-kins.x-offset": 12.5,
            "xyzbc-trt-kins.z-offset": -40.0}
    monkeypatch.setattr(halkins, "read_pins", lambda names: {n: pins[n] for n in names})
    store = Store(conf.store_path)
    try:
        setup = conf.machines["lcnc"]
        assert controller_model(setup, store).axes == setup.machine.axes
        pins["xyzbc-trt-kins.x-offset"] = 12.6  # someone edited the HAL file by hand
        with pytest.raises(ControllerModelError, match="changed the kinematics outside rumba"):
            controller_model(setup, store)
        with pytest.raises(pipeline.PipelineError, match="outside rumba"):
            journal_analyse(conf.store_path)(setup, store.hits("synth"), "synth")
    finally:
        store.close()
    # nothing is set on a LinuxCNC whose pins differ from the journal: refused, journaled
    monkeypatch.setattr(halkins, "setp", lambda *a: pytest.fail("setp must not be called"))
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by",
                            "alice"], capsys)
    assert code == 2 and "outside rumba" in out
    assert [r.state for r in _journal(cfg)] == ["refused"]


def test_hal_file_found_from_the_ini_and_replaced_with_a_backup(tmp_path):
    hal = tmp_path / "machine.hal"
    hal.write_text("loadrt trivkins\nsetp xyzbc-trt-kins.x-offset 12.5\n")
    hal.chmod(0o640)
    (tmp_path / "other.hal").write_text("net a b\n")
    ini = tmp_path / "m.ini"
    ini.write_text("[HAL]\nHALFILE = LIB:basic_sim.tcl -x\nHALFILE = other.hal\n"
                   "HALFILE = machine.hal\n[TRAJ]\nHALFILE = nope.hal\n")
    assert halkins.hal_files(ini) == [tmp_path / "other.hal", hal]
    assert halkins.hal_file_with(ini, ["xyzbc-trt-kins.x-offset"]) == hal
    with pytest.raises(halkins.HalError, match="no HAL file"):
        halkins.hal_file_with(ini, ["xyzbc-trt-kins.z-offset"])
    backup = halkins.replace_file(hal, "setp xyzbc-trt-kins.x-offset 12.6\n", "20260101T000000")
    assert backup.name == "machine.hal.rumba-20260101T000000.bak"
    assert "12.5" in backup.read_text() and "12.6" in hal.read_text()
    assert os.stat(hal).st_mode & 0o777 == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "m.ini", "machine.hal", "machine.hal.rumba-20260101T000000.bak", "other.hal"]
    again = halkins.replace_file(hal, "setp xyzbc-trt-kins.x-offset 12.5\n", "20260101T000000")
    assert again.name == "machine.hal.rumba-20260101T000000-1.bak"  # the first one is kept
    assert "12.6" in again.read_text() and "12.5" in backup.read_text()
    with pytest.raises(halkins.HalError, match="invalid HAL pin"):
        halkins.getp("x; rm -rf /")


def test_siemens_program_journals_the_closing_vector_and_rolls_back(tmp_path, capsys):
    """Another family: the reviewed $TC_CARR program in the reports directory; the closing
    vector the writer changes with a pivot is journaled too and restored by the rollback."""
    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup

    cfg = write_daemon_yaml(tmp_path, dialect="siemens")  # the machine file's controller
    thesis = CONFIG / "machines/thesis_wcbxfzyt.yaml"
    data = yaml.safe_load(thesis.read_text())
    assert data["controller_kinematics"]["family"] == "siemens"
    data["controller_kinematics"]["guards"] = {"max_change_um": 150, "max_total_um": 300}
    (tmp_path / "wide.yaml").write_text(yaml.safe_dump(data))
    cfg.write_text(cfg.read_text().replace(str(thesis), str(tmp_path / "wide.yaml")))
    cfg = str(cfg)
    log = tmp_path / "in.csv"
    write_log(log, thesis_rows(thesis_setup()))
    assert run_cli(["history", "--config", cfg, "--import", str(log), "--machine", "mill1"],
                   capsys)[0] == 0
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by", "eve"],
                           capsys)
    assert code == 0, out
    assert "siemens: the operator loads/enters" in out
    program = Path(out.strip().splitlines()[-1].split("program: ")[1])
    assert program.parent == tmp_path / "reports" and "$TC_CARR" in program.read_text()
    (row,) = _journal(cfg)
    own = [v for v in row.values if not v.name.endswith(" closing")]
    closing = [v for v in row.values if v.name.endswith(" closing")]
    assert own and closing and all(v.address.startswith("$TC_CARR") for v in row.values)
    for v in closing:  # the closing component gets the opposite of the pivot changes
        assert abs(v.new - v.old) > 1e-4
    code, out, _ = run_cli(["compensate", "--config", cfg, "--rollback", "--machine", "mill1",
                            "--by", "eve"], capsys)
    assert code == 0, out
    back = Path(out.strip().splitlines()[-1].split("program: ")[1]).read_text()
    for v in row.values:  # every address, the closing ones too, gets its old value back
        assert f"{v.address}={v.old:.6f}".replace("-0.000000", "0.000000") in \
            back.replace(" ", ""), (v, back)


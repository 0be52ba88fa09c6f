"""``rumba sim --run`` offline and the errors file: what an operator sees."""

from __future__ import annotations

import pytest

from benchmarks.rigs.sim_helpers import TABLE_B2, truth_with
from contracts.probing_log import read_log
from contracts.setup_files import load_artefact, load_machine
from contracts.yaml_files import ConfigError
from daemon.cli.main import main
from simulators.errors_schema import errors_from_dict, load_errors
from simulators.truth import TruthModel
from tests.sim_programs import program

M = "config/machines/thesis_wcbxfzyt.yaml"
A = "config/artefacts/thesis_4ball.yaml"


def test_sim_run_writes_the_probing_log(tmp_path, capsys):
    truth = truth_with(TABLE_B2)
    text, _ = program("linuxcnc", truth, [(0.0, 0.0), (30.0, 60.0)], balls=[0, 2])
    prog = tmp_path / "p.ngc"
    prog.write_text(text)
    log = tmp_path / "out.csv"
    rc = main(["sim", "--machine", M, "--artefact", A, "--errors",
               "config/errors/thesis_tableB2.yaml", "--run", str(prog), "--dialect", "linuxcnc",
               "--log", str(log), "--seed", "4"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "20 probing moves, 0 without trigger, 20 touches logged" in out
    rows = read_log(log, load_artefact(A))
    assert [(r.pose, r.ball, r.touch) for r in rows[:6]] == [
        (0, "B1", 1), (0, "B1", 2), (0, "B1", 3), (0, "B1", 4), (0, "B1", 5), (0, "B3", 1)]
    assert rows[-1].b_deg == 30.0 and rows[-1].c_deg == 60.0 and rows[0].run_id == "p"
    assert rows[4].dir_z == -1.0 and rows[0].feed_mm_min == 300.0
    # Same seed, same log; the identity columns also come without result lines (inferred).
    log2 = tmp_path / "out2.csv"
    bare = "\n".join(ln for ln in text.splitlines() if not ln.startswith("(LOG"))
    prog2 = tmp_path / "bare.ngc"
    prog2.write_text(bare)
    main(["sim", "--machine", M, "--artefact", A, "--errors",
          "config/errors/thesis_tableB2.yaml", "--run", str(prog2), "--dialect", "linuxcnc",
          "--log", str(log2), "--seed", "4", "--run-id", "p"])
    rows2 = read_log(log2, load_artefact(A))
    assert [(r.pose, r.ball, r.touch, r.x_mm) for r in rows2] == [
        (r.pose, r.ball, r.touch, r.x_mm) for r in rows]


def test_sim_run_reports_an_alarm_with_exit_code(tmp_path, capsys):
    prog = tmp_path / "bad.nc"
    prog.write_text("%\nG00 X900.\nM30\n%\n")
    rc = main(["sim", "--machine", M, "--artefact", A, "--run", str(prog), "--dialect",
               "fanuc", "--log", str(tmp_path / "o.csv")])
    assert rc == 1
    assert "controller alarm: OVERTRAVEL X+900.0000" in capsys.readouterr().out


def test_format_files_beside_the_program_are_bounded(tmp_path, capsys):
    """The simulator's aux files (Heidenhain ``*.A`` beside the program): an
    oversized, non-UTF-8 or FIFO one is one error line naming it, never a traceback, a hang
    or the whole file in memory."""
    import os

    from simulators.offline import MAX_AUX_BYTES, aux_files

    prog = tmp_path / "bad.nc"
    prog.write_text("%\nG00 X900.\nM30\n%\n")
    args = ["sim", "--machine", M, "--artefact", A, "--run", str(prog), "--dialect", "fanuc",
            "--log", str(tmp_path / "o.csv")]
    fmt = tmp_path / "FMT.A"
    fmt.write_bytes(b"x" * (MAX_AUX_BYTES + 1))
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"{fmt}: larger than {MAX_AUX_BYTES} bytes" in err and "Traceback" not in err
    fmt.write_bytes(b"P01 \xff\n")
    assert main(args) == 2 and f"{fmt}: byte 4: not UTF-8" in capsys.readouterr().err
    fmt.unlink()
    os.mkfifo(tmp_path / "PIPE.A")  # no writer: reading it would block forever
    (tmp_path / "OK.A").write_text("F-PRINT\n")
    assert aux_files(prog) == {"OK.A": "F-PRINT\n"}


def test_errors_file_errors_are_one_line(tmp_path, capsys):
    bad = tmp_path / "e.yaml"
    bad.write_text("links: {EB0Z: -12, EQ0Z: 3}\n")
    with pytest.raises(ConfigError, match=r"e.yaml: links: .*'EQ0Z' is not an ISO 230-1"):
        load_errors(bad)
    bad.write_text("probe: {stylus_diameter: 6}\n")
    with pytest.raises(ConfigError, match=r"probe\.stylus_diameter: unknown key"):
        load_errors(bad)
    m, mf = load_machine(M)
    a = load_artefact(A)
    with pytest.raises(ConfigError, match=r"links.EX0Y: not a location error of WCBXFZYT"):
        TruthModel.build(m, mf, a, errors_from_dict({"links": {"EX0Y": 3}}))
    with pytest.raises(ConfigError, match=r"setup.balls_um.B9: unknown ball"):
        TruthModel.build(m, mf, a, errors_from_dict({"setup": {"balls_um": {"B9": [0, 0, 0]}}}))
    with pytest.raises(ConfigError, match=r"effects\[0\] \(straightness/X\): params: missing"):
        TruthModel.build(m, mf, a, errors_from_dict(
            {"effects": [{"family": "straightness", "axis": "X", "params": {"EYX_q2": 1}}]}))
    with pytest.raises(ConfigError, match="unknown effect family"):
        TruthModel.build(m, mf, a, errors_from_dict({"effects": [{"family": "warp"}]}))
    rc = main(["sim", "--machine", M, "--artefact", A, "--errors", str(bad), "--run", "x",
               "--dialect", "fanuc", "--log", "y"])
    assert rc == 2 and "error: " in capsys.readouterr().err


def test_default_errors_file_is_table_b2():
    e = load_errors("config/errors/thesis_tableB2.yaml")
    assert e.links == {"EB0Z": -12, "EA0Y": -24, "EC0Y": 17, "EC0B": -23, "EA0B": 2,
                       "EA0C": -19, "EB0C": 26, "EX0C": -106}
    t = TruthModel.from_files(M, A, "config/errors/thesis_tableB2.yaml")
    assert t.links["EX0C"] == pytest.approx(-0.106) and t.links["EB0Z"] == pytest.approx(-12e-6)


def test_shipped_errors_and_faults_files_load():
    from pathlib import Path

    from simulators.faults import FaultPlan

    machines = {load_machine(m)[0].name: m for m in Path("config/machines").glob("*.yaml")}
    for p in sorted(Path("config/errors").glob("*.yaml")):
        name = load_errors(p).machine or "thesis-wcbxfzyt"
        balls = set(load_errors(p).setup.balls_um)
        art = next(a for a in sorted(Path("config/artefacts").glob("*.yaml"))
                   if balls <= set(load_artefact(a).ids))
        assert TruthModel.from_files(machines[name], art, p).machine.name == name
    for p in sorted(Path("config/faults").glob("*.yaml")):
        assert FaultPlan.load(p).faults


@pytest.mark.parametrize("transport", ["modbus", "opcua", "serial", "sinumerik", "lsv2"])
def test_sim_serve_on_a_port_in_use_is_one_line_exit_2(transport, capsys):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        rc = main(["sim", "--machine", M, "--artefact", A, "--serve", transport,
                   "--port", str(port), "--security", "none"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert f"--serve {transport}: " in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err

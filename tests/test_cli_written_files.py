"""What a command says about its output: ``--dialect haas`` is called haas in
the summary and in the program's header (the Fanuc template, its rotary skips by letter), and
every file a command writes is named in its output."""

from __future__ import annotations

import json

import pytest

from benchmarks.rigs.daemon_helpers import CONFIG
from daemon.cli.main import main as cli_main
from programs.dialects import get_dialect

SETUP = ["--machine", str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
         "--artefact", str(CONFIG / "artefacts/thesis_4ball.yaml")]
GCODE = ["gcode", *SETUP, "--plan", str(CONFIG / "plans/thesis_ch3_7poses.yaml")]


@pytest.mark.parametrize(("dialect", "header"), [("haas", "(DIALECT HAAS)"),
                                                  ("fanuc", "(DIALECT FANUC)"),
                                                  ("siemens", "; DIALECT siemens")])
def test_gcode_names_the_dialect_asked_for_and_the_file_it_wrote(tmp_path, capsys, dialect,
                                                                   header):
    out_file = tmp_path / "p.nc"
    assert cli_main([*GCODE, "--dialect", dialect, "-o", str(out_file)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"{dialect}: ") and err == ""
    assert f"wrote {out_file}" in out.splitlines()
    text = out_file.read_text()
    assert header in text.splitlines()[:6]
    other = {"haas": "FANUC", "fanuc": "HAAS", "siemens": "FANUC"}[dialect]
    assert f"DIALECT {other}" not in text.upper()


def test_haas_is_the_fanuc_template_under_its_own_name():
    assert get_dialect("haas").label == "haas" and get_dialect("haas").name == "fanuc"
    assert get_dialect("fanuc").label == "fanuc"


def test_gcode_names_every_auxiliary_file(tmp_path, capsys):
    out_file = tmp_path / "RUMBA.h"
    assert cli_main([*GCODE, "--dialect", "heidenhain", "-o", str(out_file)]) == 0
    out = capsys.readouterr().out.splitlines()
    aux = sorted(p for p in tmp_path.iterdir() if p != out_file)
    assert aux  # the F-PRINT format files, one per ball
    for p in [out_file, *aux]:
        assert f"wrote {p}" in out


def test_gcode_to_stdout_writes_the_program_and_names_no_file(capsys):
    assert cli_main([*GCODE, "--dialect", "haas"]) == 0
    out, err = capsys.readouterr()
    assert "(DIALECT HAAS)" in out and err.startswith("haas: ") and "wrote" not in err


def test_analyze_names_its_json(tmp_path, capsys):
    js = tmp_path / "a.json"
    assert cli_main(["analyze", "--log", str(CONFIG / "examples/thesis_annexB_14poses.csv"),
                     *SETUP, "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert f"wrote {js}" in out and json.loads(js.read_text())

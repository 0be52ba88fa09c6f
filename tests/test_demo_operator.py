"""`make demo-hmi`'s simulated operator runs on the control only a program a confirmation wrote
(the journal names it and it is the machine's current state): never a proposal (which is no
program any more), never a file someone put in the reports folder, and a rollback's program
once the rollback is journaled. Real journal, real `rumba compensate`, the simulated
SINUMERIK's own kinematic values checked after each pass."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from benchmarks.rigs.daemon_helpers import CONFIG, thesis_rows, thesis_setup, write_daemon_yaml
from contracts.probing_log import write_log
from simulators.controller import VirtualController
from simulators.truth import TruthModel
from tests.cli_helpers import run_cli

THESIS = CONFIG / "machines/thesis_wcbxfzyt.yaml"


def _world(tmp: Path, capsys) -> tuple[str, Path]:
    """daemon.yaml of mill1 (Siemens, guards widened for Table B.2's EX0C), run ``synth``
    imported; the machine file used."""
    cfg = write_daemon_yaml(tmp, dialect="siemens")
    data = yaml.safe_load(THESIS.read_text())
    data["controller_kinematics"]["guards"] = {"max_change_um": 150, "max_total_um": 300}
    machine = tmp / "wide.yaml"
    machine.write_text(yaml.safe_dump(data))
    cfg.write_text(cfg.read_text().replace(str(THESIS), str(machine)))
    log = tmp / "in.csv"
    write_log(log, thesis_rows(thesis_setup()))
    assert run_cli(["history", "--config", str(cfg), "--import", str(log), "--machine",
                    "mill1"], capsys)[0] == 0
    return str(cfg), machine


async def test_the_demo_operator_runs_only_what_a_confirmation_wrote(tmp_path, capsys):
    cfg, machine = _world(tmp_path, capsys)
    reports, journal = tmp_path / "reports", tmp_path / "journal.sqlite"
    code, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 0, out
    # a proposal: nothing a control could load
    assert sorted(p.suffix for p in reports.iterdir() if p.name.startswith(
        ("compensation", "proposal"))) == [".json"], sorted(reports.iterdir())
    doc = json.loads((reports / "proposal-mill1-synth.json").read_text())
    assert doc["state"] == "proposed" and doc["writes"]

    from demos.hmi import operator_pass

    truth = TruthModel.from_files(machine, CONFIG / "artefacts/thesis_4ball.yaml",
                                  CONFIG / "errors/thesis_tableB2.yaml")
    ctrl = VirtualController(truth, time_scale=0.01, dialect="siemens")
    before = dict(ctrl.kinematics.current)
    seen: set[tuple[str, int]] = set()
    assert await operator_pass(ctrl, reports, journal, "mill1", seen) == []
    # a program nobody confirmed, put in the folder by hand (as the proposal once was)
    planted = reports / doc["program_name"]
    planted.write_text("; RUMBA COMPENSATION RUN synth MACHINE mill1\n" + "".join(
        f"{w['address']}={w['written']}\n" for w in doc["writes"]) + "M30\n")
    done = await operator_pass(ctrl, reports, journal, "mill1", seen)
    assert done == [f"operator: not running {planted.name}: no confirmed compensation in "
                    "the journal wrote it"], done
    assert ctrl.kinematics.current == before and ctrl.kinematics.audit == []
    # confirmed: the program the confirmation wrote is run, the control holds the listing
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by", "eve",
                            "--listing", doc["listing_fingerprint"]], capsys)
    assert code == 0, out
    done = await operator_pass(ctrl, reports, journal, "mill1", seen)
    assert len(done) == 1 and done[0].startswith(f"operator: ran {planted.name} on the "
                                                 "control (done)"), done
    for w in doc["writes"]:
        assert ctrl.kinematics.current[w["address"]] == float(w["written"]), w
    assert await operator_pass(ctrl, reports, journal, "mill1", seen) == []  # once
    # the rollback's program too, once journaled; the control is back where it was
    code, out, _ = run_cli(["compensate", "--config", cfg, "--rollback", "--machine", "mill1",
                            "--by", "eve"], capsys)
    assert code == 0, out
    done = await operator_pass(ctrl, reports, journal, "mill1", seen)
    assert len(done) == 1 and "ran rollback_mill1_synth.mpf" in done[0], done
    assert ctrl.kinematics.current == before

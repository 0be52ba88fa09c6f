"""Limits a shop would set: the shipped configurations and the demos state
what their limits are derived from (``tolerances.basis``, a ``source`` per limit) and no longer
call a 0.1 mm pivot error fit for production; a compensation proposes only the configured
control's addresses ($TC_CARR values were listed for a machine configured as Fanuc)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from benchmarks.rigs.daemon_helpers import CONFIG, thesis_rows, thesis_setup, write_daemon_yaml
from contracts.probing_log import write_log
from contracts.yaml_files import ConfigError
from daemon.config import load_daemon_config
from daemon.machines.setup import TolerancesFile
from demos.limits import tolerances as demo_tolerances
from tests.cli_helpers import run_cli

LIMITED = ("default_translation_um", "default_rotation_urad", "volumetric_max_um")


def shipped() -> list[tuple[str, dict]]:
    out = [("demos/limits.py", demo_tolerances())]
    for name in ("daemon.yaml", "examples/daemon_sim.yaml"):
        doc = yaml.safe_load((CONFIG / name).read_text(encoding="utf-8"))
        out += [(f"config/{name}: {m['name']}", m["tolerances"]) for m in doc["machines"]]
    return out


@pytest.mark.parametrize("where,tol", shipped(), ids=[w for w, _ in shipped()])
def test_shipped_limits_state_their_basis_and_sources(where, tol):
    t = TolerancesFile.model_validate(tol).to_tolerances()
    assert "0.10 mm" in t.basis and "ISO 10791-6" in t.basis, where
    keys = [k for k in LIMITED if k in tol] + [f"links.{k}" for k in tol.get("links", {})]
    assert keys and set(keys) == set(t.sources), (where, keys, t.sources)
    # a 0.1 mm pivot error (the thesis' EX0C −106 µm) is not fit for 0.1 mm parts
    ex0c = t.links.get("EX0C") or t.default_translation_um
    assert ex0c.fail is not None and ex0c.fail < 106 / 3, where
    assert t.volumetric_max_um.fail <= 1e3 * 0.10 / 3, where


def test_basis_and_source_are_checked(tmp_path):
    path = write_daemon_yaml(tmp_path)
    text = path.read_text()
    path.write_text(text.replace("default_translation_um: {warn: 150, fail: 300}",
                                 "default_translation_um: {warn: 150, fail: 300, sauce: x}"))
    with pytest.raises(ConfigError, match=r"default_translation_um\.sauce"):
        load_daemon_config(path)
    path.write_text(text.replace("default_translation_um: {warn: 150, fail: 300}",
                                 "default_translation_um: {warn: 150, fail: 300, source: ''}"))
    with pytest.raises(ConfigError, match=r"default_translation_um\.source"):
        load_daemon_config(path)
    path.write_text(text.replace("    tolerances:\n", "    tolerances:\n      basis: "
                                 "'ISO 10791-6 K2 acceptance, 0.05 mm parts'\n"))
    tol = load_daemon_config(path).machines["mill1"].tolerances
    assert tol.basis == "ISO 10791-6 K2 acceptance, 0.05 mm parts"


def _imported(tmp_path: Path, capsys, dialect: str) -> str:
    cfg = str(write_daemon_yaml(tmp_path, dialect=dialect))
    log = tmp_path / "in.csv"
    write_log(log, thesis_rows(thesis_setup()))
    assert run_cli(["history", "--config", cfg, "--import", str(log), "--machine", "mill1"],
                   capsys)[0] == 0
    return cfg


def test_a_fanuc_machine_is_not_offered_siemens_addresses(tmp_path, capsys):
    cfg = _imported(tmp_path, capsys, "fanuc")  # the thesis file holds $TC_CARR values
    code, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert code == 2, out
    assert "configured as fanuc (daemon.yaml dialect) but its machine file's " \
           "controller_kinematics holds siemens addresses ($TC_CARR4[1], …)" in out
    assert "$TC_CARR15" not in out  # no table of another control's values


def test_the_machines_own_control_gets_its_addresses(tmp_path, capsys):
    cfg = _imported(tmp_path, capsys, "siemens")
    _, out, _ = run_cli(["compensate", "--config", cfg, "synth"], capsys)
    assert "$TC_CARR15[1]" in out and "configured as" not in out, out

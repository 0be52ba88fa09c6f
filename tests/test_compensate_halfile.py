"""LinuxCNC on this PC: the live pins and the persistent HAL file change together or not at
all — failed read-back, planted backup symlink, symlinked HAL file, an edit made
between read and replace; the read-back setting; an import that never reads a live machine.
Real temp directories and symlinks, setp/getp faked (tests/test_compensate_transaction.py)."""

from __future__ import annotations

import json

import pytest
import yaml

from contracts.setup_files import load_machine
from contracts.yaml_files import ConfigError
from daemon.compensation.propose import ControllerModelError, controller_model
from daemon.config import load_daemon_config
from daemon.store.journal import Store
from drivers.linuxcnc import halkins
from tests.cli_helpers import run_cli
from tests.test_compensate import MACHINE, _journal, _world
from tests.test_compensate_transaction import PINS, X, fake_linuxcnc

CONFIRM = ["--confirm", "synth", "--by", "alice"]


def _agree(cfg: str, pins, hal, want: float) -> None:
    """Journal, live value and file say the same: ``want``."""
    assert json.loads(pins.read_text())["pins"][X] == want
    assert f"setp {X} {want}" in hal.read_text() or f"setp {X} {want:.6f}" in hal.read_text()
    store = Store(load_daemon_config(cfg).store_path)
    try:
        from daemon.compensation import journal as cj

        cur = cj.current_values(store, "lcnc")
        assert (cur[X.split(".")[1]].new if cur else PINS[X]) == want
    finally:
        store.close()


def test_failed_read_back_restores_the_pin_and_the_file(tmp_path, capsys, monkeypatch):
    cfg = _world(tmp_path, capsys, host="127.0.0.1")
    pins, hal = fake_linuxcnc(tmp_path, monkeypatch)
    before = hal.read_bytes()
    good = halkins.read_pins
    calls = {"n": 0}

    def flaky(names):  # the first read (journal check) is fine; the read-back is wrong
        calls["n"] += 1
        got = good(names)
        return got if calls["n"] == 1 else {n: v + 0.5 for n, v in got.items()}

    monkeypatch.setattr(halkins, "read_pins", flaky)
    code, out, _ = run_cli(["compensate", "--config", cfg, *CONFIRM], capsys)
    assert code == 2 and "read-back differs" in out and "old values set again" in out, out
    assert "HAL file" in out and "restored" in out and "NOT restored" not in out
    assert hal.read_bytes() == before
    assert [r.state for r in _journal(cfg)] == ["refused"]
    _agree(cfg, pins, hal, 12.5)


def test_backup_is_never_written_through_a_planted_symlink(tmp_path):
    hal = tmp_path / "machine.hal"
    hal.write_text(f"setp {X} 12.5\n")
    victim = tmp_path / "victim"
    (tmp_path / "machine.hal.rumba-20260101T000000.bak").symlink_to(victim)  # dangling
    backup = halkins.replace_file(hal, f"setp {X} 12.6\n", "20260101T000000")
    assert not victim.exists()  # nothing written through the link
    assert backup is not None and backup.name == "machine.hal.rumba-20260101T000000-1.bak"
    assert not backup.is_symlink() and "12.5" in backup.read_text()
    assert "12.6" in hal.read_text()


def test_a_symlinked_hal_file_is_refused_and_left_alone(tmp_path, capsys, monkeypatch):
    cfg = _world(tmp_path, capsys, host="127.0.0.1")
    pins, hal = fake_linuxcnc(tmp_path, monkeypatch)
    real = tmp_path / "real.hal"
    hal.rename(real)
    hal.symlink_to(real.name)
    code, out, _ = run_cli(["compensate", "--config", cfg, *CONFIRM], capsys)
    assert code == 2 and "is a symbolic link" in out and "nothing set" in out, out
    assert hal.is_symlink() and f"setp {X} 12.5" in real.read_text()
    assert json.loads(pins.read_text())["setp"] == 0  # the controller untouched
    assert [r.state for r in _journal(cfg)] == ["refused"]


def test_a_hal_file_over_the_size_limit_is_refused_naming_it(tmp_path, capsys, monkeypatch):
    cfg = _world(tmp_path, capsys, host="127.0.0.1")
    pins, hal = fake_linuxcnc(tmp_path, monkeypatch)
    # the pins' setp lines first (found by hal_file_with), then comments past the limit
    big = hal.read_text() + ("# " + "x" * 98 + "\n") * (halkins.MAX_HAL_BYTES // 100 + 1)
    hal.write_text(big)
    code, out, _ = run_cli(["compensate", "--config", cfg, *CONFIRM], capsys)
    assert code == 2 and f"{hal}: larger than {halkins.MAX_HAL_BYTES} bytes" in out, out
    assert "nothing set" in out and "Traceback" not in out
    assert hal.read_text() == big and json.loads(pins.read_text())["setp"] == 0
    assert [r.state for r in _journal(cfg)] == ["refused"]
    # found through the INI, an oversized HAL file is refused too, never read whole nor skipped
    with pytest.raises(halkins.HalError, match="larger than"):
        halkins.hal_file_with(halkins.running_ini(), [X])
    hal.write_text(big[:halkins.MAX_HAL_BYTES])  # at the limit: read
    assert halkins.read_file(hal) == big[:halkins.MAX_HAL_BYTES].encode()


def test_an_edit_between_read_and_replace_is_refused_not_lost(tmp_path, capsys, monkeypatch):
    cfg = _world(tmp_path, capsys, host="127.0.0.1")
    pins, hal = fake_linuxcnc(tmp_path, monkeypatch)
    setp = halkins.setp

    def operator_edits_meanwhile(pin, value):
        setp(pin, value)
        if not hal.read_text().startswith("# edited"):
            hal.write_text("# edited by the operator\n" + hal.read_text())

    monkeypatch.setattr(halkins, "setp", operator_edits_meanwhile)
    code, out, _ = run_cli(["compensate", "--config", cfg, *CONFIRM], capsys)
    assert code == 2 and "changed since rumba read it" in out, out
    assert hal.read_text().startswith("# edited by the operator")  # the edit is kept
    assert f"setp {X} 12.5\n" in hal.read_text()
    assert [r.state for r in _journal(cfg)] == ["refused"]
    assert json.loads(pins.read_text())["pins"][X] == 12.5  # the live pin set back


def _machine_with(tmp_path, **section) -> str:
    data = yaml.safe_load(MACHINE.read_text())
    data["controller_kinematics"].update(section)
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_read_back_is_a_machine_setting(tmp_path, capsys, monkeypatch):
    with pytest.raises(ConfigError, match="read_back"):
        load_machine(_machine_with(tmp_path, read_back="sometimes"))
    cfg = _world(tmp_path, capsys, host="127.0.0.1")
    conf = load_daemon_config(cfg)

    def unreadable(names):
        raise halkins.HalError("halcmd: no HAL access")

    monkeypatch.setattr(halkins, "read_pins", unreadable)
    store = Store(conf.store_path)
    try:
        setup = conf.machines["lcnc"]
        # when_written (default): never written by rumba → the machine file's model
        assert controller_model(setup, store).axes == setup.machine.axes
        text = MACHINE.read_text().replace("  params:", "  read_back: required\n  params:", 1)
        (tmp_path / "req.yaml").write_text(text)
        cfg2 = cfg.replace("daemon.yaml", "daemon2.yaml")
        (tmp_path / "daemon2.yaml").write_text(
            (tmp_path / "daemon.yaml").read_text().replace(str(MACHINE),
                                                           str(tmp_path / "req.yaml")))
        strict = load_daemon_config(cfg2).machines["lcnc"]
        with pytest.raises(ControllerModelError, match="cannot read the kinematics pins"):
            controller_model(strict, store)
    finally:
        store.close()


def test_offline_import_never_reads_the_live_pins(tmp_path, capsys, monkeypatch):
    def live(names):
        raise AssertionError("an import read the live HAL pins")

    monkeypatch.setattr(halkins, "read_pins", live)
    cfg = _world(tmp_path, capsys, host="127.0.0.1")  # imports inside, LinuxCNC on loopback
    store = Store(load_daemon_config(cfg).store_path)
    try:
        assert store.run("synth").imported and store.analysis("synth") is not None
    finally:
        store.close()

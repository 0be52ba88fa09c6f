"""The LinuxCNC demos' daemon.yaml (one writer, demos.linuxcnc.daemon_yaml) loads as a checked
config naming each demo's machine, machine file, artefact, link and HMI."""

from __future__ import annotations

from pathlib import Path

from daemon.config import load_daemon_config
from demos import compensate, compensate_head, linuxcnc


def _load(tmp: Path, text: str):  # type: ignore[no-untyped-def]
    path = tmp / "daemon.yaml"
    path.write_text(text, encoding="utf-8")
    return load_daemon_config(path)


def test_linuxcnc_demo_yaml_carries_the_hmi_token_file(tmp_path):
    token_file = tmp_path / "hmi.token"
    token_file.write_text("t0k3n-for-tests-0123456789")
    token_file.chmod(0o600)  # as the demo: the config refuses a token others can read
    plan = linuxcnc.CONFIG / "plans/linuxcnc_7poses.yaml"
    text = linuxcnc.daemon_yaml(tmp_path, 5007, plan,
                                hmi=f"{{host: 127.0.0.1, port: 0, token_file: {token_file}}}")
    assert text.startswith("# written by demos/linuxcnc.py\n")
    cfg = _load(tmp_path, text)
    setup = cfg.machines["lcnc-trt"]
    assert cfg.hmi.enabled and cfg.hmi.token_file == str(token_file)
    assert setup.artefact.name == "thesis-4ball" and setup.machine.name == "linuxcnc-xyzbc"
    assert (setup.link.transport, setup.link.port, setup.link.prelude_mdi) == \
        ("linuxcnc", 5007, ["M429"])
    assert cfg.store_path == tmp_path / "journal.sqlite"


def test_compensate_demo_yaml_uses_the_guarded_machine_file(tmp_path):
    machine = compensate.demo_machine_file(tmp_path)
    plan = linuxcnc.CONFIG / "plans/linuxcnc_7poses.yaml"
    text = compensate.daemon_yaml(tmp_path, 5008, plan, machine)
    assert text.startswith("# written by demos/compensate.py\n")
    cfg = _load(tmp_path, text)
    setup = cfg.machines[compensate.MACHINE_NAME]
    assert not cfg.hmi.enabled
    assert setup.machine_file.controller_kinematics.guards.max_change_um == \
        compensate.DEMO_GUARDS["max_change_um"]
    assert setup.artefact.name == "thesis-4ball" and setup.link.port == 5008


def test_head_demo_yaml_names_the_head_and_its_artefact(tmp_path):
    machine = compensate_head.demo_machine_file(tmp_path, unattended=True)
    text = compensate_head.daemon_yaml(tmp_path, 5009, compensate_head.PLAN, machine)
    assert text.startswith("# written by demos/compensate_head.py\n")
    cfg = _load(tmp_path, text)
    setup = cfg.machines[compensate_head.MACHINE_NAME]
    assert setup.machine.name == "linuxcnc-swivelhead"
    assert setup.artefact.name == "vertical-4ball"
    assert setup.machine_file.controller_kinematics.guards.unattended
    assert setup.plan.name == "linuxcnc-swivelhead-9poses" and setup.link.port == 5009

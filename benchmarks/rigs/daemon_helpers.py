"""Shared set-up for the daemon tests: a thesis machine setup and exact synthetic logs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from contracts.probing_log import LogRow
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.machines.setup import MachineSetup, TriggersFile
from daemon.machines.tolerances import Limit, Tolerances
from simulators.exact_log import THESIS_LINKS_UM_URAD, Truth, make_rows, thesis_noise, to_internal

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config"

TOLERANCES = Tolerances(
    default_rotation_urad=Limit(warn=40, fail=80, drift_warn=10, drift_fail=20),
    default_translation_um=Limit(warn=150, fail=300, drift_warn=10, drift_fail=20),
    volumetric_max_um=Limit(warn=200, fail=400),
    residual_rms_um=5.0,
)


def thesis_setup(tolerances: Tolerances = TOLERANCES, plan: str = "thesis_ch3_7poses",
                 name: str = "mill1", touch_timeout_s: float = 30.0) -> MachineSetup:
    m, mf = load_machine(CONFIG / "machines/thesis_wcbxfzyt.yaml")
    a = load_artefact(CONFIG / "artefacts/thesis_4ball.yaml")
    p = load_plan(CONFIG / f"plans/{plan}.yaml")
    return MachineSetup(name, m, mf, a, p, "fanuc", None, TriggersFile(), tolerances,
                        touch_timeout_s, tuple(p.indices("validate")), False)


def thesis_rows(setup: MachineSetup, links_um_urad: dict[str, float] | None = None,
                seed: int = 0) -> list[LogRow]:
    """Exact centres of the thesis machine with Table B.2 link errors, thesis noise."""
    rng = np.random.default_rng(seed + 100)
    truth = Truth(links=to_internal(THESIS_LINKS_UM_URAD if links_um_urad is None
                                    else links_um_urad),
                  balls_mm=rng.normal(0.0, 0.2, (len(setup.artefact.balls), 3)),
                  tip_mm=rng.normal(0.0, 0.02, 3))
    tn, cn = thesis_noise()
    poses = [(p.b_deg, p.c_deg) for p in setup.plan.poses]
    return make_rows(setup.machine, setup.artefact, poses, truth,
                     setup.plan.stylus_radius_mm, tn, cn, seed=seed)


def write_daemon_yaml(tmp: Path, *, token: str = "t0k3n-for-tests-0123456789",
                      link: str = "{transport: opcua, url: 'opc.tcp://127.0.0.1:4840', "
                                  "security: none}",
                      extra_machine: str = "", extra_top: str = "",
                      plan: str = "thesis_ch3_7poses", dialect: str = "fanuc") -> Path:
    """A daemon.yaml in ``tmp`` for machine ``mill1`` (thesis machine, shipped files)."""
    text = f"""
store: {{path: {tmp / 'journal.sqlite'}}}
reports_dir: {tmp / 'reports'}
hmi: {{host: 127.0.0.1, port: 0, token: {token}}}
{extra_top}
machines:
  - name: mill1
    machine: {CONFIG / 'machines/thesis_wcbxfzyt.yaml'}
    artefact: {CONFIG / 'artefacts/thesis_4ball.yaml'}
    plan: {CONFIG / f'plans/{plan}.yaml'}
    dialect: {dialect}
    link: {link}
    touch_timeout_s: 30
    tolerances:
      default_rotation_urad: {{warn: 40, fail: 80, drift_warn: 10, drift_fail: 20}}
      default_translation_um: {{warn: 150, fail: 300}}
      volumetric_max_um: {{warn: 200, fail: 400}}
{extra_machine}
"""
    path = tmp / "daemon.yaml"
    path.write_text(text, encoding="utf-8")
    return path

"""The configuration pages: which schema describes which file, in the order a reader meets them."""

from __future__ import annotations

from docs.gen.schemas import section
from docs.gen.text import header


def daemon_yaml() -> str:
    from daemon.config import DaemonFile
    from drivers.can.schema import CanPanelConfig
    from drivers.linuxcnc.schema import LinuxCncLinkConfig
    from drivers.modbus.schema import ModbusLinkConfig
    from drivers.opcua.schema import OpcUaLinkConfig
    from drivers.serial.schema import SerialLinkConfig

    out = [header("daemon.yaml", "daemon/config.py, daemon/machines/setup.py and the link "
                                 "schemas in drivers/*/schema.py"),
           "The service's configuration (`rumba run --config`, `rumba verify --config`, every "
           "command that reads the journal). Unknown keys are errors; relative paths are "
           "relative to the file; `${VARIABLES}` in paths are expanded (systemd's "
           "`${CREDENTIALS_DIRECTORY}`). Check a file without starting anything with "
           "`rumba run --config FILE --check`. Examples: `config/daemon.yaml` (a shop PC, "
           "commented), `config/examples/daemon_sim.yaml` (the simulator on this computer).\n",
           "## Keys\n", section(DaemonFile, intro="")]
    for title, model in (("serial DNC", SerialLinkConfig), ("OPC UA", OpcUaLinkConfig),
                         ("Modbus TCP", ModbusLinkConfig), ("LinuxCNC", LinuxCncLinkConfig)):
        out += [f"## machines[].link: {title}\n",
                section(model, "machines[].link.")]
    out += ["## can_panel\n", section(CanPanelConfig, "can_panel.")]
    return "\n".join(out)


def machine_yaml() -> str:
    from contracts.setup_files import MachineFile

    return "\n".join([
        header("Machine file", "contracts/setup_files.py and contracts/controller_kinematics.py"),
        "One machine tool's kinematic chain and what bounds its moves (`config/machines/*.yaml`; "
        "`rumba gcode --machine`, `rumba analyze --machine`, daemon.yaml's `machines[].machine`). "
        "The topology string runs from the workpiece to the tool, e.g. `WCBXFZYT` (workpiece on "
        "C on B on X on the foundation F; Z on F, Y on Z, tool on Y). Names that reach a "
        "program or a file name are 1-32 of `A-Za-z0-9_.-`.\n",
        section(MachineFile, intro=""),
    ])


def artefact_yaml() -> str:
    from contracts.setup_files import ArtefactFile

    return "\n".join([
        header("Artefact file", "contracts/setup_files.py"),
        "The master balls on the table (`config/artefacts/*.yaml`): nominal positions in the "
        "last workpiece frame, rod lengths, ball diameter; optionally calibrated distances "
        "(then the linear axes' scale is observable) and the calibration certificate printed "
        "on reports.\n",
        section(ArtefactFile, intro=""),
    ])


def plan_yaml() -> str:
    from contracts.plan_files import PlanFile
    from contracts.plan_targets import TargetsFile

    return "\n".join([
        header("Plan and target files", "contracts/plan_files.py and contracts/plan_targets.py"),
        "A plan (`config/plans/*.yaml`) says which poses are probed and how: the stylus, the "
        "poses as a list or a grid, feeds, standoff, overtravel, held-out poses and the drift "
        "check. A target file (`config/plans/targets/*.yaml`) is what `rumba plan` optimises "
        "a plan for.\n",
        "## Plan\n", section(PlanFile, intro=""),
        "## Targets (`rumba plan --target`)\n", section(TargetsFile, intro=""),
    ])


def errors_yaml() -> str:
    from simulators.errors_schema import ErrorsFile
    from simulators.faults import FaultsFile

    return "\n".join([
        header("Simulator files", "simulators/errors_schema.py and simulators/faults.py"),
        "The software CNC's truth (`rumba sim --errors`, `config/errors/*.yaml`): link and setup "
        "errors, probe physics, index scatter, effects the identification does not model, a "
        "thermal state; and the faults it can inject (`rumba sim --faults`, "
        "`config/faults/*.yaml`). Without an errors file the simulated machine is perfect.\n",
        "## Errors file\n", section(ErrorsFile, intro=""),
        "## Faults file\n", section(FaultsFile, intro=""),
    ])

"""One command line for both LinuxCNC demos (``demos.linuxcnc.run_demo``): --plan/--out, a kept
temp folder by prefix, the demo's expected failures as one line and exit code 2."""

from __future__ import annotations

from pathlib import Path

import pytest

from demos.linuxcnc import CONFIG, run_demo


def test_plan_and_out_reach_the_demo(tmp_path):
    seen = []

    async def demo(plan: Path, out: Path) -> int:
        seen.append((plan, out))
        return 0

    assert run_demo("demos.x", "rumba-demo-x-", demo, (RuntimeError,),
                    ["--out", str(tmp_path / "o")]) == 0
    assert seen == [((CONFIG / "plans/linuxcnc_7poses.yaml").resolve(), tmp_path / "o")]
    assert (tmp_path / "o").is_dir()


def test_a_new_temp_folder_by_prefix(tmp_path, monkeypatch):
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    outs = []

    async def demo(plan: Path, out: Path) -> int:
        outs.append(out)
        return 3

    assert run_demo("demos.x", "rumba-demo-x-", demo, (RuntimeError,), []) == 3
    assert outs[0].parent == tmp_path.resolve() and outs[0].name.startswith("rumba-demo-x-")


def test_expected_failures_are_one_line_others_propagate(capsys):
    async def refused(plan: Path, out: Path) -> int:
        raise RuntimeError("peer refused")

    assert run_demo("demos.x", "p-", refused, (RuntimeError,), ["--out", "/tmp"]) == 2
    assert capsys.readouterr().err == "demos.x: peer refused\n"
    with pytest.raises(RuntimeError):
        run_demo("demos.x", "p-", refused, (KeyError,), ["--out", "/tmp"])

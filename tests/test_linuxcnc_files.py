"""The files a headless LinuxCNC instance runs on (simulators/linuxcnc_files.py), without
LinuxCNC: the shipped INIs patched for linuxcncrsh on a port, and the HAL probe's net file."""

from __future__ import annotations

import re

import pytest

from simulators.linuxcnc_files import REPO, probe_net, write_ini, write_probe_hal
from simulators.linuxcnc_peer import CONFIG


@pytest.mark.parametrize("ini", ["rumba_xyzbc.ini", "rumba_swivelhead.ini"])
def test_the_ini_gets_the_port_the_program_folder_and_the_probe_after_its_hal(tmp_path, ini):
    src = CONFIG / ini
    probe = tmp_path / "config" / "rumba_probe.hal"
    write_ini(src, tmp_path / ini, 51234, tmp_path / "nc_files", probe)
    old, new = src.read_text().splitlines(), (tmp_path / ini).read_text().splitlines()
    assert "DISPLAY = linuxcncrsh --port 51234" in new
    assert f"PROGRAM_PREFIX = {tmp_path / 'nc_files'}" in new
    hal = new.index(f"HALFILE = {src.stem}.hal")
    assert new[hal + 1] == f"HALFILE = {probe}" and new.count(f"HALFILE = {probe}") == 1
    # nothing else changed: the same lines but the two rewritten and the one added
    assert len(new) == len(old) + 1
    changed = [(a, b) for a, b in zip(old, new[:hal + 1] + new[hal + 2:], strict=True) if a != b]
    assert [b.split("=")[0].strip() for _, b in changed] == ["DISPLAY", "PROGRAM_PREFIX"]
    # the comment lines naming DISPLAY stay comments
    assert [ln for ln in old if ln.startswith("#")] == [ln for ln in new if ln.startswith("#")]


def test_without_a_probe_no_hal_file_is_added(tmp_path):
    write_ini(CONFIG / "rumba_xyzbc.ini", tmp_path / "x.ini", 5007, tmp_path / "nc", None)
    assert sum(ln.startswith("HALFILE") for ln in (tmp_path / "x.ini").read_text().splitlines()) \
        == 2


def test_the_probe_hal_feeds_the_joints_and_gates_the_trip_to_probing_moves(tmp_path):
    spec = tmp_path / "probe_spec.json"
    spec.write_text('{"ball_ids": ["B1", "B2", "B3"]}')
    write_probe_hal(tmp_path / "p.hal", spec)
    text = (tmp_path / "p.hal").read_text()
    assert text.splitlines()[0] == (f"loadusr -Wn rumba-probe /usr/bin/python3 "
                                    f"{REPO}/simulators/hal_probe.py {spec.resolve()}")
    assert re.findall(r"^net rumba-j(\d) joint\.(\d)\.pos-fb => rumba-probe\.(\w)$", text,
                      flags=re.M) == [(str(i), str(i), a) for i, a in enumerate("xyzbc")]
    # one sphere test per ball of the spec, in the servo thread
    assert re.findall(r"^loadrt hypot names=(\S+)$", text, flags=re.M) == [
        "rumba-b0-d,rumba-b1-d,rumba-b2-d"]
    # the touch reaches motion only while probing (motion type 5) and with a valid set; a
    # crash in any move
    assert "setp rumba-probing.min 4.5\nsetp rumba-probing.max 5.5\n" in text
    assert "net rumba-probe-gated rumba-probe-gate.out => rumba-probe-any.in0" in text
    assert "motion.feed-inhibit" not in text  # netted, LinuxCNC AUTO raced (README)
    assert text.endswith("net rumba-probe-trip rumba-probe-any.out => motion.probe-input\n")
    # every function loaded is added to the servo thread, once
    names = [n for ln in text.splitlines() if ln.startswith("loadrt ")
             for n in ln.split("names=")[1].split(",")]
    addf = re.findall(r"^addf (\S+) servo-thread$", text, flags=re.M)
    assert sorted(names) == sorted(addf) and len(set(addf)) == len(addf)
    with pytest.raises(ValueError, match="at least one ball"):
        probe_net(0)

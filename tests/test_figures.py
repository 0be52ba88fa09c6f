"""Each figure's name and definition, and the plain and controller names of
the link errors per configured controller family (item 4), from the shipped machine files."""

from __future__ import annotations

import pytest

from benchmarks.rigs.daemon_helpers import CONFIG
from contracts.setup_files import load_machine
from daemon.analysis.figures import (
    DEFINITIONS,
    LABELS,
    controller_term,
    link_label,
    plain_name,
    plan_figures,
    run_figures,
)
from daemon.analysis.result import Analysis, VolumetricPoint
from daemon.compensation.propose import spec_of


class _Setup:
    def __init__(self, name: str) -> None:
        self.machine, self.machine_file = load_machine(CONFIG / f"machines/{name}.yaml")
        self.name = name


def test_every_figure_has_a_name_and_a_one_sentence_definition():
    assert set(LABELS) == set(DEFINITIONS)
    for key, text in DEFINITIONS.items():
        assert text and "." not in text.rstrip(".").replace("Eq. 3.22", ""), key  # one sentence
    a = Analysis(volumetric=(VolumetricPoint(0, error_um=(3.0, 4.0, 0.0),
                                             error_after_links_um=(0.3, 0.4, 0.0)),
                             VolumetricPoint(1, role="validate", held_out=True,
                                             error_um=(0.0, 0.0, -12.04),
                                             error_after_links_um=(0.0, 0.0, 0.1))))
    vol, after = run_figures(a)
    assert (vol.value, after.value) == (12.0, 0.5)  # held-out poses count: "probed poses"
    assert vol.text() == "max volumetric distortion (probed poses) 12.0 µm"
    assert run_figures(Analysis())[0].text() == "max volumetric distortion (probed poses) —"
    figs = plan_figures((39.68, 55.78), (2.66, 4.10))
    assert [f.value for f in figs] == [39.7, 55.8, 2.7, 4.1]
    assert not any("compensable" in f.label for f in figs)


@pytest.mark.parametrize("iso, words", [
    ("EX0C", "X offset of the C axis line"), ("EY0B", "Y offset of the B axis line"),
    ("EA0C", "tilt of the C axis line about X"), ("EB0C", "tilt of the C axis line about Y"),
    ("EB0Z", "squareness of the Z axis about Y"), ("EC0Y", "squareness of the Y axis about Z"),
    ("XYZ", "XYZ"),
])
def test_plain_names(iso, words):
    assert plain_name(iso) == words


@pytest.mark.parametrize("machine, iso, term", [
    # Siemens: c-x moves the C line alone ($TC_CARR15), b-x moves B and C together (no term)
    ("thesis_wcbxfzyt", "EX0C", "Siemens $TC_CARR15[1] (c-x)"),
    ("thesis_wcbxfzyt", "EB0C", "Siemens $TC_CARR10[1] (c-tilt-b)"),
    ("thesis_wcbxfzyt", "EB0Z", None),
    # LinuxCNC xyzbc-trt: x-offset moves B alone, ≡ −EX0C; the rot-points move both
    ("linuxcnc_xyzbc", "EX0C", "LinuxCNC xyzbc-trt-kins.x-offset (x-offset)"),
    # Haas (a vertical WCAYFXZT): the C table's MRZP x setting
    ("vertical_wcayfxzt", "EX0C", "Haas 255 (mrzp-x)"),
])
def test_controller_terms_per_family(machine, iso, term):
    spec = spec_of(_Setup(machine))
    got = controller_term(iso, spec)
    if term is None:
        assert got is None
    else:
        assert got is not None and got.endswith(term), got
    assert link_label(iso, spec).startswith(f"{iso} — {plain_name(iso)}")
    assert link_label(iso, None) == f"{iso} — {plain_name(iso)}"

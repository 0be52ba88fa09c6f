"""Ball centres fitted in the frame the estimate corrects (identification/touch_frame.py,
METHOD.md §7): on axes out of square the touches lie on an ellipsoid in controller axes, and a
sphere fitted there is off the chain's centre by a pose-dependent bias; fitted in the frame the
estimate's chain maps them to, it is not."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from benchmarks.rigs.daemon_helpers import CONFIG, TOLERANCES
from contracts.messages import TOUCH_DIRECTIONS
from contracts.probing_log import read_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis import pipeline
from daemon.analysis.identify import analyse_centres
from daemon.analysis.touch_centres import rows_to_centres, screen_centres
from daemon.compensation.identified import centres_of, estimation_centres, identify
from daemon.machines.setup import MachineSetup, TriggersFile
from identification.estimate import estimate
from identification.touch_frame import fit_in_frame
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.truth import TruthModel

DIRS = np.array(list(TOUCH_DIRECTIONS.values()))
R_MM = 15.7
# the probing repeatability the u of the fork-head runs below rest on (its errors file's)
SIGMA_UM = [0.625, 0.957, 0.285]


def _sheared(seed: int, g: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(maps A (g, 3, 3), true centres (g, 3), touches (g, 5, 3)): touches along the five
    directions d, tilted per group as a head tilts them, where |A (q − c)| = R."""
    rng = np.random.default_rng(seed)
    shear = np.eye(3) + rng.uniform(-400e-6, 400e-6, (g, 3, 3))
    rot = np.linalg.qr(rng.normal(size=(g, 3, 3)))[0]
    maps = rot @ shear
    c = rng.uniform(-300, 300, (g, 3))
    tilt = np.linalg.qr(np.eye(3) + 0.4 * rng.normal(size=(g, 3, 3)))[0]
    d = np.einsum("gij,tj->gti", tilt, DIRS)
    rho = R_MM / np.linalg.norm(np.einsum("gij,gtj->gti", maps, d), axis=2)
    return maps, c, c[:, None, :] - d * rho[..., None]


@pytest.mark.parametrize("fixed", [False, True])
def test_the_mapped_fit_returns_the_chains_centre(fixed):
    maps, c, pts = _sheared(1)
    ff = fit_in_frame(pts, R_MM, maps, fixed_radius=fixed)
    assert np.abs(ff.fit.centre_mm - c).max() < 1e-9
    assert np.abs(ff.fit.radius_dev_um).max() < 1e-6 and ff.fit.form_rms_um.max() < 1e-6
    # in controller axes the same touches give a centre off by tenths of a µm
    raw = fit_in_frame(pts, R_MM, None, fixed_radius=fixed)
    assert np.abs(raw.fit.centre_mm - c).max() > 1e-4


@pytest.mark.parametrize("fixed", [False, True])
def test_the_sensitivity_is_the_mapped_fits_derivative(fixed):
    """∂centre/∂touch in controller axes (the drift-aware fit's ``touch_sens``): sums to I
    (a translation of the touches moves the centre by it) and is the fit's derivative."""
    maps, _, pts = _sheared(2, g=1)
    pts = pts + np.random.default_rng(3).normal(0, 1e-3, pts.shape)
    ff = fit_in_frame(pts, R_MM, maps, fixed_radius=fixed)
    np.testing.assert_allclose(ff.sens.sum(axis=1)[0], np.eye(3), atol=1e-9)
    h = 1e-5
    for i in range(5):
        for a in range(3):
            q = pts.copy()
            q[0, i, a] += h
            fd = (fit_in_frame(q, R_MM, maps, fixed).fit.centre_mm - ff.fit.centre_mm)[0] / h
            np.testing.assert_allclose(ff.sens[0, i, :, a], fd, atol=1e-3)


SQUARENESS = {"EA0C": -19.0, "EB0C": 26.0, "EY0A": 48.0, "EB0A": -31.0, "EC0A": 14.0,
              "EC0Y": 300.0, "EA0Z": -200.0, "EB0Z": 250.0}  # µrad, µm: a few hundred µrad


def _fork_rows(links: dict[str, float], noise: bool = False):
    """(machine, machine file, artefact, plan, log rows, stylus radius) of a simulated run of
    the fork head's shipped plan with these link errors; noise-free unless ``noise`` (the
    errors file's touch and centre noise)."""
    machine, mf = load_machine(CONFIG / "machines/forkhead_wxfyzcat.yaml")
    artefact = load_artefact(CONFIG / "artefacts/vertical_4ball.yaml")
    plan = load_plan(CONFIG / "plans/forkhead_11poses.yaml")
    probe = {"stylus_diameter_mm": 6, "touch_noise_um": 0.3 if noise else 0.0}
    if noise:
        probe["centre_noise_um"] = SIGMA_UM
    errors = {"machine": machine.name, "seed": 0, "links": links,
              "setup": {"balls_um": {"B1": [212, -184, 95], "B2": [-241, 166, -150],
                                     "B3": [178, 241, 121], "B4": [-205, -127, -168]},
                        "probe_um": [45, -110, 180]},
              "probe": probe}
    truth = TruthModel.build(machine, mf, artefact, errors_from_dict(errors))
    d = get_dialect("heidenhain")
    prog = build_program(machine, mf, artefact, plan, two_speed=False)
    res = run_sync(truth, d.render(prog), "heidenhain", files=d.aux_files(prog), seed=0)
    assert res.state == "done", res.alarm
    return machine, mf, artefact, plan, res.rows, truth.stylus_radius_mm


def _fork_run(links: dict[str, float]):
    """A noise-free simulated run of the fork head, its centres fitted in controller axes."""
    machine, _, artefact, _, rows, stylus_r = _fork_rows(links)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = rows_to_centres(rows, artefact, stylus_r)
    return machine, artefact, data


def test_a_fork_head_out_of_square_gives_its_links_without_bias():
    """Noise-free, squareness of a few hundred µrad: fitted in controller axes the centres
    put EB0C 1.4u off its truth; the analysis, fitting them in its estimate's frame, returns
    every link within 0.1u, the true ball (radius and form) and the touch sensitivities."""
    links = SQUARENESS
    machine, artefact, data = _fork_run(links)
    with np.errstate(all="ignore"):
        raw = estimate(machine, artefact, screen_centres(machine, artefact, data)[0].centres,
                       sigma_um=SIGMA_UM).links_si()
        keep: dict = {}
        out = analyse_centres(machine, artefact, data, repeatability_um=SIGMA_UM, keep=keep)
    z_raw = {k: (v - links[k]) / s for k, (v, s, _) in raw.items()}
    assert max(abs(z) for z in z_raw.values()) > 0.5, z_raw  # the bias, in controller axes
    z = {k: (v.value - links[k]) / v.std for k, v in out.links.items()}
    assert max(abs(x) for x in z.values()) < 0.1, z
    sf = out.estimation.sphere_frame
    assert sf is not None and sf.note == "" and 2 <= sf.passes <= 4
    assert 0.5 < sf.max_shift_um < 5.0
    # the health figures are the true ball's: no sheared form residual, no radius change
    assert max(h.form_rms_um for h in data.health) > 1.0  # controller axes: the shear
    assert max(h.form_rms_um for h in out.health) < 1e-3
    assert max(abs(h.radius_dev_um) for h in out.health) < 1e-3
    # the centres the store and --write-centres get are the estimate's, with sensitivities
    # that still sum to I (the drift-aware fit's columns)
    got = keep["touch_data"].centres
    assert np.linalg.norm(got.xyz_mm - data.centres.xyz_mm, axis=1).max() * 1e3 == \
        pytest.approx(sf.max_shift_um, abs=1e-3)
    np.testing.assert_allclose(got.touch_sens.sum(axis=1),
                               np.broadcast_to(np.eye(3), (len(got), 3, 3)), atol=1e-9)


def test_a_square_machine_keeps_its_figures():
    """The thesis machine's shipped example log: the refit moves no centre by a nanometre,
    one pass, every link within 0.01u of the controller-axes fit's."""
    machine, _ = load_machine(CONFIG / "machines/thesis_wcbxfzyt.yaml")
    artefact = load_artefact(CONFIG / "artefacts/thesis_4ball.yaml")
    data = rows_to_centres(read_log(CONFIG / "examples/thesis_annexB_14poses.csv", artefact),
                           artefact, 3.0)
    with np.errstate(all="ignore"):
        raw = estimate(machine, artefact, data.centres).links_si()
        out = analyse_centres(machine, artefact, data)
    sf = out.estimation.sphere_frame
    assert sf is not None and sf.passes == 1 and sf.max_shift_um < 1e-3
    for k, (v, s, _) in raw.items():
        assert abs(out.links[k].value - v) < 0.01 * s, k


def test_the_store_keeps_the_centres_the_estimate_used():
    """A daemon run out of square: the centres it stores are those fitted in the estimate's
    frame, so the compensation's estimate from the store (``compensation.identified``) gives
    the run's links (from controller-axes centres EA0C differs by 0.6u)."""
    machine, mf, artefact, plan, rows, _ = _fork_rows(SQUARENESS, noise=True)
    setup = MachineSetup("fork", machine, mf, artefact, plan, "heidenhain", None,
                         TriggersFile(), TOLERANCES, 30.0, tuple(plan.indices("validate")),
                         False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = pipeline.analyse(setup, [pipeline.row_to_hit(r, machine) for r in rows], "r1")
    assert run.data.estimation.sphere_frame.max_shift_um > 0.5
    stored = estimation_centres(setup, centres_of(setup, run.centre_rows, "r1"))
    again = identify(setup, stored, "r1", machine).links_si()
    for k, v in run.data.links.items():
        assert again[k][0] == pytest.approx(v.value, abs=1e-3 * v.std), k

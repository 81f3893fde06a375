"""The PEDS supercell surrogate (issue #34): low-truncation supercell solves with matched unit cells, one
complex coefficient per level.  Checked against exact facts, not its own output: four identical pillars are
the library's unit cell whatever the coefficients; a lattice translation leaves t unchanged and the x <-> y
mirror swaps the polarisations (the solver's symmetries, kept by shared coefficients); least squares recovers
known coefficients; calibrated against labels solved at one of its own levels it becomes that level exactly
(coefficients 0 and 1, error at round-off); the CLI's bad inputs are one line and write nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest

from metadesign.library.coupling import lpa_t, transpose_supercells
from metadesign.library.peds import PedsModel, certified_t, fit_peds, load_peds, low_fidelity_couplings, peds_t, save_peds
from metadesign.library.store import interpolate_t
from metadesign.validation import ValidationError

LEVELS = (25, 41)  # tiny truncations: the facts below hold at any truncation
COEF = (0.3 - 0.7j, 1.2 + 0.4j)


def _widths(n, seed=0):
    return np.random.default_rng(seed).uniform(0.15e-6, 0.45e-6, size=(n, 2, 2, 2))


@pytest.fixture(scope="module")
def model(paper_library):
    return PedsModel(LEVELS, COEF, paper_library.identity)


def test_identical_pillars_are_the_unit_cell(model, paper_library, tmp_path):
    w = _widths(3, 1)[:, :1, :1].repeat(2, 1).repeat(2, 2)
    t = certified_t(paper_library, w, tmp_path / "p", model)
    ref = interpolate_t(paper_library, w[:, 0, 0, 0], w[:, 0, 0, 1])[0]
    np.testing.assert_allclose(t, ref, atol=1e-8)


def test_symmetries_of_the_lattice(model, paper_library, tmp_path):
    """Rows or columns swapped (a translation by one pitch): the same t; x <-> y mirrored: t_x and t_y swap.
    And the correction is not trivially zero."""
    w = _widths(3, 2)
    t = certified_t(paper_library, w, tmp_path / "p", model)
    for shifted in (w[:, ::-1], w[:, :, ::-1]):
        np.testing.assert_allclose(certified_t(paper_library, shifted, tmp_path / "p", model), t, atol=1e-6)
    np.testing.assert_allclose(certified_t(paper_library, transpose_supercells(w), tmp_path / "p", model),
                               t[:, ::-1], atol=1e-6)  # the library table is float32
    tu = interpolate_t(paper_library, w[..., 0], w[..., 1])[0]
    assert np.abs(t - lpa_t(tu)).min() > 1e-3


def test_least_squares_recovers_known_coefficients():
    rng = np.random.default_rng(3)
    c = rng.normal(size=(3, 40, 2)) + 1j * rng.normal(size=(3, 40, 2))
    a = np.array([0.5 + 0.2j, -1.0j, 2.0])
    np.testing.assert_allclose(fit_peds(c, np.tensordot(a, c, axes=1)), a, atol=1e-12)
    lpa = rng.normal(size=(40, 2)) + 0j
    np.testing.assert_allclose(peds_t(a, c, lpa) - lpa, np.tensordot(a, c, axes=1))


def test_calibrated_on_one_of_its_levels_it_is_that_level(paper_library, tmp_path):
    """Labels solved at the top level (LPA + the coupling measured there, as a table at another truncation
    holds them): the fit gives that level coefficient 1 and the other 0, and the held-out error is round-off;
    the report's learning curve, levels and cost are there."""
    from metadesign.library.supercells import SupercellTable, matched_unit_harmonics, solve_table
    from metadesign.studies.supercells import PedsSettings, certify_peds

    w = _widths(8, 4)
    ns, nu = matched_unit_harmonics(LEVELS[1], paper_library.stack)
    t, nG, _, t_unit = solve_table(w, paper_library.stack, ns, tmp_path / "labels", unit_harmonics=nu)
    test = np.arange(8) % 2 == 1
    table = SupercellTable(w, t, np.zeros(8, int), test, {"n_harmonics": nG}, t_unit)
    m, rep = certify_peds(table, paper_library, PedsSettings(LEVELS, (2, 4), probe_rows=1, probe_label=False),
                          tmp_path / "p")
    np.testing.assert_allclose(m.coef, [0, 1], atol=1e-8)
    assert rep["mean_both"] < 1e-8 and rep["passed"]
    assert [c["supercells"] for c in rep["learning_curve"]] == [2, 4]
    assert rep["levels"][1]["n_harmonics"] == nG and rep["levels"][1]["alone"]["max"][0] < 1e-8
    assert rep["levels"][0]["alone"]["mean"][0] > 1e-4  # the lower level alone is not the labels
    assert rep["cost"]["seconds_per_supercell_core"] > 0


def test_saved_model_round_trips_and_checks_its_library(model, paper_library, tmp_path):
    p = save_peds(tmp_path / "m.json", model)
    back = load_peds(p, paper_library)
    assert back == model
    rec = json.loads(p.read_text())
    rec["library"]["sha256"] = "0" * 64
    p.write_text(json.dumps(rec))
    with pytest.raises(ValidationError, match="another library"):
        load_peds(p, paper_library)
    with pytest.raises(ValidationError, match="ascending"):
        PedsModel((41, 25), COEF)
    with pytest.raises(ValidationError, match="another library"):
        certified_t(paper_library, _widths(1), tmp_path / "p", PedsModel(LEVELS, COEF, "f" * 64))
    p.write_text(json.dumps({"format": rec["format"], "coef": [[1, 0]]}))
    with pytest.raises(ValidationError, match="needs harmonics"):
        load_peds(p)


def test_resolved_couplings_are_resumable(paper_library, tmp_path):
    """A second call on the same rows solves nothing (content-keyed chunks) and returns the same bytes."""
    w = _widths(4, 5)
    c1, n1 = low_fidelity_couplings(w, paper_library.stack, LEVELS, tmp_path / "p", chunk_size=2)
    stamp = {f: f.stat().st_mtime_ns for f in (tmp_path / "p").rglob("*.npz")}
    c2, n2 = low_fidelity_couplings(w, paper_library.stack, LEVELS, tmp_path / "p", chunk_size=2)
    assert n1 == n2 and c1.tobytes() == c2.tobytes()
    assert stamp == {f: f.stat().st_mtime_ns for f in (tmp_path / "p").rglob("*.npz")}


@pytest.mark.parametrize("args, msg", [
    (["--harmonics", "97", "900"], "below the table's truncation"),
    (["--harmonics", "93", "97"], "solve the same truncation"),
    (["--harmonics", *map(str, range(40, 130, 10)), "--select"], "at most 8 candidate levels"),
])
def test_cli_bad_levels_are_one_line(args, msg, tmp_path, capsys):
    from conftest import REPO, run_main

    out = tmp_path / "peds.json"
    rc, _, err = run_main(["library", "peds", REPO / "library" / "paper-supercells.npz", *args, "-o", out], capsys)
    assert rc == 2 and len(err) == 1 and msg in err[0], err
    assert not out.exists() and not (tmp_path / "peds.json.partial").exists()


def test_selected_model_is_what_the_report_says(paper_library, tmp_path):
    """With --select the model holds the chosen levels only, its coefficients are the last learning-curve
    fit's, and its cost is the chosen levels' (labels solved at the top candidate: every subset holding it
    is exact, the cheapest of them, the top level alone, is kept)."""
    from metadesign.library.supercells import SupercellTable, matched_unit_harmonics, solve_table
    from metadesign.studies.supercells import PedsSettings, certify_peds

    levels = (25, 33, 41)
    w = _widths(10, 6)
    ns, nu = matched_unit_harmonics(levels[-1], paper_library.stack)
    t, nG, _, t_unit = solve_table(w, paper_library.stack, ns, tmp_path / "labels", unit_harmonics=nu)
    table = SupercellTable(w, t, np.zeros(10, int), np.arange(10) % 2 == 1, {"n_harmonics": nG}, t_unit)
    m, rep = certify_peds(table, paper_library, PedsSettings(levels, (5,), select=True, probe_rows=1,
                                                             probe_label=False), tmp_path / "p")
    assert m.harmonics == (levels[-1],) and rep["selection"]["chosen"] == [2]
    np.testing.assert_allclose(np.array(m.coef), [complex(*c) for c in rep["learning_curve"][-1]["coef"]])
    np.testing.assert_allclose(m.coef, [1], atol=1e-8)
    assert [lv["chosen"] for lv in rep["levels"]] == [False, False, True]
    assert rep["cost"]["seconds_per_supercell_core"] == rep["levels"][2]["seconds_per_supercell_core"]


def test_level_selection_uses_the_fitting_rows_only_and_prefers_the_cheap():
    """Labels that are level 2 exactly (plus a little noise): every subset holding level 2 cross-validates
    alike, and the cheapest of them (level 2 alone) is chosen; rows outside ``rows`` (the held-out ones)
    can be anything without changing the choice or the scores."""
    from metadesign.studies.supercells import select_levels

    rng = np.random.default_rng(7)
    c = rng.normal(size=(3, 200, 2)) + 1j * rng.normal(size=(3, 200, 2))
    tu = np.ones((200, 2, 2, 2), complex)
    target = (0.8 - 0.3j) * c[2] + 1e-3 * rng.normal(size=(200, 2))
    rows = np.arange(150)
    sel = select_levels(c, target, rows, tu, cost=[0.01, 0.05, 0.2])
    assert sel["chosen"] == [2]
    assert len(sel["subsets"]) == 7
    worst = max(sel["subsets"], key=lambda r: r["cv_mean"])
    assert 2 not in worst["levels"] and worst["cv_mean"] > 0.5
    scrambled = target.copy()
    scrambled[150:] = 99.0
    again = select_levels(c, scrambled, rows, tu, cost=[0.01, 0.05, 0.2])
    assert again == sel


def test_neighbour_ring_vanishes_for_a_repeat_and_keeps_the_lattice_symmetries(paper_library, tmp_path):
    """The ring term of a 4 x 4 patch (its periodic t minus its four supercells' mean, matched truncations):
    none for a patch repeating one supercell (the same periodic structure); the same for the patch translated
    by one supercell (the same lattice, the same four supercells); t_x and t_y swapped for the x <-> y mirror
    image; and not trivially zero for four different supercells."""
    from metadesign.library.peds import ring_couplings

    st = paper_library.stack
    rng = np.random.default_rng(5)
    sc = rng.uniform(0.15e-6, 0.45e-6, size=(2, 2, 2))
    mixed = rng.uniform(0.15e-6, 0.45e-6, size=(4, 4, 2))
    patches = np.stack([np.tile(sc, (2, 2, 1)), mixed, np.roll(mixed, 2, axis=1), np.roll(mixed, 2, axis=0),
                        mixed[:, :, ::-1].transpose(1, 0, 2)])
    c = ring_couplings(patches, st, [25], tmp_path / "ring")[0]
    assert np.abs(c[0]).max() < 1e-10
    assert np.abs(c[1]).min() > 1e-3
    np.testing.assert_allclose(c[2], c[1], atol=1e-9)
    np.testing.assert_allclose(c[3], c[1], atol=1e-9)
    np.testing.assert_allclose(c[4], c[1, ::-1], atol=1e-9)
    again = ring_couplings(patches[1:2], st, [25], tmp_path / "ring")[0]  # resumed: nothing solved, same bytes
    assert again.tobytes() == c[1:2].tobytes()


def test_overlapping_windows_of_a_patch_and_of_a_device_agree():
    """The patch study's ring (the mean of a periodic patch's sixteen 2 x 2 windows minus its four
    supercells') equals the device path's (each supercell's three straddling windows, window_ring) averaged
    over the patch's four supercells, their neighbourhoods wrapped round the period; any response ``t`` of
    a window will do, and the supercells are the four aligned windows."""
    from metadesign.library.peds import neighbour_windows, patch_windows, window_ring

    rng = np.random.default_rng(11)
    w = rng.uniform(0.1, 0.5, size=(3, 4, 4, 2))
    a = rng.normal(size=8) + 1j * rng.normal(size=8)

    def t(win):  # (..., 2, 2, 2) -> (..., 2): some nonlinear response of a window
        f = win.reshape(*win.shape[:-3], 8)
        return np.stack([np.exp(1j * f @ a.real) * f[..., 0], np.tanh(f @ a.imag) + f[..., 3] ** 2], -1)

    pw = patch_windows(w)
    np.testing.assert_array_equal(pw[:, 10], w[:, 2:4, 2:4])  # window (2, 2): a supercell
    np.testing.assert_array_equal(pw[:, 3], w[:, [0, 1]][:, :, [3, 0]])  # window (0, 3) wraps round
    tw = t(pw)
    patch_ring = tw.mean(1) - tw[:, [0, 2, 8, 10]].mean(1)
    device = []
    for i in (0, 2):
        for j in (0, 2):
            nb = np.roll(w, (-i, -j), axis=(1, 2))[:, :3, :3]
            device.append(window_ring(t(neighbour_windows(nb)), t(w[:, i:i + 2, j:j + 2])))
    np.testing.assert_allclose(np.mean(device, 0), patch_ring, atol=1e-12)

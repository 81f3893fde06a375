"""Layered and supercell RCWA (the LPA check and tapered pillars) against exact references: the single-pillar
solver, the analytic Fabry-Perot slab, translation symmetry (four identical pillars = the unit cell at the
matched truncation), mirror symmetry (the two-sector solve = the full coupled solve, no cross-polarisation),
and energy conservation."""

from __future__ import annotations

import numpy as np
import pytest

from metadesign.library.rcwa import (
    Factorization,
    SolverSettings,
    Stack,
    fabry_perot_t,
    permittivity_matrices,
    solve_cell,
)
from metadesign.library.supercell import (
    Rect,
    solve_layers,
    solve_supercell,
    solve_tapered,
    staircase_permittivity,
    supercell_rects,
    tapered_layers,
)

ST = Stack()
MIXED = np.array([[(205e-9, 285e-9), (320e-9, 305e-9)], [(320e-9, 200e-9), (345e-9, 270e-9)]])


def test_one_centred_rectangle_is_the_library_factorization():
    import grcwa

    obj = grcwa.obj(60, [1.0, 0.0], [0.0, 1.0], 0.5, 0.0, 0.0, verbose=0)
    obj.Add_LayerUniform(0.0, 1.0)
    obj.Init_Setup(Gmethod=0)
    G = np.asarray(obj.G)
    a = staircase_permittivity(G, 1.0, [Rect(0, 0, 0.43, 0.29)], 12.1, 1.0)
    b = permittivity_matrices(G, 0.43, 0.29, 12.1, 1.0, Factorization.LI)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, atol=1e-12)


def test_sliced_and_90_degree_tapered_pillars_equal_the_vertical_one():
    ref = solve_cell(0.3e-6, 0.2e-6, ST, SolverSettings(60))
    sliced = solve_layers([(ST.height / 3, [Rect(0, 0, 0.3e-6, 0.2e-6)])] * 3, ST.period, ST, 60, symmetric=True)
    np.testing.assert_allclose(sliced.jones, ref.jones, atol=1e-9)
    np.testing.assert_allclose(solve_tapered(0.3e-6, 0.2e-6, 90.0, 4, ST, SolverSettings(60)).jones, ref.jones, atol=1e-9)
    # an 85 degree wall is a different pillar: the widths change by 2 (h/2) cot(85 deg) = 105 nm top to bottom
    lay = tapered_layers(0.3e-6, 0.2e-6, ST.height, 85.0, 4)
    assert lay[0][1][0].wx - lay[-1][1][0].wx == pytest.approx(2 * ST.height * 0.75 / np.tan(np.deg2rad(85)), rel=1e-9)
    assert abs(solve_tapered(0.3e-6, 0.2e-6, 85.0, 4, ST, SolverSettings(60)).t_x - ref.t_x) > 1e-3


def test_supercell_of_identical_pillars_is_the_unit_cell():
    """Translation symmetry: at the matched truncation (the unit cell's harmonics = the supercell's even
    ones) the odd harmonics decouple and the supercell is the unit cell exactly."""
    from metadesign.library.supercells import matched_unit_harmonics

    ns, nu = matched_unit_harmonics(240, ST)
    cell = solve_cell(0.32e-6, 0.21e-6, ST, SolverSettings(nu))
    sc = solve_supercell([[(0.32e-6, 0.21e-6)] * 2] * 2, ST, ns)
    assert sc.n_harmonics == ns - 1 and cell.n_harmonics == nu - 1 and sc.n_harmonics > 3.5 * cell.n_harmonics
    np.testing.assert_allclose(sc.jones, cell.jones, atol=1e-8)


def test_tapered_supercell_of_identical_pillars_is_the_tapered_unit_cell():
    """The same translation symmetry with sloped walls (every slice a supercell of four identical
    rectangles); and a taper of 90 degrees is the vertical supercell, one of 86 degrees is not."""
    from metadesign.library.supercells import matched_unit_harmonics

    ns, nu = matched_unit_harmonics(120, ST)
    cell = solve_tapered(0.32e-6, 0.21e-6, 86.0, 3, ST, SolverSettings(nu))
    sc = solve_supercell([[(0.32e-6, 0.21e-6)] * 2] * 2, ST, ns, taper=(86.0, 3))
    np.testing.assert_allclose(sc.jones, cell.jones, atol=1e-8)
    vertical = solve_supercell(MIXED, ST, 120)
    np.testing.assert_allclose(solve_supercell(MIXED, ST, 120, taper=(90.0, 3)).jones, vertical.jones, atol=1e-9)
    assert abs(solve_supercell(MIXED, ST, 120, taper=(86.0, 3)).t_x - vertical.t_x) > 1e-3


def test_mirror_symmetric_supercell_sector_solve_equals_the_full_solve():
    a = solve_supercell(MIXED, ST, 120, symmetric=True)
    b = solve_supercell(MIXED, ST, 120, symmetric=False)
    np.testing.assert_allclose(a.jones, b.jones, atol=1e-9)
    assert np.abs(b.jones[[0, 1], [1, 0]]).max() < 1e-10  # mirror lines through the pillar centres
    assert np.allclose(b.T_total + b.R_total, 1, atol=1e-6)  # lossless
    # and the four different pillars are not their mean (the LPA): the check measures something
    units = [solve_cell(wx, wy, ST, SolverSettings(30)) for wx, wy in MIXED.reshape(4, 2)]
    lpa = np.mean([u.t_x for u in units])
    assert abs(a.t_x / lpa - 1) > 0.05


def test_four_rectangles_tiling_the_cell_are_the_fabry_perot_slab():
    p = ST.period
    rects = [Rect(c * p, r * p, p, p) for r in range(2) for c in range(2)]
    res = solve_layers([(ST.height, rects)], 2 * p, ST, 40, symmetric=True)
    assert res.t_x == pytest.approx(fabry_perot_t(ST, ST.n_pillar), abs=1e-9)
    assert res.t_y == pytest.approx(fabry_perot_t(ST, ST.n_pillar), abs=1e-9)


def test_supercell_rects_layout():
    r = supercell_rects(MIXED, 0.7e-6)
    assert (r[1].xc, r[1].yc, r[1].wx) == (0.7e-6, 0.0, 320e-9)  # row 0, column 1
    assert (r[2].xc, r[2].yc, r[2].wy) == (0.0, 0.7e-6, 200e-9)  # row 1, column 0


def test_lpa_check_command_end_to_end(tmp_path, demo_products, tiny_dataset):
    """``library lpa-check`` on the demo layout (2 supercells, low harmonics, one convergence re-solve) with the
    downstream study on the tiny dataset: widths are the layout's atoms, the matched unit-cell truncation is
    recorded, the downstream keeps the references (uncorrected, conjugate) and changes the U-Net's input."""
    import json

    from conftest import run_cli, tiny_model

    tiny_model(tmp_path)
    r = run_cli("library", "lpa-check", str(demo_products["layout"]), "--supercells", "2", "--harmonics", "120",
                "--check", "1", "--dataset", str(tiny_dataset), "--model", str(tmp_path / "m.safetensors"),
                "--limit", "2", "--noise", "0", "-j", "1", "-o", str(tmp_path / "lpa"), "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert len(rep["rows"]) == 2 and rep["n_harmonics_supercell"] > 3.5 * rep["n_harmonics_unit"]
    assert rep["convergence_rel_change_max"] is not None and len(rep["convergence_rel_change_max"]) == 2
    from metadesign.layouts import read_layout

    atoms = {tuple(w) for w in read_layout(demo_products["layout"]).atom_widths_nm.tolist()}
    for row in rep["rows"]:
        assert all(tuple(w) in atoms for w in np.asarray(row["widths_nm"]).reshape(4, 2).tolist())
    d = rep["downstream"]
    assert d["samples"] == 2 and 0 < d["npib_none"] < d["npib_phase_conjugate"] <= 1.0
    strehl = {m: [c["strehl"] for c in d[m]["channels"]] for m in ("nominal", "correlated")}
    assert len(strehl["nominal"]) == 8 and not np.allclose(strehl["nominal"], strehl["correlated"], rtol=1e-3)
    assert (tmp_path / "lpa" / "lpa.png").stat().st_size > 0 and (tmp_path / "lpa" / "lpa.json").exists()


def test_smatrix_columns_are_grcwas_recursion():
    """The rearranged S-matrix recursion (S11, S21 carried as the incident columns, diagonal propagators as
    scalings, identity eigenvectors of uniform layers not inverted) against grcwa's own GetSMatrix on a
    random four-layer stack: uniform, two patterned layers of finite thickness, uniform."""
    from grcwa import rcwa as _g

    from metadesign.library.supercell import smatrix_11_21

    rng = np.random.default_rng(7)
    n = 24

    def cplx(*shape):
        return rng.normal(size=shape) + 1j * rng.normal(size=shape)

    qs = [cplx(n) + 3, cplx(n) + 3, cplx(n) + 3, cplx(n) + 3]
    phis = [np.eye(n), cplx(n, n) + 4 * np.eye(n), cplx(n, n) + 4 * np.eye(n), np.eye(n)]
    kps = [cplx(n, n) + 4 * np.eye(n) for _ in range(4)]
    thick = [0.0, 0.3, 0.2, 0.0]
    a = cplx(n, 2)
    S11, _, S21, _ = _g.GetSMatrix(0, 3, qs, phis, kps, thick)
    s11, s21 = smatrix_11_21(qs, phis, kps, thick, a)
    np.testing.assert_allclose(s11, S11 @ a, rtol=1e-10, atol=1e-10 * np.abs(S11 @ a).max())
    np.testing.assert_allclose(s21, S21 @ a, rtol=1e-10, atol=1e-10 * np.abs(S21 @ a).max())


def test_lattice_and_half_spaces_are_grcwas():
    """The solve's own harmonic set and uniform half-spaces (``_Cell``: the diagonal ``kp`` and grcwa's
    branch of ``q``) against grcwa's ``Init_Setup`` of the same stack, circular and rectangular truncation."""
    import grcwa

    from metadesign.library.rcwa import Truncation
    from metadesign.library.supercell import _Cell

    for trunc, method in ((Truncation.CIRCULAR, 0), (Truncation.RECTANGULAR, 1)):
        obj = grcwa.obj(90, [1.0, 0.0], [0.0, 1.0], 1.4 / 1.55, 0.0, 0.0, verbose=0)
        obj.Add_LayerUniform(0.0, 1.444 ** 2)
        obj.Add_LayerGrid(0.8, 1, 1)
        obj.Add_LayerUniform(0.0, 1.0)
        obj.Init_Setup(Gmethod=method)
        cell = _Cell(90, 1.4 / 1.55, trunc, [0.0, 0.8, 0.0], (1.444 ** 2, 1.0))
        assert cell.nG == obj.nG and np.array_equal(cell.G, obj.G)
        np.testing.assert_allclose(cell.kx, obj.kx, rtol=0, atol=1e-12)
        np.testing.assert_allclose(cell.ky, obj.ky, rtol=0, atol=1e-12)
        assert cell.omega == pytest.approx(obj.omega, rel=1e-15)
        for i in (0, -1):
            np.testing.assert_allclose(cell.q_list[i], obj.q_list[i], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(cell.kp_list[i], obj.kp_list[i], rtol=1e-12, atol=1e-12)


def test_sector_change_of_basis_by_gathers_is_the_dense_product():
    """``U^T m U`` by gathers over each orbit's harmonics equals the dense product, complex and real."""
    from metadesign.library.rcwa import Truncation, symmetry_bases
    from metadesign.library.supercell import _Cell, _sector_projector

    G = _Cell(60, 0.9, Truncation.CIRCULAR, [0.0, 0.0], (1.0, 1.0)).G
    rng = np.random.default_rng(3)
    m = rng.normal(size=(2 * len(G),) * 2) + 1j * rng.normal(size=(2 * len(G),) * 2)
    for U in symmetry_bases(G):
        np.testing.assert_allclose(_sector_projector(U, False)(m), U.T @ m @ U, atol=1e-12)
        np.testing.assert_allclose(_sector_projector(U, True)(m.real), U.T @ m.real @ U, atol=1e-12)
    with pytest.raises(ValueError, match="not mirror-symmetric"):  # a complex matrix in a real sector solve
        _sector_projector(symmetry_bases(G)[0], True)(m)


def test_sector_solve_refuses_a_structure_without_the_mirror_symmetry():
    off = [(ST.height, [Rect(0.1e-6, 0.0, 0.3e-6, 0.2e-6)])]  # off centre: no mirror line through x = 0
    # inversion-symmetric (real convolution matrices) but without either mirror line
    inv = [(ST.height, [Rect(0.15e-6, 0.15e-6, 0.2e-6, 0.1e-6), Rect(-0.15e-6, -0.15e-6, 0.2e-6, 0.1e-6)])]
    for layers in (off, inv):
        with pytest.raises(ValueError, match="not mirror-symmetric"):
            solve_layers(layers, ST.period, ST, 30, symmetric=True)
        res = solve_layers(layers, ST.period, ST, 30, symmetric=False)  # the full solve takes it
        assert np.isfinite(res.jones).all()
    assert abs(res.jones[0, 1]) > 1e-4  # and the inversion-only structure does mix the polarisations


def test_sector_solve_on_an_off_grid_period_and_a_taper_is_the_full_solve():
    """A period off any round grid (the band edges' rounding leaves ~1e-9 imaginary parts) and a tapered
    supercell of three different slices: the real-arithmetic sector solve equals the complex full one."""
    st = Stack(period=0.633333333333e-6)
    w = np.array([[[105.9, 485.2], [462.1, 184.6]], [[507.4, 93.0], [233.6, 139.5]]]) * 1e-9
    np.testing.assert_allclose(solve_supercell(w, st, 150).jones, solve_supercell(w, st, 150, symmetric=False).jones,
                               atol=1e-9)
    a = solve_supercell(MIXED, ST, 60, taper=(86.0, 3))
    b = solve_supercell(MIXED, ST, 60, taper=(86.0, 3), symmetric=False)
    np.testing.assert_allclose(a.jones, b.jones, atol=1e-9)

"""The torch twin of the certified surrogate (issue #34): a batched, differentiable low-fidelity supercell
solve.  References are independent of the twin: the numpy/grcwa solvers (:func:`solve_supercell`,
:func:`solve_cell`, :func:`solve_layers`) for values, central finite differences of the numpy surrogate
(:func:`certified_t`'s parts) for gradients, and the lattice's exact symmetries."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from metadesign.library.coupling import lpa_t, transpose_supercells
from metadesign.library.peds import PedsModel, certified_t, peds_t
from metadesign.library.peds_torch import (couplings_torch, lpa_torch, peds_t_torch, solve_symmetric_t,
                                           supercell_t_torch, unit_t_torch)
from metadesign.library.rcwa import SolverSettings, Stack, solve_cell
from metadesign.library.store import interpolate_t
from metadesign.library.supercell import solve_layers, solve_supercell, tapered_layers
from metadesign.library.supercells import matched_unit_harmonics
from metadesign.validation import ValidationError

LEVELS = (25, 41)
COEF = (0.3 - 0.7j, 1.2 + 0.4j)


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _widths(n, seed=0):
    return np.random.default_rng(seed).uniform(0.15e-6, 0.45e-6, size=(n, 2, 2, 2))


@pytest.fixture(scope="module")
def model(paper_library):
    return PedsModel(LEVELS, COEF, paper_library.identity)


def test_supercells_and_unit_cells_match_the_numpy_solver():
    w = _widths(3, 1)
    t = supercell_t_torch(torch.tensor(w), n_harmonics=41).numpy()
    ref = np.array([[solve_supercell(x, n_harmonics=41).t_x, solve_supercell(x, n_harmonics=41).t_y] for x in w])
    np.testing.assert_allclose(t, ref, atol=1e-8)
    tu = unit_t_torch(torch.tensor(w[0]), n_harmonics=29).numpy()
    cells = [solve_cell(*w[0, r, c], Stack(), SolverSettings(n_harmonics=29)) for r in range(2) for c in range(2)]
    np.testing.assert_allclose(tu.reshape(4, 2), [[c.t_x, c.t_y] for c in cells], atol=1e-10)


def test_several_layers_match_the_numpy_solver():
    """A tapered pillar (three slices) and a supercell of two different slices: the multi-layer S-matrix."""
    layers = tapered_layers(0.30e-6, 0.22e-6, 1.2e-6, 84.0, 3)
    rects = [(t, torch.tensor([[[r.xc, r.yc, r.wx, r.wy] for r in rs]])) for t, rs in layers]
    t = solve_symmetric_t(rects, 0.7e-6, n_harmonics=29).numpy()[0]
    ref = solve_layers(layers, 0.7e-6, Stack(), 29, symmetric=True)
    np.testing.assert_allclose(t, [ref.t_x, ref.t_y], atol=1e-10)


def test_surrogate_matches_the_numpy_surrogate(model, paper_library, tmp_path):
    w = _widths(2, 3)
    t = peds_t_torch(model, paper_library, torch.tensor(w)).numpy()
    np.testing.assert_allclose(t, certified_t(paper_library, w, tmp_path / "p", model), atol=2e-6)  # float32 table


def test_identical_pillars_are_the_unit_cell_and_symmetries_hold(model, paper_library):
    w = _widths(2, 4)[:, :1, :1].repeat(2, 1).repeat(2, 2)
    c = couplings_torch(torch.tensor(w), paper_library.stack, LEVELS).numpy()
    assert np.abs(c).max() < 1e-8  # matched truncations: the coupling of identical pillars is zero
    w = _widths(2, 5)
    t = peds_t_torch(model, paper_library, torch.tensor(w)).numpy()
    for shifted in (w[:, ::-1], w[:, :, ::-1]):
        np.testing.assert_allclose(peds_t_torch(model, paper_library, torch.tensor(shifted.copy())).numpy(), t,
                                   atol=1e-8)
    np.testing.assert_allclose(
        peds_t_torch(model, paper_library, torch.tensor(transpose_supercells(w).copy())).numpy(), t[:, ::-1],
        atol=1e-8)


def _numpy_surrogate(lib, w):
    """The surrogate from the numpy solvers and a float64 bilinear look-up (the reference of gradients)."""
    c = []
    for h in LEVELS:
        ns, nu = matched_unit_harmonics(h, lib.stack)
        sup = np.array([solve_supercell(x, lib.stack, n_harmonics=ns).jones.diagonal() for x in w])
        unit = np.array([[solve_cell(*x[r, q], lib.stack, SolverSettings(n_harmonics=nu)).jones.diagonal()
                          for r in range(2) for q in range(2)] for x in w])
        c.append(sup - unit.mean(1))
    gx, gy = lib.wx, lib.wy
    tab = np.stack([lib.t_x, lib.t_y], -1).astype(complex)
    fx, fy = np.interp(w[..., 0], gx, np.arange(len(gx))), np.interp(w[..., 1], gy, np.arange(len(gy)))
    i, j = np.floor(fx).astype(int), np.floor(fy).astype(int)
    ax, ay = (fx - i)[..., None], (fy - j)[..., None]
    tu = ((1 - ax) * (1 - ay) * tab[i, j] + ax * (1 - ay) * tab[i + 1, j] + (1 - ax) * ay * tab[i, j + 1]
          + ax * ay * tab[i + 1, j + 1])
    return peds_t(COEF, np.stack(c), lpa_t(tu))


def test_gradient_against_finite_differences(model, paper_library):
    """d(objective)/d(width) of the torch surrogate against central differences of the numpy one, for
    widths of every role (a pillar's own wx, another pillar's wy, a diagonal pillar's)."""
    w = _widths(2, 6)
    wt = torch.tensor(w, requires_grad=True)
    t = peds_t_torch(model, paper_library, wt)
    (g,) = torch.autograd.grad(t[0, 0].real - 0.5 * t[0, 1].imag + 0.2 * t[1, 1].real, wt)
    g = g.numpy()

    def f(x):
        s = _numpy_surrogate(paper_library, x)
        return s[0, 0].real - 0.5 * s[0, 1].imag + 0.2 * s[1, 1].real

    h = 2e-11
    for idx in [(0, 0, 0, 0), (0, 1, 0, 1), (0, 1, 1, 0), (1, 1, 1, 1)]:
        up, dn = w.copy(), w.copy()
        up[idx] += h
        dn[idx] -= h
        fd = (f(up) - f(dn)) / (2 * h)
        assert abs(fd) > 1e4  # a real dependence (per metre), not a zero compared with a zero
        assert g[idx] == pytest.approx(fd, rel=1e-4), idx
    assert np.abs(g[1, 0]).sum() > 0 and np.abs(g[0]).sum() > 0


def test_lpa_twin_and_bad_inputs(model, paper_library):
    w = _widths(4, 7)
    ref = lpa_t(interpolate_t(paper_library, w[..., 0], w[..., 1])[0])
    np.testing.assert_allclose(lpa_torch(paper_library, torch.tensor(w)).numpy(), ref, atol=1e-6)
    with pytest.raises(ValidationError, match=r"\(n, 2, 2, 2\)"):
        peds_t_torch(model, paper_library, torch.zeros(3, 2, 2))
    with pytest.raises(ValidationError, match="another library"):
        peds_t_torch(PedsModel(LEVELS, COEF, "0" * 64), paper_library, torch.tensor(w))


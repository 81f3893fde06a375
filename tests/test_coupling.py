"""The supercell coupling model and its table (issue #25): the model's structure against exact facts (four
identical pillars are the unit cell; translating the lattice by one pitch or mirroring x <-> y maps t as
the physics does; autograd against finite differences), the coupled forward path against the model
(every supercell's pillars average to the model's t; the LPA path unchanged), and the table engine
(resumable after SIGKILL, same bytes on 1 and 2 workers, a larger table reuses a smaller one's rows)."""

from __future__ import annotations

import numpy as np
import pytest

from metadesign.library import (
    CouplingConfig,
    build_coupling,
    coupling_t,
    fit_coupling,
    load_coupling,
    lpa_t,
    pillar_terms,
    relative_error,
    save_coupling,
    transpose_supercells,
)
from metadesign.library.rcwa import Stack
from metadesign.library.store import interpolate_t


def _rand_widths(n, seed=0, lo=0.12e-6, hi=0.48e-6):
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, 2, 2, 2))


@pytest.fixture(scope="module")
def model(paper_library):
    import torch

    torch.manual_seed(3)
    m = build_coupling(CouplingConfig(hidden=16, layers=3), paper_library)
    with torch.no_grad():  # a network far from zero, so every property below is tested on a real correction
        for p in m.parameters():
            p.mul_(3.0)
    return m.eval()


def test_identical_pillars_are_the_unit_cell(model, paper_library):
    w = _rand_widths(20, 1)[:, :1, :1].repeat(2, 1).repeat(2, 2)  # four copies of one pillar per supercell
    t = coupling_t(model, w)
    ref, _, _ = interpolate_t(paper_library, w[:, 0, 0, 0], w[:, 0, 0, 1])
    np.testing.assert_allclose(t, ref, atol=2e-6)


def test_correction_is_not_trivially_zero(model, paper_library):
    w = _rand_widths(50, 2)
    tu, _, _ = interpolate_t(paper_library, w[..., 0], w[..., 1])
    assert np.abs(coupling_t(model, w) - lpa_t(tu)).mean() > 1e-2


def test_lattice_translations_leave_t_unchanged(model):
    """Swapping the rows or the columns is a translation by one pitch: the 0th order is the same."""
    w = _rand_widths(30, 4)
    t = coupling_t(model, w)
    for shifted in (w[:, ::-1], w[:, :, ::-1], w[:, ::-1, ::-1]):
        np.testing.assert_allclose(coupling_t(model, shifted), t, atol=1e-6)
    # a non-symmetry (swapping only two diagonal pillars' roles with the others) does change t
    odd = w.copy()
    odd[:, 0, 0], odd[:, 0, 1] = w[:, 0, 1], w[:, 0, 0]
    assert np.abs(coupling_t(model, odd) - t).max() > 1e-3


def test_mirror_x_y_swaps_the_polarisations(model):
    w = _rand_widths(30, 5)
    np.testing.assert_allclose(coupling_t(model, transpose_supercells(w))[:, ::-1], coupling_t(model, w), atol=1e-6)


def test_gradient_matches_finite_differences(model):
    import torch

    w0 = (np.round(_rand_widths(4, 6) / 5e-9) + 0.5) * 5e-9  # mid-cell of the 5 nm library grid
    W = torch.tensor(w0, dtype=torch.float64, requires_grad=True)
    out = model(W)  # (n, 2, 2)
    v = torch.tensor(np.random.default_rng(7).normal(size=tuple(out.shape)), dtype=torch.float32)
    (out * v).sum().backward()
    g = W.grad.numpy()
    h = 2e-10  # inside a 5 nm library cell: the look-up is linear there; float32 network -> not smaller
    for idx in [(0, 0, 0, 0), (1, 1, 0, 1), (2, 0, 1, 0), (3, 1, 1, 1)]:
        wp, wm = w0.copy(), w0.copy()
        wp[idx] += h
        wm[idx] -= h
        with torch.no_grad():
            fp = (model(torch.tensor(wp)) * v).sum().double().item()
            fm = (model(torch.tensor(wm)) * v).sum().double().item()
        fd = (fp - fm) / (2 * h)
        assert abs(fd - g[idx]) <= 2e-2 * abs(g[idx]) + 1e4, (idx, fd, g[idx])


def test_pillar_terms_average_to_the_supercell(model, paper_library):
    w = _rand_widths(25, 8)
    tu, _, _ = interpolate_t(paper_library, w[..., 0], w[..., 1])
    eff = tu + pillar_terms(model, w, tu)
    np.testing.assert_allclose(eff.mean((1, 2)), coupling_t(model, w, tu), atol=2e-6)


def test_coupled_pupil_rows_and_lpa_unchanged(model, paper_library):
    """The forward path with coupling: every complete supercell's four pillars average to the model's t;
    pillars of incomplete supercells (empty cells) keep the LPA's t; coupling=None is the LPA path."""
    from metadesign.sensing.transmission import pillar_transmission

    rng = np.random.default_rng(9)
    atoms = rng.uniform(130, 470, size=(12, 2)).round()
    im = rng.integers(0, 12, size=(6, 8)).astype(np.int32)
    im[0, 0] = -1  # an empty cell: its supercell stays LPA
    t0, _ = pillar_transmission(im, atoms, paper_library)
    ref, _, _ = interpolate_t(paper_library, atoms[np.maximum(im, 0), 0] * 1e-9, atoms[np.maximum(im, 0), 1] * 1e-9)
    np.testing.assert_array_equal(t0[im >= 0], ref[im >= 0])
    t1, _ = pillar_transmission(im, atoms, paper_library, coupling=model)
    np.testing.assert_array_equal(t1[:2, :2], t0[:2, :2])
    w = atoms[np.maximum(im, 0)] * 1e-9
    for I in range(3):
        for J in range(4):
            if I == 0 and J == 0:
                continue
            blk = (slice(2 * I, 2 * I + 2), slice(2 * J, 2 * J + 2))
            want = coupling_t(model, w[blk][None])[0]
            np.testing.assert_allclose(t1[blk].mean((0, 1)), want, atol=2e-6)
            assert np.abs(t1[blk] - t0[blk]).max() > 1e-4
    # row tiles on supercell rows give the same pillars
    t2 = np.concatenate([pillar_transmission(im, atoms, paper_library, rows=slice(r, r + 2), coupling=model)[0]
                         for r in (0, 2, 4)])
    np.testing.assert_array_equal(t2, t1)
    with pytest.raises(ValueError, match="supercell"):
        pillar_transmission(im, atoms, paper_library, rows=slice(1, 3), coupling=model)


def test_fit_recovers_a_known_coupling(paper_library, tmp_path):
    """Data made by a known coupling model (a different seed) is learned by a fresh fit far below the LPA's
    error on rows it never saw; the saved model reloads to the same predictions and refuses another
    library."""
    import torch

    torch.manual_seed(11)
    teacher = build_coupling(CouplingConfig(hidden=8, layers=2), paper_library).eval()
    w = _rand_widths(500, 12)
    t = coupling_t(teacher, w)
    tu, _, _ = interpolate_t(paper_library, w[..., 0], w[..., 1])
    fit, held = slice(0, 400), slice(400, 500)
    m, info = fit_coupling(paper_library, w[fit], t[fit], CouplingConfig(hidden=24, layers=2), steps=600, lr=1e-2)
    e = relative_error(coupling_t(m, w[held]), t[held], tu[held]).mean()
    e_lpa = relative_error(lpa_t(tu[held]), t[held], tu[held]).mean()
    assert e < 0.2 * e_lpa, (e, e_lpa)
    from conftest import REPO

    p = save_coupling(tmp_path / "c.safetensors", m, REPO / "library" / "paper.npz", {"note": "test"})
    m2, card = load_coupling(p, paper_library, check_library=False)
    np.testing.assert_array_equal(coupling_t(m2, w[held]), coupling_t(m, w[held]))
    assert card["note"] == "test" and card["config"]["hidden"] == 24


# ---------------------------------------------------------------- the table engine (tiny truncation: fast)

def _tiny_widths(n=10):
    return np.random.default_rng(1).uniform(0.15e-6, 0.45e-6, size=(n, 2, 2, 2))


def test_table_same_bytes_any_workers_and_grows(tmp_path):
    from metadesign.library.supercells import solve_table

    w = _tiny_widths(10)
    t1, nG, _, _ = solve_table(w, Stack(), 30, tmp_path / "a", workers=1, chunk_size=3)
    t2, _, _, _ = solve_table(w, Stack(), 30, tmp_path / "b", workers=2, chunk_size=3)
    assert t1.tobytes() == t2.tobytes() and nG < 30
    # the first 6 rows' chunks are reused by the 10-row table in the same folder: nothing new to solve
    part = tmp_path / "c"
    solve_table(w[:6], Stack(), 30, part, chunk_size=3)
    seen = []
    t3, _, _, _ = solve_table(w, Stack(), 30, part, chunk_size=3, progress=lambda a, b: seen.append(a))
    assert seen[0] == 6 and t3.tobytes() == t1.tobytes()


def test_table_resumes_after_sigkill(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    from conftest import REPO

    from metadesign.library.supercells import solve_table

    w = _tiny_widths(40)
    np.save(tmp_path / "w.npy", w)
    part = tmp_path / "part"
    code = ("import numpy as np; from metadesign.library.supercells import solve_table; "
            "from metadesign.library.rcwa import Stack; "
            f"solve_table(np.load(r'{tmp_path / 'w.npy'}'), Stack(), 60, r'{part}', chunk_size=2)")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    t0 = time.time()
    while len(list(part.glob("chunk-*.npz"))) < 2 and time.time() - t0 < 120:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = len(list(part.glob("chunk-*.npz")))
    assert 2 <= done < 20
    logs = []
    t, _, _, _ = solve_table(w, Stack(), 60, part, chunk_size=2, log=logs.append)
    assert any(f"resuming: {done}/20 tasks ({2 * done}/40 " in s for s in logs), logs
    clean, _, _, _ = solve_table(w, Stack(), 60, tmp_path / "clean", workers=2, chunk_size=2)
    assert clean.tobytes() == t.tobytes()


def test_table_rows_are_prefix_stable_and_hold_out_the_same_rows():
    from metadesign.studies.supercells import RowDraw, sample_rows

    aw = np.random.default_rng(0).uniform(0.1e-6, 0.5e-6, size=(16, 2))
    im = np.random.default_rng(1).integers(0, 16, size=(20, 20)).astype(np.uint8)
    mix = (0.4, 0.0, 0.3, 0.3)
    a = sample_rows(30, RowDraw(7, mix, 10e-9, 5), (aw, im), None, (0.1e-6, 0.5e-6))
    b = sample_rows(12, RowDraw(7, mix, 10e-9, 5), (aw, im), None, (0.1e-6, 0.5e-6))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x[:12], y)
    assert list(np.flatnonzero(a[2])) == [4, 9, 14, 19, 24, 29]
    # design rows are supercells of the map; atom rows are atoms; jittered rows stay within range and jitter
    for k in range(30):
        if a[1][k] == 0:
            hits = [(I, J) for I in range(10) for J in range(10)
                    if np.array_equal(aw[im[2 * I:2 * I + 2, 2 * J:2 * J + 2]], a[0][k])]
            assert hits
        elif a[1][k] == 2:
            assert all(any(np.array_equal(p, q) for q in aw) for p in a[0][k].reshape(4, 2))
        else:
            d = np.min(np.abs(a[0][k].reshape(4, 1, 2) - aw[None]).max(-1), axis=1)
            assert (d <= 10e-9 + 1e-15).all()


def test_supercell_recipe_refuses_bad_mix(tmp_path, capsys):
    from conftest import run_main

    p = tmp_path / "r.toml"
    p.write_text('[table]\nlibrary = "x.npz"\ndesign = "d.toml"\n[mix]\ndesign = 0.5\nextra_design = 0.0\n'
                 'atom_tuples = 0.2\njittered_atoms = 0.2\n')
    rc, out, err = run_main(["library", "supercells", p], capsys)
    assert rc == 2 and len(err) == 1 and "mix" in err[0] and not list(tmp_path.glob("*.npz*"))
    p.write_text('[table]\nlibrary = "x.npz"\ndesign = "d.toml"\nsupercells = nan\n')
    rc, out, err = run_main(["library", "supercells", p], capsys)
    assert rc == 2 and len(err) == 1 and "table.supercells" in err[0]


def test_pair_tables_reproduce_the_network(paper_library):
    """The discretizer's look-up path (pair tables over an atom set) equals running the network."""
    import torch

    from metadesign.library import pair_tables, tuple_t

    torch.manual_seed(5)
    m = build_coupling(CouplingConfig(hidden=16, layers=3, interaction="pair"), paper_library).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.mul_(3.0)
    aw = np.random.default_rng(2).uniform(0.12e-6, 0.48e-6, size=(9, 2))
    ta, _, _ = interpolate_t(paper_library, aw[:, 0], aw[:, 1])
    tab = pair_tables(m, aw, ta)
    a = np.random.default_rng(3).integers(0, 9, size=(40, 2, 2))
    want = coupling_t(m, aw[a], ta[a])
    np.testing.assert_allclose(tuple_t(tab, ta, a), want, atol=3e-6)
    assert np.abs(want - ta[a].mean((1, 2))).mean() > 1e-2


def _strong_pair_table(lib, seed: int, n_atoms: int):
    """A pair model with its weights scaled up (coupling terms well above rounding) and its tables over
    ``n_atoms`` random atoms: ``(atom widths, atom t, tables)``."""
    import torch

    from metadesign.library import pair_tables

    torch.manual_seed(seed)
    m = build_coupling(CouplingConfig(hidden=16, layers=3, interaction="pair"), lib).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.mul_(3.0)
    aw = np.random.default_rng(seed).uniform(0.15e-6, 0.45e-6, size=(n_atoms, 2))
    ta = interpolate_t(lib, aw[:, 0], aw[:, 1])[0].astype(np.complex64)
    return aw, ta, pair_tables(m, aw, ta)


def test_compensation_descends_and_its_updates_are_exact(paper_library):
    """The discretizer's incremental look-ups give exactly the pair-table t of the atoms it ends on; no
    supercell's cost rises; its cost never beats the brute-force optimum over every 4-tuple."""
    import itertools

    from metadesign.design.compensate import _descend, atom_neighbours
    from metadesign.library import tuple_t

    _, ta, tab = _strong_pair_table(paper_library, 8, 6)
    rng = np.random.default_rng(4)
    a0 = rng.integers(0, 6, size=(30, 2, 2))
    S = (np.exp(1j * rng.uniform(-np.pi, np.pi, size=(30, 2))) * 0.5).astype(np.complex64)
    a = a0.copy()
    t = _descend(a, S, tab, ta, atom_neighbours(np.angle(ta), 6), sweeps=3)
    np.testing.assert_allclose(t, tuple_t(tab, ta, a), atol=1e-5)
    cost = lambda tt: (np.abs(tt - S) ** 2).sum(-1)  # noqa: E731
    assert (cost(t) <= cost(tuple_t(tab, ta, a0)) + 1e-6).all()
    assert (a != a0).any()
    every = np.array(list(itertools.product(range(6), repeat=4))).reshape(-1, 2, 2)
    tt = tuple_t(tab, ta, every)
    best = np.array([(np.abs(tt - S[k]) ** 2).sum(-1).min()
                     for k in range(30)])
    assert (cost(t) >= best - 1e-6).all()


def test_descent_under_a_whole_tuple_model_is_the_table_descent(paper_library):
    """The descent that scores whole candidate tuples (for models without pair tables: the certified one),
    given the pair model's own tuple look-up as its model, ends on the atoms and ``t`` of the incremental
    table descent, supercell by supercell, and never raises a cost."""
    from metadesign.design.compensate import _descend, atom_neighbours, descend_under
    from metadesign.library import tuple_t

    _, ta, tab = _strong_pair_table(paper_library, 9, 9)
    rng = np.random.default_rng(5)
    nbr = atom_neighbours(np.angle(ta), 5)
    a0 = rng.integers(0, 9, size=(40, 2, 2))
    S = (np.exp(1j * rng.uniform(-np.pi, np.pi, size=(40, 2))) * 0.5).astype(np.complex64)
    a_tab, a_whole = a0.copy(), a0.copy()
    t_tab = _descend(a_tab, S, tab, ta, nbr, sweeps=2)
    calls = []
    t_whole = descend_under(a_whole, S, nbr, lambda x: calls.append(len(x)) or tuple_t(tab, ta, x), sweeps=2,
                            progress=lambda d, n: None)
    np.testing.assert_array_equal(a_whole, a_tab)
    np.testing.assert_allclose(t_whole, t_tab, atol=1e-5)
    assert calls == [40] + [40 * 4] * 8  # the start, then (K - 1) candidates per supercell per position
    cost = lambda tt: (np.abs(tt - S) ** 2).sum(-1)  # noqa: E731
    assert (cost(t_whole) <= cost(tuple_t(tab, ta, a0)) + 1e-6).all() and (a_whole != a0).any()


def test_pair_model_pupil_rows_by_tables_equal_the_network(paper_library):
    """Without jitter the coupled rows come from pair tables over the atoms; with jitter 0 vs a jitter so
    small it changes nothing, the network path gives the same pillars."""
    import torch

    from metadesign.sensing.transmission import Perturbation, couple_supercells, pillar_transmission

    torch.manual_seed(6)
    m = build_coupling(CouplingConfig(hidden=16, layers=3, interaction="pair"), paper_library).eval()
    with torch.no_grad():
        for p in m.parameters():
            p.mul_(3.0)
    rng = np.random.default_rng(10)
    atoms = rng.uniform(130, 470, size=(10, 2)).round()
    im = rng.integers(0, 10, size=(8, 8)).astype(np.int32)
    t_tab, _ = pillar_transmission(im, atoms, paper_library, Perturbation(), coupling=m)
    t0, _ = pillar_transmission(im, atoms, paper_library)
    w = atoms[im] * 1e-9
    t_net = couple_supercells(t0, w, im >= 0, m)  # no atom table: the network per supercell
    np.testing.assert_allclose(t_tab, t_net, atol=3e-6)
    assert np.abs(t_tab - t0).max() > 1e-3


def test_a_table_at_another_truncation_solves_matched_unit_cells(tmp_path, capsys):
    """Built through the CLI at a truncation that is not the library's: each row carries its four unit cells
    at the matched truncation; four identical pillars then measure no coupling (the supercell of one pillar
    is its unit cell when the harmonic sets match), so the label is the LPA's."""
    from conftest import REPO, run_main

    from metadesign.library.supercells import load_table, matched_unit_harmonics, solve_table

    st = Stack()
    ns, nu = matched_unit_harmonics(40, st)
    w = np.broadcast_to(np.array([0.31e-6, 0.22e-6]), (2, 2, 2, 2)).copy()
    w[1] = _tiny_widths(1)[0]
    t, nG, _, t_unit = solve_table(w, st, ns, tmp_path / "p", unit_harmonics=nu)
    assert t_unit.shape == (2, 2, 2, 2) and nG == ns - 1
    np.testing.assert_allclose(t[0], t_unit[0, 0, 0], atol=1e-9)  # identical pillars: no coupling
    assert np.abs(t[1] - t_unit[1].mean((0, 1))).max() > 1e-3  # four different ones: some
    rec = tmp_path / "sc.toml"
    rec.write_text(f'[table]\nlibrary = "{REPO / "library" / "paper.npz"}"\ndesign = "{REPO / "layouts" / "demo.toml"}"\n'
                   'supercells = 4\nseed = 1\ntest_every = 2\nn_harmonics = 40\nchunk = 2\n'
                   '[mix]\ndesign = 0.5\nextra_design = 0.0\natom_tuples = 0.25\njittered_atoms = 0.25\n')
    rc, out, err = run_main(["library", "supercells", rec, "-o", tmp_path / "sc.npz", "--json"], capsys)
    assert rc == 0, err
    tab = load_table(tmp_path / "sc.npz")
    assert tab.t_unit.shape == (4, 2, 2, 2) and tab.meta["n_harmonics"] == ns - 1
    lpa = np.full((4, 2), 0.5 + 0.1j)
    np.testing.assert_allclose(tab.labels(lpa), lpa + tab.t - tab.t_unit.mean((1, 2)))


def test_active_learning_picks_the_most_uncertain_and_resumes(paper_library, tmp_path):
    """The loop's batch is the pool's top spread (checked against the members' predictions directly), the
    solves land in content-keyed chunks (a rerun solves nothing and reports the same numbers), and the
    learning curves hold the start and the grown label counts."""
    from metadesign.library.coupling import CouplingConfig, unit_rms
    from metadesign.library.coupling_net import coupling_t
    from metadesign.library.store import interpolate_t
    from metadesign.library.supercells import SupercellTable, matched_unit_harmonics, solve_table
    from metadesign.execution import Execution
    from metadesign.studies.active import ActiveConfig, active_learning, ensemble_spread

    st = Stack()
    ns, nu = matched_unit_harmonics(30, st)
    rng = np.random.default_rng(5)
    w = rng.uniform(0.2e-6, 0.4e-6, size=(30, 2, 2, 2))
    t, nG, _, tu = solve_table(w, st, ns, tmp_path / "t", chunk_size=10, unit_harmonics=nu)
    test = np.arange(30) % 3 == 2
    table = SupercellTable(w, t, np.zeros(30, np.int8), test, {"n_harmonics": nG}, tu)
    pool = rng.uniform(0.2e-6, 0.4e-6, size=(12, 2, 2, 2))
    cfg = ActiveConfig(start=8, batch=4, rounds=1, members=2, steps=30,
                       model=CouplingConfig(hidden=8, layers=2, interaction="environment"))
    logs = []
    rep = active_learning(table, table, paper_library, pool, tmp_path / "part", cfg, Execution(log=logs.append))
    assert [r["solves"] for r in rep["active"]] == [8, 12] and [r["solves"] for r in rep["random"]] == [8, 12]
    assert len(list((tmp_path / "part").glob("chunk-*.npz"))) == 1  # the batch, one chunk
    # the batch was the round-0 ensemble's top-4 spread: refit round 0 (deterministic) and rank independently
    from metadesign.studies.active import _fit_members

    fit_rows = np.flatnonzero(~test)[:8]
    tu_fit = interpolate_t(paper_library, w[fit_rows][..., 0], w[fit_rows][..., 1])[0]
    labels = table.rows(fit_rows).labels(tu_fit.mean((1, 2)))
    members = _fit_members(paper_library, w[fit_rows], labels, cfg)
    tu_pool = interpolate_t(paper_library, pool[..., 0], pool[..., 1])[0]
    preds = np.stack([coupling_t(m, pool, tu_pool) for m in members])
    sd = np.sqrt((np.abs(preds - preds.mean(0)) ** 2).mean(0)) / unit_rms(tu_pool)
    top = set(np.argsort(-sd.max(1))[:4].tolist())
    _, spread = ensemble_spread(members, pool, tu_pool)
    assert set(np.argsort(-spread)[:4].tolist()) == top == set(rep["active"][0]["picked"])
    logs.clear()
    again = active_learning(table, table, paper_library, pool, tmp_path / "part", cfg, Execution(log=logs.append))
    assert any("resuming: 1/1 tasks" in s for s in logs), logs  # the batch's solves kept, none redone
    drop = lambda c: [{k: v for k, v in r.items() if k != "fit_seconds"} for r in c]  # noqa: E731
    assert drop(again["active"]) == drop(rep["active"]) and drop(again["random"]) == drop(rep["random"])


def test_convergence_ladder_measures_label_changes(paper_library, tmp_path):
    """Labels re-solved at rising truncation: four identical pillars never move (their coupling is zero at
    every matched truncation), four different ones do; the table's own labels are compared with the top."""
    from metadesign.library.supercells import SupercellTable
    from metadesign.studies.supercells import convergence_ladder

    w = np.broadcast_to(np.array([0.31e-6, 0.22e-6]), (2, 2, 2, 2)).copy()
    w[1] = _tiny_widths(1)[0]
    tab = SupercellTable(w, np.zeros((2, 2), complex), np.zeros(2, np.int8), np.ones(2, bool),
                         {"n_harmonics": 0}, np.zeros((2, 2, 2, 2), complex))
    rep = convergence_ladder(tab, paper_library, np.arange(2), [30, 60], tmp_path / "p")
    (step,) = rep["steps"]
    assert step["label_change_per_row"][0] < 1e-9 < 1e-3 < step["label_change_per_row"][1]
    assert [lv["n_harmonics"] for lv in rep["levels"]] == sorted(lv["n_harmonics"] for lv in rep["levels"])
    labels = rep["_labels"]
    tu = interpolate_t(paper_library, w[..., 0], w[..., 1])[0]
    np.testing.assert_allclose(labels[:, 0], tu[0].mean((0, 1))[None].repeat(2, 0), atol=1e-9)


@pytest.mark.slow  # a training run: the default suite's 10-minute budget
def test_ladder_and_active_cli(tmp_path, capsys):
    """The two commands end to end at a small truncation: JSON products with their format tags, a rerun
    over our own output allowed (and resumed), a foreign file at the output refused with one line."""
    import json

    from conftest import REPO, run_main

    rec = tmp_path / "sc.toml"
    rec.write_text(f'[table]\nlibrary = "{REPO / "library" / "paper.npz"}"\ndesign = "{REPO / "layouts" / "demo.toml"}"\n'
                   'supercells = 16\nseed = 3\ntest_every = 4\nn_harmonics = 30\nchunk = 4\n'
                   '[mix]\ndesign = 0.5\nextra_design = 0.0\natom_tuples = 0.25\njittered_atoms = 0.25\n')
    rc, _, err = run_main(["library", "supercells", rec, "--json"], capsys)
    assert rc == 0, err
    table = tmp_path / "sc.npz"
    rc, _, err = run_main(["library", "coupling", table, "--reference", table, "--sizes", "10", "--steps", "5",
                           "--hidden", "8", "-o", tmp_path / "c.safetensors", "--json"], capsys)
    assert rc == 0, err  # fitted on labels of a table at another truncation, certified on a reference
    out = tmp_path / "ladder.json"
    args = ["library", "ladder", table, "--rows", "2", "--harmonics", "30", "50", "-o", out, "--json"]
    rc, _, err = run_main(args, capsys)
    assert rc == 0, err
    rep = json.loads(out.read_text())
    assert rep["format"].startswith("metadesign.ladder/") and len(rep["steps"]) == 1 and len(rep["rows"]) == 2
    rc, _, err = run_main(args, capsys)  # ours: replaced
    assert rc == 0, err
    (tmp_path / "foreign.json").write_text("{}")
    rc, _, err = run_main(args[:-3] + ["-o", tmp_path / "foreign.json"], capsys)
    assert rc == 2 and len(err) == 1 and (tmp_path / "foreign.json").read_text() == "{}"
    rc, _, err = run_main(["library", "active", rec, "--reference", table, "--start", "4", "--batch", "2",
                           "--rounds", "1", "--members", "2", "--pool", "10", "--steps", "10", "--hidden", "8",
                           "--json"], capsys)
    assert rc == 0, err
    act = json.loads((tmp_path / "sc-active.json").read_text())
    assert act["format"].startswith("metadesign.active/") and [r["solves"] for r in act["active"]] == [4, 6]
    assert (tmp_path / "sc-active.png").exists()
    rc, _, err = run_main(["library", "patches", REPO / "layouts" / "demo.toml", "--patches", "2", "--harmonics",
                           "120", "-o", tmp_path / "patches.json", "--json"], capsys)
    assert rc == 0, err
    pt = json.loads((tmp_path / "patches.json").read_text())
    assert pt["format"].startswith("metadesign.patches/") and pt["patches"] == 2 and pt["beyond_2x2_mean_both"] > 0


def test_a_patch_repeating_one_supercell_is_that_supercell():
    """A 4 x 4 patch made of one 2 x 2 supercell repeated is the same periodic structure: at matched
    truncations its 0th order equals the supercell's (the even harmonics decouple), with no cross-
    polarisation; a patch of four different supercells differs from their mean (the effect measured)."""
    from metadesign.library.supercells import matched_harmonics, matched_unit_harmonics
    from metadesign.studies.supercells import _patch_task

    st = Stack()
    ns_p, ns_s = matched_harmonics(150, st, 4, 2)
    _, nu = matched_unit_harmonics(ns_s, st)
    sc = _tiny_widths(1)[0]  # (2, 2, 2)
    w = np.tile(sc, (2, 2, 1))  # (4, 4, 2): the supercell twice in x and y
    _, r = _patch_task(("p", w, st, ns_p, ns_s, nu))
    np.testing.assert_allclose(r["t_patch"], r["t_super"][0], atol=1e-8)
    np.testing.assert_allclose(r["t_super"], np.broadcast_to(r["t_super"][0], (4, 2)), atol=1e-12)
    assert r["cross"].max() < 1e-8
    w2 = np.concatenate([np.concatenate([sc, sc[::-1]], 1), np.concatenate([sc[:, ::-1], sc], 1)], 0)
    _, r2 = _patch_task(("q", w2, st, ns_p, ns_s, nu))
    assert np.abs(r2["t_patch"] - r2["t_super"].mean(0)).max() > 1e-4


def test_ring_low_fidelity_at_the_patch_truncation_is_the_patch(tmp_path, capsys):
    """The neighbour-ring low fidelity solved at the very truncation of the patch study (the same patch and
    supercell harmonic sets) is the study's ring term: residual zero, coefficients (0, 1), held out or not;
    the cheaper level alone is not.  The overlapping windows are reported too; a bad option is one line."""
    import json

    from conftest import REPO, run_main

    from metadesign.library.peds import PedsModel, patch_harmonics, save_peds
    from metadesign.library.rcwa import Stack
    from metadesign.library.store import load_library

    nb, _ = patch_harmonics(25, Stack())
    out, peds = tmp_path / "patches.json", tmp_path / "tiny-peds.json"  # a cheap surrogate for the windows
    save_peds(peds, PedsModel((20,), (0.9 + 0.1j,), load_library(REPO / "library" / "paper.npz").identity))
    rc, _, err = run_main(["library", "patches", REPO / "layouts" / "demo.toml", "--patches", "4", "--harmonics",
                           str(nb), "--ring-levels", "20", "25", "--windows", "--peds", peds, "-o", out, "--json"],
                          capsys)
    assert rc == 0, err
    rep = json.loads(out.read_text())
    assert rep["ring"]["calibrated_held_out_mean_both"] < 1e-8 and max(rep["ring"]["raw_per_level"]["25"]["max"]) < 1e-8
    assert max(rep["ring"]["raw_per_level"]["20"]["max"]) > 1e-3  # the cheaper level alone is not it
    np.testing.assert_allclose([complex(*c) for c in rep["ring"]["coefficients"]], [0.0, 1.0], atol=1e-7)
    assert rep["beyond_2x2_mean_both"] > 1e-3
    for k in ("windows_exact", "windows_peds"):
        assert np.isfinite(rep[k]["mean_both"]) and rep[k]["p90_both"] >= 0
        assert np.mean(rep["per_patch"][k]) == pytest.approx(rep[k]["mean_both"])  # the figure's data
    assert (tmp_path / rep["figure"]).exists() and not out.with_name(out.name + ".partial").exists()
    rc, _, err = run_main(["library", "patches", REPO / "layouts" / "demo.toml", "--patches", "2", "--ring-levels", "20",
                           "-o", tmp_path / "p2.json"], capsys)
    assert rc == 2 and len(err) == 1 and "--ring-levels" in err[0] and not (tmp_path / "p2.json").exists()

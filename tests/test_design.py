"""Stage 2: Eq. 1 geometry, wrap-aware exact mapping, metrics with known answers, bad input."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from metadesign.design import (
    AtomTable,
    Metric,
    NearestAtom,
    SupercellSpec,
    brute_force_nearest,
    cell_coordinates,
    design_phase_rows,
    paper_channels,
    select_atoms,
    wrap,
)
from metadesign.design.build import discretize_design

CX, CY = paper_channels()


def _unwrap2d(ph):
    return np.unwrap(np.unwrap(ph, axis=1), axis=0)


@pytest.mark.parametrize("pol", [0, 1])
def test_paraboloid_fit_recovers_table_s1(pol):
    """Fit each sub-lattice's unwrapped phase: f_k and offsets (Table S1) within 0.1 %."""
    n = 1000  # 0.7 mm: the quartic term of Eq. 1 is < 1e-4 of the quadratic one here
    spec = SupercellSpec(1.55e-6, 0.7e-6, n, 2, CX, CY)
    ph = design_phase_rows(spec, pol, 0, n)  # wrapped, as stored
    x = cell_coordinates(n, spec.period)
    expected_f = [48.8e-3, 49.2e-3, 49.6e-3, 50.0e-3] if pol == 0 else [50.4e-3, 50.8e-3, 51.2e-3, 51.6e-3]
    expected_off = [(-240e-6, -192e-6), (240e-6, -192e-6), (-240e-6, 192e-6), (240e-6, 192e-6)]
    k0 = 2 * np.pi / 1.55e-6
    for k in range(4):
        a, b = k % 2, k // 2
        sub = _unwrap2d(ph[b::2, a::2])
        X, Y = np.meshgrid(x[a::2], x[b::2])
        A = np.stack([np.ones(X.size), X.ravel(), Y.ravel(), (X**2 + Y**2).ravel()], axis=1)
        c = np.linalg.lstsq(A, sub.ravel(), rcond=None)[0]
        d = c[3]
        f = -k0 / (2 * d)
        dx, dy = -c[1] / (2 * d), -c[2] / (2 * d)
        assert f == pytest.approx(expected_f[k], rel=1e-3)
        assert dx == pytest.approx(expected_off[k][0], rel=1e-3)
        assert dy == pytest.approx(expected_off[k][1], rel=1e-3)
        assert d < 0  # converging: phase decreases away from the lens axis


def _atoms(phx, phy, T=1.0):
    phx, phy = np.asarray(phx, float), np.asarray(phy, float)
    n = phx.size
    t = np.stack([np.exp(1j * phx), np.exp(1j * phy)], axis=1) * np.sqrt(T)
    return AtomTable(np.full(n, 2e-7), np.full(n, 2e-7), t, np.full((n, 2), T), np.zeros((n, 2), int), 0, n, 1.0)


def test_wrap_aware_mapping():
    e = 0.05
    atoms = _atoms([np.pi - e, -np.pi + 4 * e], [0.0, 0.0])
    for m in (NearestAtom(atoms), lambda x, y: brute_force_nearest(x, y, atoms)):
        assert int(np.ravel(m(np.array([-np.pi + e]), np.array([0.0])))[0]) == 0


@pytest.mark.parametrize("metric", list(Metric))
def test_lut_mapping_equals_brute_force(paper_library, metric):
    lib = paper_library
    atoms = select_atoms(lib.t_x, lib.t_y, lib.T0, lib.wx, lib.wy, 0.7, 16, np.sqrt(1 / 1.444))
    rng = np.random.default_rng(3)
    px = rng.uniform(-np.pi, np.pi, 300_000)
    py = rng.uniform(-np.pi, np.pi, 300_000)
    # adversarial points: exactly on atom phases, on the LUT grid lines and at -pi
    g = -np.pi + np.arange(1024) * 2 * np.pi / 1024
    px = np.concatenate([px, atoms.phase[:, 0], g, np.full(1024, -np.pi)])
    py = np.concatenate([py, atoms.phase[:, 1], g[::-1], g])
    lut = NearestAtom(atoms, metric)
    assert 0 < lut.unsafe_fraction < 0.5
    np.testing.assert_array_equal(lut(px, py), brute_force_nearest(px, py, atoms, metric))


def test_atom_selection_bins_and_gap_filling():
    # synthetic library: a 64 x 64 (wx, wy) grid whose phases sweep the torus linearly
    n = 64
    w = np.linspace(1e-7, 5e-7, n)
    phx = wrap(np.linspace(-np.pi, np.pi, n, endpoint=False))[:, None] + np.zeros((1, n))
    phy = np.zeros((n, 1)) + wrap(np.linspace(-np.pi, np.pi, n, endpoint=False))[None, :]
    T0 = np.ones((n, n, 2))
    T0[20:40, 20:40] = 0.1  # a coverage gap of ~4 x 4 bins
    atoms = select_atoms(np.exp(1j * phx), np.exp(1j * phy), T0, w, w, 0.7, 16)
    assert atoms.n_empty_bins == 25  # samples 20..39 fill bins 5..9: 5 x 5 bins wholly inside the gap
    assert len(atoms) < 256  # gap bins borrowed neighbours' cells, deduplicated
    assert np.all(atoms.T0 >= 0.7)
    assert len(np.unique(atoms.lib_index, axis=0)) == len(atoms)


def test_metrics_known_answer_uniform_quantiser():
    """Atoms exactly at the 16 x 16 bin centres: a lens's wrapped phase is ~uniform,
    so RMSE per polarisation -> bin width / sqrt(12) and peak -> half a bin."""
    c = -np.pi + (np.arange(16) + 0.5) * 2 * np.pi / 16
    gx, gy = np.meshgrid(c, c, indexing="ij")
    atoms = _atoms(gx.ravel(), gy.ravel(), T=0.9)
    spec = SupercellSpec(1.55e-6, 0.7e-6, 2000, 2, CX, CY)
    res = discretize_design(spec, atoms, Metric.PHASE, optimise_offsets=False)
    delta = 2 * np.pi / 16
    np.testing.assert_allclose(res.metrics["rmse_rad"], delta / np.sqrt(12), rtol=0.02)
    np.testing.assert_allclose(res.metrics["peak_error_rad"], delta / 2, rtol=0.01)
    np.testing.assert_allclose(res.metrics["mean_T0"], 0.9, rtol=1e-12)
    # every cell's atom is its brute-force nearest
    ph = design_phase_rows(spec, 0, 0, 50), design_phase_rows(spec, 1, 0, 50)
    np.testing.assert_array_equal(res.index_map[:50].ravel(), brute_force_nearest(ph[0], ph[1], atoms))


def _brute_cost(spec, atoms, ox, oy):
    """Mean over cells of the squared wrapped phase error (both pols) of the nearest atom: numpy brute force."""
    from metadesign.design.phase import design_phase, wrap

    i = np.arange(spec.n_cells)
    px = design_phase(spec, 0, i, i, ox).ravel()
    py = design_phase(spec, 1, i, i, oy).ravel()
    ap = np.angle(atoms.t)  # (n_atoms, 2)
    d = wrap(px[:, None] - ap[None, :, 0]) ** 2 + wrap(py[:, None] - ap[None, :, 1]) ** 2
    return float(d.min(axis=1).mean())


def test_offset_optimisation_finds_the_best_constant(paper_library):
    """A 40-cell aperture: each lens covers a narrow phase range, so the constant offset matters.  The
    optimiser's choice must beat zero offset and be as good as the best of a brute-force grid of offsets."""
    from metadesign.design.phase import wrap

    lib = paper_library
    atoms = select_atoms(lib.t_x, lib.t_y, lib.T0, lib.wx, lib.wy, 0.7, 16, np.sqrt(1 / 1.444))
    spec = SupercellSpec(1.55e-6, 0.7e-6, 40, 2, CX, CY)
    res = discretize_design(spec, atoms, optimise_offsets=True)
    ox, oy = res.offsets
    best = _brute_cost(spec, atoms, ox, oy)
    zero = _brute_cost(spec, atoms, 0.0, 0.0)
    assert best < 0.8 * zero  # switched off, the optimiser would fail here
    grid = np.linspace(-np.pi, np.pi, 17)[:-1] + 0.07
    brute = min(_brute_cost(spec, atoms, a, b) for a in grid for b in grid)
    assert best <= brute * 1.02
    # the reported RMSE is that of the chosen offsets
    off = discretize_design(spec, atoms, optimise_offsets=False).metrics
    assert sum(res.metrics["rmse_rad"]) < sum(off["rmse_rad"])
    assert np.all(np.abs(wrap(np.array(res.offsets))) <= np.pi)


def test_circular_aperture_leaves_corners_empty(paper_library):
    lib = paper_library
    atoms = select_atoms(lib.t_x, lib.t_y, lib.T0, lib.wx, lib.wy, 0.7, 16, np.sqrt(1 / 1.444))
    spec = SupercellSpec(1.55e-6, 0.7e-6, 200, 2, CX, CY, circular_aperture=True)
    res = discretize_design(spec, atoms)
    assert res.empty == np.iinfo(res.index_map.dtype).max  # 256 atoms + "no pillar" need uint16
    empty = res.index_map == res.empty
    assert empty[0, 0] and empty[-1, -1] and not empty[100, 100]
    assert res.metrics["n_cells_in_aperture"] == pytest.approx(np.pi / 4 * 200**2, rel=0.02)


DEMO = """
[design]
library = "{lib}"
wavelength_nm = 1550.0
period_um = 0.7
aperture_mm = 0.1
"""


def test_design_cli_writes_reproducible_design(tmp_path, repo):
    rec = tmp_path / "small.toml"
    rec.write_text(DEMO.format(lib=repo / "library" / "paper.npz"))
    p = run_cli("design", rec, "--json")
    assert p.returncode == 0, p.stderr
    m = json.loads(p.stdout)
    assert m["n_cells"] == 142 * 142
    first = (tmp_path / "small" / "design.npz").read_bytes()
    p = run_cli("design", rec, "-o", tmp_path / "again")
    assert (tmp_path / "again" / "design.npz").read_bytes() == first
    p = run_cli("design", "plot", tmp_path / "small")
    assert p.returncode == 0 and (tmp_path / "small" / "fig-s2.png").stat().st_size > 10_000
    from metadesign.design.store import load_design
    d = load_design(tmp_path / "small")
    assert d.index_map.shape == (142, 142) and d.index_map.dtype == np.uint8


@pytest.mark.parametrize("edit,field", [
    (("wavelength_nm = 1550.0", "wavelength_nm = 1310.0"), "design.wavelength_nm"),
    (("period_um = 0.7", "period_um = 0.65"), "design.period_um"),
    (("aperture_mm = 0.1", "aperture_mm = 0.001"), "design.aperture_mm"),
    (("aperture_mm = 0.1", "aperture_mm = 0.1\n[discretizer]\ntransmission_threshold = 0.9999"),
     "discretizer.transmission_threshold"),
    (("aperture_mm = 0.1", "aperture_mm = 0.1\n[x_pol]\nfocal_lengths_mm = [50.0]"), "x_pol.focal_lengths_mm"),
    (("aperture_mm = 0.1", "aperture_mm = 0.1\nsupercel = 2"), "design.supercel"),
])
def test_design_bad_input(tmp_path, repo, edit, field):
    rec = tmp_path / "bad.toml"
    rec.write_text(DEMO.format(lib=repo / "library" / "paper.npz").replace(*edit))
    p = run_cli("design", rec)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0]
    assert sorted(x.name for x in tmp_path.iterdir()) == ["bad.toml"]


def test_paper_design_metrics_match_the_uniform_quantiser(tmp_path, repo):
    """The README's paper-design figures (51 M cells, committed library), against independent references:
    with every 16 x 16 bin covered the mapping error is a uniform quantiser's, bin / sqrt(12) per
    polarisation, and the peak is bounded by the largest nearest-atom distance on the torus."""
    from metadesign.design.recipe import load_design_recipe
    from metadesign.design.store import run_design

    d, _ = run_design(load_design_recipe(repo / "layouts" / "paper-5mm.toml"), tmp_path / "paper")
    m = d.metrics
    assert d.spec.n_cells == 7142 and m["n_cells_in_aperture"] == 7142**2
    q = 2 * np.pi / 16 / np.sqrt(12)  # 0.1134 rad
    for r in m["rmse_rad"]:
        assert r == pytest.approx(q, rel=0.05)
    assert max(m["peak_error_rad"]) < 2 * np.pi / 16  # < one bin: README says 0.33
    assert m["n_atoms"] == 256 and m["n_empty_bins"] == 0
    assert min(m["mean_T0"]) > 0.95  # every atom has T0 >= 0.7; README says 0.953


def test_distinct_supercells_counts_tuples_not_atoms():
    """#34's measurement on a map with a known answer: 2 x 2 tuples in reading order, (a, b, c, d) and
    (b, a, c, d) distinct; the most frequent tuple covering half of them."""
    from metadesign.design.discretize import distinct_supercells

    t1 = np.array([[1, 2], [3, 4]])
    t2 = np.array([[2, 1], [3, 4]])
    t3 = np.array([[300, 0], [0, 300]])
    im = np.block([[t1, t1, t1, t2], [t1, t1, t1, t3]])  # 8 supercells: 6 x t1, t2, t3
    r = distinct_supercells(im, 2)
    assert r["supercells"] == 8 and r["distinct"] == 3
    assert r["most_frequent_covering"]["0.5"] == 1 and r["most_frequent_covering"]["0.99"] == 3
    assert distinct_supercells(np.zeros((7, 7), int), 2)["supercells"] == 9  # whole supercells only


def test_design_phase_views_equal_the_scatter_path():
    """Consecutive rows and columns take the strided-view path; adding one far index forces the general
    (np.ix_) path: the shared cells must agree bit for bit, on both polarisations and any parity of start."""
    from metadesign.design.phase import design_phase
    from metadesign.design.recipe import load_design_recipe

    spec = load_design_recipe(Path(__file__).resolve().parents[1] / "layouts" / "demo.toml").spec
    for r0, c0 in ((0, 0), (3, 8), (10, 5)):
        iy, ix = np.arange(r0, r0 + 9), np.arange(c0, c0 + 13)
        for pol in (0, 1):
            fast = design_phase(spec, pol, iy, ix, 0.4)
            slow = design_phase(spec, pol, np.append(iy, r0 + 20), np.append(ix, c0 + 30), 0.4)
            assert np.array_equal(fast, slow[:-1, :-1])

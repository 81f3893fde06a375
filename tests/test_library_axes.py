"""Libraries with height and sidewall-angle axes: the nominal slice reproduces the committed 2-D library
exactly, the 2-D library's file and records are unchanged, and the as-fabricated look-up interpolates in
the new axes (equal to the 2-D path at the nominal, to the grid values on the grid)."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from conftest import REPO


@pytest.fixture(scope="module")
def axes_library(tmp_path_factory):
    from metadesign.library.build import build_library
    from metadesign.library.recipe import recipe_from_dict

    d = tomllib.loads((REPO / "library" / "paper.toml").read_text())
    d["sweep"] = {"w_min_um": 0.30, "w_max_um": 0.31, "step_nm": 5.0}
    d["convergence"]["check_cells_um"] = [[0.30, 0.31]]
    d["fab_axes"] = {"heights_um": [1.17, 1.2], "sidewall_deg": [88.0, 90.0], "slices": 4, "reference_slices": 8}
    d["convergence"]["tolerance_rad"] = 0.05
    out = tmp_path_factory.mktemp("axes") / "lib.npz"
    lib, rep = build_library(recipe_from_dict(d, "axes"), out, workers=1)
    return out, rep


def test_nominal_slice_reproduces_the_committed_library(axes_library):
    from metadesign.library.store import load_library

    out, rep = axes_library
    lib = load_library(out)
    ref = load_library(REPO / "library" / "paper.npz")
    i = [int(np.argmin(np.abs(ref.wx - w))) for w in lib.wx]
    assert np.allclose(ref.wx[i], lib.wx, atol=1e-15)
    np.testing.assert_allclose(lib.jones, ref.jones[np.ix_(i, i)], atol=1e-12)
    assert lib.fab["jones"].shape == (3, 3, 2, 2, 2, 2)
    np.testing.assert_allclose(lib.fab["jones"][:, :, 1, 1], lib.jones, atol=0)  # (1.2 um, 90 deg)
    # the other heights and angles are different pillars, and the mirror symmetry holds at each
    assert np.abs(lib.fab["jones"][:, :, 0, 1] - lib.jones).max() > 1e-3
    assert np.abs(lib.fab["jones"][:, :, 1, 0] - lib.jones).max() > 1e-3
    np.testing.assert_allclose(lib.fab["jones"][0, 2, 0, 0, 0, 0], lib.fab["jones"][2, 0, 0, 0, 1, 1], atol=1e-12)
    sc = rep["slice_convergence"]
    assert sc["slices"] == 4 and sc["reference_slices"] == 8 and sc["max_phase_change_rad"] < 0.05
    assert lib.meta["fab_axes"]["slices"] == 4


def test_two_d_library_file_and_records_are_unchanged(tmp_path):
    from metadesign.library.recipe import load_recipe
    from metadesign.library.store import load_library, save_library
    from metadesign.sensing.transmission import Perturbation

    ref = load_library(REPO / "library" / "paper.npz")
    assert ref.fab is None and "fab_axes" not in ref.meta
    assert "fab_axes" not in load_recipe(REPO / "library" / "paper.toml").to_dict()
    save_library(tmp_path / "again.npz", ref)  # the writer (with the fab-axes branch) gives the same bytes
    assert (tmp_path / "again.npz").read_bytes() == (REPO / "library" / "paper.npz").read_bytes()
    assert set(Perturbation(5e-9, 5e-9).to_dict()) == {"bias_x_nm", "bias_y_nm", "jitter_nm", "corner_nm", "seed"}


def test_fab_lookup_interpolates_in_height_and_angle(axes_library):
    from metadesign.library.store import load_library
    from metadesign.sensing.transmission import Perturbation, interpolate_t, interpolate_t_fab, pillar_transmission
    from metadesign.validation import ValidationError

    lib = load_library(axes_library[0])
    rng = np.random.default_rng(0)
    wx, wy = rng.uniform(0.30e-6, 0.31e-6, 20), rng.uniform(0.30e-6, 0.31e-6, 20)
    t2, _, _ = interpolate_t(lib, wx, wy)
    t4, n_out = interpolate_t_fab(lib, wx, wy, 1.2e-6, 90.0)
    np.testing.assert_allclose(t4, t2, atol=1e-6)
    assert n_out == 0
    # on the grid: the grid values; half-way in height: the mean of the two heights (multilinear)
    g = lib.fab["jones"]
    t, _ = interpolate_t_fab(lib, lib.wx[1], lib.wy[2], 1.17e-6, 88.0)
    np.testing.assert_allclose(t, [g[1, 2, 0, 0, 0, 0], g[1, 2, 0, 0, 1, 1]], atol=1e-6)
    t, _ = interpolate_t_fab(lib, lib.wx[1], lib.wy[2], 1.185e-6, 90.0)
    np.testing.assert_allclose(t[0], (g[1, 2, 0, 1, 0, 0] + g[1, 2, 1, 1, 0, 0]) / 2, atol=1e-6)
    _, n_out = interpolate_t_fab(lib, lib.wx[1], lib.wy[2], 1.25e-6, 90.0)
    assert n_out == 1  # outside the height axis: clamped and counted
    # the as-fabricated look-up: a 30 nm under-etch everywhere is the 1.17 um slice; a gradient varies by column
    im = np.array([[0, 1, 2, 0]])
    atoms = np.array([[300, 305], [305, 310], [310, 300]], float)
    t, _ = pillar_transmission(im, atoms, lib, Perturbation(height=-30e-9))
    np.testing.assert_allclose(t[0, 1, 0], g[1, 2, 0, 1, 0, 0], atol=1e-6)
    t0, _ = pillar_transmission(im, atoms, lib, Perturbation())
    # -20 nm at the +x edge: column 3 (u = +0.75) is 15 nm under-etched, columns 0, 1 (u = -0.75, -0.25) over:
    # beyond the height axis, so clamped to it and counted
    tg, n_out = pillar_transmission(im, atoms, lib, Perturbation(height_gradient=-20e-9))
    h = 1.2e-6 - 15e-9
    np.testing.assert_allclose(tg[0, 3], interpolate_t_fab(lib, 300e-9, 305e-9, h, 90.0)[0], atol=1e-6)
    np.testing.assert_allclose(tg[0, 0], t0[0, 0], atol=1e-6)
    assert n_out == 2
    ref = load_library(REPO / "library" / "paper.npz")
    with pytest.raises(ValidationError, match="fab axes"):
        pillar_transmission(im, atoms, ref, Perturbation(sidewall_deg=88.0))


def test_fab_library_correction_on_a_two_d_library_is_exact_on_the_same_grid(axes_library):
    """A 2-D library plus a fab library on the same grid: t_lib + t_F(h, a) - t_F(h0, 90) = t_F(h, a)."""
    from dataclasses import replace

    from metadesign.library.store import load_library
    from metadesign.sensing.transmission import Perturbation, pillar_transmission

    F = load_library(axes_library[0])
    flat = replace(F, fab=None)
    im = np.array([[0, 1, 2, 1]])
    atoms = np.array([[300, 305], [303, 309], [310, 300]], float)
    pert = Perturbation(height=-12e-9, sidewall_deg=89.0, sidewall_gradient_deg=-0.5)
    direct, _ = pillar_transmission(im, atoms, F, pert)
    corrected, _ = pillar_transmission(im, atoms, flat, pert, fab_lib=F)
    np.testing.assert_allclose(corrected, direct, atol=2e-6)
    assert np.abs(direct - pillar_transmission(im, atoms, flat, Perturbation())[0]).max() > 1e-3


def test_library_build_on_a_dask_cluster_gives_the_same_bytes(tmp_path):
    """The chunks on a Dask LocalCluster (2 single-threaded workers) or on the local pool: the same file."""
    from dask.distributed import LocalCluster

    from metadesign.library.build import build_library
    from metadesign.library.recipe import recipe_from_dict

    d = tomllib.loads((REPO / "library" / "paper.toml").read_text())
    d["sweep"] = {"w_min_um": 0.30, "w_max_um": 0.32, "step_nm": 10.0}
    d["solver"]["n_harmonics"] = 40
    d["convergence"] = {"tolerance_rad": 3.0, "reference_n_harmonics": 60, "check_cells_um": [[0.30, 0.31]]}
    d["fab_axes"] = {"heights_um": [1.2], "sidewall_deg": [88.0, 90.0], "slices": 2, "reference_slices": 4}
    rec = recipe_from_dict(d, "dask")
    build_library(rec, tmp_path / "local.npz", workers=1, chunk_size=2)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
        build_library(rec, tmp_path / "dask.npz", workers=1, chunk_size=2, scheduler=cl.scheduler_address)
    assert (tmp_path / "dask.npz").read_bytes() == (tmp_path / "local.npz").read_bytes()


def test_tolerance_cases_with_etch_depth_gradient(tmp_path, demo_products, axes_library):
    """A reconstruction-level case with an across-wafer etch-depth gradient renders the same turbulence through
    a different device (the fab library's correction on top of the layout's own library)."""
    import json

    from conftest import run_cli, tiny_model

    tiny_model(tmp_path)
    (tmp_path / "tol.toml").write_text(f"""[dataset]
layout = "{demo_products['layout']}"
sensor = "{REPO / 'sensing' / 'demo.toml'}"
turbulence = "{REPO / 'sensing' / 'turbulence.toml'}"
samples = 6
split = [0.5, 0.17, 0.33]
seed = 3
tensor_size = 16
shard_size = 6
[cases]
bias_nm = [0.0]
height_gradient_nm = [-25.0]
fab_library = "{axes_library[0]}"
[evaluate]
model = "m.safetensors"
noise_percent = 0.0
[finetune]
train = "t.toml"
epochs = 0
""")
    r = run_cli("tolerance", str(tmp_path / "tol.toml"), "-o", str(tmp_path / "out"), "-j", "1", "--json")
    assert r.returncode == 0, r.stderr
    rows = {x["case"]: x for x in json.loads(r.stdout)["rows"]}
    assert set(rows) == {"nominal", "heightgrad-25nm"}
    g = rows["heightgrad-25nm"]
    assert g["height_gradient_nm"] == -25.0 and "after" not in g
    assert g["before"]["npib_none"] == pytest.approx(rows["nominal"]["before"]["npib_none"], rel=1e-6)
    import zarr

    def power(case):
        return np.asarray(zarr.open_group(str(tmp_path / "out" / f"case-{case}" / "dataset"), mode="r")["psf_power"][:])

    assert not np.allclose(power("heightgrad-25nm"), power("nominal"), rtol=1e-4, atol=0)


def test_supercell_of_identical_pillars_is_the_committed_library_cell():
    """At the library's own resolution (supercell nG 797 <-> unit nG 197) four identical pillars reproduce the
    committed library's entry."""
    from metadesign.library.rcwa import Stack
    from metadesign.library.store import load_library
    from metadesign.library.supercell import solve_supercell
    from metadesign.library.supercells import matched_unit_harmonics

    lib = load_library(REPO / "library" / "paper.npz")
    st = Stack()
    ns, nu = matched_unit_harmonics(800, st)
    assert nu - 1 == lib.meta["solver"]["n_harmonics"]
    i, j = int(np.argmin(np.abs(lib.wx - 0.30e-6))), int(np.argmin(np.abs(lib.wy - 0.20e-6)))
    sc = solve_supercell([[(lib.wx[i], lib.wy[j])] * 2] * 2, st, ns)
    np.testing.assert_allclose(sc.jones, lib.jones[i, j], atol=1e-7)

"""Hostile inputs to the newest commands, as a new user would give them: each ends in one line on stderr,
exit 2, before the work, with nothing written or changed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import run_main

REPO = Path(__file__).resolve().parents[1]


def _refused(argv, capsys, match: str, folder: Path | None = None):
    before = _tree(folder) if folder is not None else None
    rc, _, err = run_main(argv, capsys)
    assert rc == 2 and len(err) == 1 and err[0].startswith("metadesign: error:"), (argv, rc, err)
    assert match in err[0], err[0]
    if folder is not None:
        assert _tree(folder) == before, "a refused command wrote or changed files"
    return err[0]


def _tree(folder: Path) -> set:
    return {(str(p.relative_to(folder)), p.stat().st_size) for p in Path(folder).rglob("*")}


@pytest.mark.parametrize("address, match", [
    ("tcp://127.0.0.1:9", "nothing listens there"),
    ("127.0.0.1:8786", "expected a Dask scheduler address"),
    ("tcp://127.0.0.1", "expected tcp://host:port"),
    ("tcp://no-such-host.invalid:8786", "cannot resolve host"),
])
def test_a_refused_scheduler_is_refused_before_any_output(address, match, tmp_path, capsys):
    """Every command with --scheduler checks it before opening its output: no partial folder is left."""
    out = tmp_path / "lib.npz"
    _refused(["library", "build", REPO / "library" / "paper.toml", "-o", out, "--scheduler", address], capsys,
             match, tmp_path)
    assert not any(tmp_path.iterdir())


@pytest.fixture(scope="module")
def design_arrays(tmp_path_factory):
    """A small real design's arrays (a 0.1 mm aperture)."""
    from metadesign.design.recipe import load_design_recipe
    from metadesign.design.store import run_design

    base = tmp_path_factory.mktemp("design")
    rec = base / "tiny.toml"
    rec.write_text(f'[design]\nlibrary = "{REPO / "library" / "paper.npz"}"\nwavelength_nm = 1550.0\n'
                   'period_um = 0.7\naperture_mm = 0.1\n')
    run_design(load_design_recipe(rec), base / "d")
    with np.load(base / "d" / "design.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}, base / "d"


@pytest.mark.parametrize("name, damage, match", [
    ("atom_t", lambda a: a[:3], "atom_t has shape"),
    ("atom_wx_m", lambda a: a.astype(str), "atom_wx_m has shape"),
    ("atom_T0", lambda a: a[:, :1], "atom_T0 has shape"),
    ("atom_lib_index", lambda a: a.astype(np.float64), "atom_lib_index has shape"),
    ("atom_wy_m", lambda a: np.where(np.arange(len(a)) == 0, np.nan, a), "NaN or infinite"),
    ("atom_wy_m", lambda a: -a, "widths must be > 0"),
])
def test_a_design_with_a_broken_atom_table_is_refused_by_every_reader(name, damage, match, design_arrays, tmp_path,
                                                                      capsys):
    """design show / plot and layout write read the design through one loader that checks the atom table
    (was: an IndexError or a ufunc error in the middle of the work, or a layout written from it)."""
    arrays, _ = design_arrays
    bad = dict(arrays)
    bad[name] = damage(arrays[name])
    f = tmp_path / "bad.npz"
    np.savez(f, **bad)
    for argv in (["design", "show", f], ["design", "plot", f, "-o", tmp_path / "p.png"],
                 ["layout", "write", f, "-o", tmp_path / "l.oas"]):
        _refused(argv, capsys, match, tmp_path)


GOOD_DIVERSITY = {"focal_length_mm": [[50.0, 50.5, 51.0, 51.5], [49.0, 49.5, 52.0, 52.5]], "zernike_noll": [4, 5],
                  "zernike_rad": [[[0.1, 0.0]] * 4, [[0.0, -0.2]] * 4]}


@pytest.mark.parametrize("change, match", [
    ({"focal_length_mm": [[float("nan"), 50.5, 51.0, 51.5], [49.0, 49.5, 52.0, 52.5]]}, "focal_length_mm"),
    ({"focal_length_mm": [[-50.0, 50.5, 51.0, 51.5], [49.0, 49.5, 52.0, 52.5]]}, "focal_length_mm"),
    ({"focal_length_mm": [[50.0, 50.5, 51.0], [49.0, 49.5, 52.0]]}, "focal_length_mm"),
    ({"zernike_noll": [4, 4]}, "zernike_noll"),
    ({"zernike_noll": [1, 5]}, "zernike_noll"),
    ({"zernike_rad": [[[float("inf"), 0.0]] * 4, [[0.0, -0.2]] * 4]}, "zernike_rad"),
    ({"zernike_rad": [[[0.1]] * 4, [[0.0]] * 4]}, "zernike_rad"),
])
def test_a_codesign_diversity_a_design_build_would_refuse_is_refused_where_it_is_read(change, match, tmp_path):
    """codesign reads diversity.json, evaluation a card's record: both refuse, in one line, what `design build`
    would refuse later (a NaN, negative or duplicated diversity) or what would evaluate to NaN."""
    from metadesign.reconstruction.codesign import check_diversity
    from metadesign.studies.codesign import read_diversity
    from metadesign.validation import ValidationError

    assert check_diversity(dict(GOOD_DIVERSITY)) == GOOD_DIVERSITY
    bad = {**GOOD_DIVERSITY, **change}
    with pytest.raises(ValidationError, match=match):
        check_diversity(bad)
    import json

    (tmp_path / "diversity.json").write_text(json.dumps(bad).replace("NaN", "NaN"))
    with pytest.raises(ValidationError, match=match):
        read_diversity(tmp_path)


def test_a_refusal_after_the_work_began_leaves_nothing_behind(tmp_path):
    """A product folder (and its scratch folder) made by this call is removed when the work ends in a
    refusal (an input found bad late: NaN labels, a wrong kind); an interruption keeps both (it resumes), and
    a folder that existed before the call is never removed."""
    from metadesign.execution import make_scratch, scratch_path
    from metadesign.outputs import product
    from metadesign.validation import ValidationError

    out = tmp_path / "report"

    def work(exc):
        with product(out, "codesign", scratch=(scratch_path(out),)):
            (out / "design.toml").write_text("written before the refusal\n")
            make_scratch(scratch_path(out, "solves"))
            raise exc

    with pytest.raises(ValidationError):
        work(ValidationError("labels hold NaN"))
    assert not out.exists() and not scratch_path(out).exists()
    with pytest.raises(KeyboardInterrupt):
        work(KeyboardInterrupt())
    assert (out / "design.toml").exists() and scratch_path(out, "solves").is_dir()
    with pytest.raises(ValidationError):  # a resumed run refused: what the earlier run made stays
        work(ValidationError("labels hold NaN"))
    assert (out / "design.toml").exists() and scratch_path(out, "solves").is_dir()


def test_codesign_checks_its_base_recipe_and_dataset_before_writing(tmp_path, capsys):
    """codesign with a --base that is not a design recipe, or a --dataset that is not a dataset, is refused in
    one line with no report folder left (it wrote the design recipe first, then refused)."""
    run = REPO / "sensing" / "codesign-demo" / "diversity-demo-x2-adapted.json"
    base = REPO / "layouts" / "paper-5mm.toml"
    _refused(["codesign", run, "--dataset", tmp_path, "--base", base, "-o", tmp_path / "cd"], capsys,
             "not a metadesign dataset", tmp_path)
    _refused(["codesign", run, "--dataset", tmp_path, "--base", REPO / "sensing" / "demo.toml", "-o",
              tmp_path / "cd"], capsys, "not a design recipe", tmp_path)


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    """The committed fast supercell table with one infinite width, and with one NaN label."""
    base = tmp_path_factory.mktemp("tables")
    with np.load(REPO / "library" / "paper-supercells-fast.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    w = arrays["widths_m"].copy()
    w[3, 0, 0, 0] = np.inf
    np.savez(base / "inf-width.npz", **{**arrays, "widths_m": w})
    t = arrays["t"].copy()
    t[5, 1] = np.nan
    np.savez(base / "nan-label.npz", **{**arrays, "t": t})
    return base


@pytest.mark.parametrize("table, match", [("inf-width.npz", "widths_m must be finite"),
                                          ("nan-label.npz", "NaN or infinite")])
@pytest.mark.parametrize("command", [["library", "ladder"], ["library", "peds"], ["library", "coupling"]])
def test_a_supercell_table_with_nan_or_infinite_values_is_refused_before_any_solve(command, table, match, tables,
                                                                                   tmp_path, capsys):
    """ladder (a traceback on an infinite width), peds (NaN labels found after the solves) and coupling read
    the table through one loader that checks its rows."""
    out = tmp_path / ("o.safetensors" if command[1] == "coupling" else "o.json")
    _refused([*command, tables / table, "-o", out], capsys, match, tmp_path)
    assert not any(tmp_path.iterdir())


def test_matched_truncations_without_grcwas_dense_setup():
    """The matched harmonic sets equal those grcwa's Init_Setup makes (its G list, the reference), computed
    from the lattice alone: a truncation far above any solve (nG 20,000) takes milliseconds, not 6 GB."""
    import time

    import grcwa

    from metadesign.library.store import load_library
    from metadesign.library.supercells import matched_harmonics, matched_unit_harmonics

    lib = load_library(REPO / "library" / "paper.npz")

    def grcwa_set(n):  # the reference: the G list grcwa's own set-up makes
        o = grcwa.obj(int(n), [1.0, 0.0], [0.0, 1.0], 0.5, 0.0, 0.0, verbose=0)
        o.Add_LayerUniform(0.0, 1.0)
        o.Init_Setup(Gmethod=0)
        return {tuple(g) for g in np.asarray(o.G)}, int(o.nG)

    def reference(n_big, q):  # matched_harmonics as it was written on grcwa's set-up
        s, ns = grcwa_set(n_big)
        sub = {(a // q, b // q) for a, b in s if a % q == 0 and b % q == 0}
        u, nu = grcwa_set(len(sub) + 1)
        assert u == sub
        return ns + 1, nu + 1

    for n in (21, 45, 97, 357):
        assert matched_unit_harmonics(n, lib.stack) == reference(n, 2)
    for n in (100, 1300):
        assert matched_harmonics(n, lib.stack, 4, 2) == reference(n, 2)
    t0 = time.perf_counter()
    assert matched_harmonics(20000, lib.stack, 4, 2)[0] > 19000
    assert time.perf_counter() - t0 < 10


def test_absurd_patch_and_certified_requests_are_refused_with_their_estimate(design_arrays, tmp_path, capsys):
    """A ring level above the patches' own truncation, a patch truncation whose solves would not fit in memory,
    and a certified sample larger than the device are refused in one line before any solve."""
    _, design = design_arrays
    _refused(["library", "patches", design, "--ring-levels", "45", "2000", "-o", tmp_path / "p.json"], capsys,
             "above the patches' own supercell truncation", tmp_path)
    _refused(["library", "patches", design, "--harmonics", "20000", "-o", tmp_path / "p.json"], capsys,
             "of memory", tmp_path)
    _refused(["library", "coupling-check", design, "--certified", "1000000", "-o", tmp_path / "cc"], capsys,
             "more than the device's", tmp_path)
    _refused(["library", "coupling-check", design, "--certified", "16", "--ring", "1000000", "-o", tmp_path / "cc"],
             capsys, "at most --certified 16", tmp_path)
    _refused(["library", "coupling-check", design, "--certified", "16", "--peds",
              REPO / "library" / "paper-coupling.safetensors", "-o", tmp_path / "cc"], capsys,
             "not a PEDS supercell model", tmp_path)

"""Products carry their provenance; clear apertures of any shape; old CLI spellings keep working."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from metadesign.cli import main

REPO = Path(__file__).resolve().parents[1]
DEMO = (REPO / "layouts" / "demo.toml").read_text()


def _recipe(tmp_path: Path, extra: str, name="r.toml", lib=None) -> Path:
    text = DEMO.replace('"../library/paper.npz"', f'"{lib or REPO / "library" / "paper.npz"}"')
    text = text.replace('clear_aperture = "square"\n', extra)
    p = tmp_path / name
    p.write_text(text)
    return p


L_SHAPE_UM = [[-250, -250], [250, -250], [250, 0], [0, 0], [0, 250], [-250, 250]]


def test_polygon_aperture_design_layout_and_forward_model(tmp_path):
    from matplotlib.path import Path as MplPath

    from metadesign.conventions import centered
    from metadesign.design.store import load_design
    from metadesign.layouts import read_layout
    from metadesign.sensing.model import AsFabricated, load_sensing_recipe
    from metadesign.sensing.render import render_psf

    r = _recipe(tmp_path, f'clear_aperture = "polygon"\naperture_polygon_um = {L_SHAPE_UM}\n')
    assert main(["design", "build", str(r), "-o", str(tmp_path / "poly")]) == 0
    d = load_design(tmp_path / "poly")
    n = d.spec.n_cells
    x = centered(n, d.spec.period) * 1e6
    X, Y = np.meshgrid(x, x)
    # an independent point-in-polygon (matplotlib), with a hair of tolerance for points on the edges
    inside = MplPath(np.array(L_SHAPE_UM, float)).contains_points(np.c_[X.ravel(), Y.ravel()], radius=1e-6)
    has = (d.index_map != d.empty).ravel()
    assert has.sum() == pytest.approx(0.75 * n * n, rel=0.01)
    assert np.mean(has == inside) > 0.999  # only cells whose centre lies on an edge may differ
    # the same outline from a WKT file and from a GeoJSON file
    (tmp_path / "o.wkt").write_text("POLYGON ((" + ", ".join(f"{a} {b}" for a, b in L_SHAPE_UM + L_SHAPE_UM[:1]) + "))")
    (tmp_path / "o.geojson").write_text(json.dumps({"type": "Polygon", "coordinates": [L_SHAPE_UM + L_SHAPE_UM[:1]]}))
    for f in ("o.wkt", "o.geojson"):
        rf = _recipe(tmp_path, f'clear_aperture = "polygon"\naperture_file = "{f}"\n', name=f + ".toml")
        assert main(["design", str(rf), "-o", str(tmp_path / f.replace(".", "-"))]) == 0
        np.testing.assert_array_equal(load_design(tmp_path / f.replace(".", "-")).index_map, d.index_map)
    # the layout's outline layer (10) is the square frame minus the L: its area says so
    assert main(["layout", str(tmp_path / "poly")]) == 0
    import gdstk

    lib = gdstk.read_oas(str(tmp_path / "poly" / "layout.oas"), unit=1e-9)
    top = [c for c in lib.cells if c.name == "METASURFACE"][0]
    outline = sum(p.area() for p in top.polygons if p.layer == 10)
    half = n * 700 // 2
    assert outline == pytest.approx((2 * half + 2000) ** 2 - 0.75 * 500_000 ** 2, rel=1e-4)  # the L is 500 um
    # the forward model honours the outline: 3/4 of the square's light reaches the sensor
    lc = read_layout(tmp_path / "poly" / "layout.oas")
    assert lc.provenance["clear_aperture"]["kind"] == "polygon"
    sr = load_sensing_recipe(REPO / "sensing" / "demo.toml")
    fab = AsFabricated.from_files(tmp_path / "poly" / "layout.oas")
    sq = tmp_path / "sq"
    assert main(["design", str(_recipe(tmp_path, 'clear_aperture = "square"\n', name="sq.toml")), "-o", str(sq)]) == 0
    assert main(["layout", str(sq)]) == 0
    poly, square = render_psf(fab, sr), render_psf(AsFabricated.from_files(sq / "layout.oas"), sr)
    pupil_ratio = np.sum(np.abs(poly.pupil.G.sum(1)) ** 2) / np.sum(np.abs(square.pupil.G.sum(1)) ** 2)
    assert pupil_ratio == pytest.approx(0.75, abs=0.015)  # propagating light leaving the metasurface (1 if ignored)
    # on the sensor a little less: the L's PSF spreads more light past the frame
    assert 0.68 < poly.frames.sum() / square.frames.sum() < 0.75


def test_bad_polygons_are_refused(tmp_path, capsys):
    bow = [[-100, -100], [100, 100], [100, -100], [-100, 100]]
    for extra, msg in ((f'clear_aperture = "polygon"\naperture_polygon_um = {bow}\n', "invalid"),
                       ('clear_aperture = "polygon"\naperture_polygon_um = [[1000, 1000], [2000, 1000], [2000, 2000]]\n',
                        "does not overlap"),
                       ('clear_aperture = "square"\naperture_polygon_um = [[0, 0], [1, 0], [0, 1]]\n', "only with"),
                       ('clear_aperture = "polygon"\naperture_file = "missing.wkt"\n', "cannot read")):
        assert main(["design", str(_recipe(tmp_path, extra)), "-o", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and msg in err, err
    assert not (tmp_path / "x").exists()


def test_library_found_relative_to_the_product_and_by_sha256(tmp_path, monkeypatch):
    from metadesign.sensing.model import AsFabricated

    libdir = tmp_path / "libs"
    libdir.mkdir()
    shutil.copy(REPO / "library" / "paper.npz", libdir / "mine.npz")
    work = tmp_path / "work"
    work.mkdir()
    (work / "r.toml").write_text(DEMO.replace('"../library/paper.npz"', '"../libs/mine.npz"'))
    monkeypatch.chdir(work)
    assert main(["design", "r.toml", "-o", "out"]) == 0
    assert main(["layout", "out"]) == 0
    meta = json.loads((work / "out" / "layout.oas.json").read_text())["provenance"]
    assert meta["library_path"] == "../../libs/mine.npz"
    monkeypatch.chdir(tmp_path)  # from anywhere else
    fab = AsFabricated.from_files(work / "out" / "layout.oas")
    assert fab.lib.identity == meta["library_sha256"]
    # moved: the recorded path breaks, the sha256 finds the copy beside the product
    shutil.move(libdir / "mine.npz", work / "out" / "moved.npz")
    fab = AsFabricated.from_files(work / "out" / "layout.oas")
    assert fab.lib.identity == meta["library_sha256"]


def test_psf_product_carries_its_provenance(demo_products, tmp_path):
    from metadesign.library.locate import file_sha256
    from metadesign.sensing.render import load_psf

    out = tmp_path / "psf"
    assert main(["psf", str(demo_products["layout"]), "--sensor", str(demo_products["sensor"]), "-o", str(out),
                 "--bias-nm", "3", "--jitter-nm", "1", "--seed", "7"]) == 0
    z, meta = load_psf(out / "psf.npz")
    assert meta["format"] == "metadesign.psf/1"
    assert meta["layout"]["sha256"] == file_sha256(demo_products["layout"])
    assert meta["library_sha256"] == file_sha256(REPO / "library" / "paper.npz")
    assert meta["perturbation"]["bias_x_nm"] == pytest.approx(3) and meta["perturbation"]["seed"] == 7
    assert meta["sensor"]["magnification"] == 100.0
    # the channel table is data: Table S1 scaled 10x for the demo
    f = {(c["pol"], c["k"]): c["focal_length_m"] for c in meta["channels"]}
    np.testing.assert_allclose([f[("x", k)] for k in range(1, 5)], [4.88e-3, 4.92e-3, 4.96e-3, 5.00e-3])
    np.testing.assert_allclose([f[("y", k)] for k in range(1, 5)], [5.04e-3, 5.08e-3, 5.12e-3, 5.16e-3])
    assert z["tensor"].shape == (8, 256, 256)


def test_old_spellings_and_real_subcommands(demo_products, tmp_path, capsys):
    d = str(demo_products["design"])
    assert main(["design", "show", d, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_atoms"] > 0
    assert main(["layout", d, "-o", str(tmp_path / "a")]) == 0  # = layout write
    assert main(["layout", "write", d, "-o", str(tmp_path / "b")]) == 0
    assert (tmp_path / "a.oas").read_bytes() == (tmp_path / "b.oas").read_bytes()
    # verify flags belong to verify only: given to write they are an error, not silently ignored
    with pytest.raises(SystemExit) as e:
        main(["layout", d, "--klayout", "--min-gap-nm", "5"])
    assert e.value.code == 2
    assert capsys.readouterr().err.startswith("metadesign: error:")


def test_device_from_design_equals_device_from_its_layout(demo_products):
    from metadesign.design.store import load_design
    from metadesign.sensing.model import AsFabricated, load_sensing_recipe

    sr = load_sensing_recipe(demo_products["sensor"])
    a = AsFabricated.from_files(demo_products["layout"]).pupil(sr.sensor.distance, sr.pupil_grid)
    b = AsFabricated.from_design(load_design(demo_products["design"])).pupil(sr.sensor.distance, sr.pupil_grid)
    np.testing.assert_array_equal(a.G, b.G)

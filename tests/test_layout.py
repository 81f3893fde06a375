"""Stage 3: layout round trips, KLayout cross-check, orientation, gdstk traps, DRC, bad files."""

import json

import numpy as np
import pytest
from conftest import run_cli

from metadesign.config import InputError
from metadesign.design import AtomTable, SupercellSpec, paper_channels
from metadesign.design.store import Design
from metadesign.layouts import (
    LayoutOptions,
    drc_check,
    read_layout,
    read_layout_klayout,
    verify_against_design,
    write_layout,
)

CX, CY = paper_channels()


def synthetic_design(n=9, n_atoms=5, seed=0, circular=False, period=0.7e-6):
    rng = np.random.default_rng(seed)
    wx = np.round(rng.uniform(100, 500, n_atoms)) * 1e-9
    wy = np.round(rng.uniform(100, 500, n_atoms)) * 1e-9
    wx[0], wy[0] = 101e-9, 333e-9  # odd widths: centred 0.5 nm low
    t = np.exp(1j * rng.uniform(-np.pi, np.pi, (n_atoms, 2)))
    atoms = AtomTable(wx, wy, t, np.full((n_atoms, 2), 0.9), np.zeros((n_atoms, 2), int), 0, n_atoms, 1.0)
    im = rng.integers(0, n_atoms, (n, n)).astype(np.uint8)
    empty = None
    spec = SupercellSpec(1.55e-6, period, n, 1, CX[:1], CY[:1], circular_aperture=circular)
    if circular:
        empty = 255
        x = (np.arange(n) - (n - 1) / 2) * period
        im[x[None, :] ** 2 + x[:, None] ** 2 > (n * period / 2) ** 2] = empty
    meta = {"name": "synthetic", "recipe": {}, "library": {"sha256": "0"}}
    return Design(spec, atoms, im, (0.0, 0.0), {}, meta, empty)


@pytest.mark.parametrize("fmt", ["oas", "gds"])
@pytest.mark.parametrize("n,circular", [(9, False), (40, True), (1, False)])
def test_round_trip_exact_and_klayout_agrees(tmp_path, fmt, n, circular):
    d = synthetic_design(n=n, circular=circular)
    rep = write_layout(d, tmp_path / f"l.{fmt}", fmt)
    assert rep["pillars"] == (int(np.count_nonzero(d.index_map != 255)) if circular else n * n)
    lc = read_layout(tmp_path / f"l.{fmt}")
    v = verify_against_design(lc, d)
    assert v["exact"], v["problems"]
    k = verify_against_design(read_layout_klayout(tmp_path / f"l.{fmt}"), d)
    assert k["exact"], k["problems"]
    assert k["counts_per_atom"] == v["counts_per_atom"]
    im = d.index_map.astype(int)
    np.testing.assert_array_equal(lc.index_map, np.where(im == 255, -1, im) if circular else im)
    side = json.loads((tmp_path / f"l.{fmt}.json").read_text())
    assert side["provenance"]["n_cells"] == n and side["pillars"] == rep["pillars"]


@pytest.mark.parametrize("fmt", ["oas", "gds"])
def test_same_design_same_bytes(tmp_path, fmt):
    d = synthetic_design(n=12, circular=True)
    write_layout(d, tmp_path / f"a.{fmt}", fmt)
    write_layout(d, tmp_path / f"b.{fmt}", fmt)
    assert (tmp_path / f"a.{fmt}").read_bytes() == (tmp_path / f"b.{fmt}").read_bytes()


def test_corner_pillars_orientation_and_sizes_with_klayout(tmp_path):
    """Cell (ix, iy) at x = (ix - (n-1)/2) p, y = (iy - (n-1)/2) p: no half-period shift, no axis swap, no mirror."""
    import klayout.db as kdb

    n, p = 8, 700
    d = synthetic_design(n=n, n_atoms=4, seed=5)
    d.index_map[:] = 0
    d.index_map[0, n - 1] = 1  # (ix = n-1, iy = 0): +x, -y corner
    d.index_map[n - 1, 0] = 2  # (ix = 0, iy = n-1): -x, +y corner
    d.index_map[n - 1, n - 1] = 3
    write_layout(d, tmp_path / "c.oas", "oas")
    ly = kdb.Layout()
    ly.read(str(tmp_path / "c.oas"))
    top = ly.cell("METASURFACE")
    found = {}
    for inst in top.each_inst():
        name = ly.cell(inst.cell_index).name
        if name in ("ATOM_001", "ATOM_002", "ATOM_003"):
            b = inst.bbox()
            found[name] = (inst.trans.disp.x, inst.trans.disp.y, b.width(), b.height())
    half = (n - 1) * p // 2  # 2450 nm
    wx = np.round(d.atoms.wx * 1e9).astype(int)
    wy = np.round(d.atoms.wy * 1e9).astype(int)
    assert found["ATOM_001"] == (half, -half, wx[1], wy[1])
    assert found["ATOM_002"] == (-half, half, wx[2], wy[2])
    assert found["ATOM_003"] == (half, half, wx[3], wy[3])
    # pillar shape: an odd 101 nm x 333 nm rectangle centred 0.5 nm towards -x/-y of its cell centre
    cell0 = ly.cell("ATOM_000")
    b = next(iter(cell0.shapes(ly.find_layer(1, 0)).each())).bbox()
    assert (b.left, b.right, b.bottom, b.top) == (-51, 50, -167, 166)


def test_gdstk_traps_origin_and_negative_offsets(tmp_path):
    """Odd n puts a cell on the origin; atoms with one pillar (no repetition), atoms whose
    first pillar is at the far +x end of a row (later offsets have negative x)."""
    d = synthetic_design(n=7, n_atoms=4, seed=1)
    d.index_map[:] = 0
    d.index_map[3, 3] = 1  # the single pillar at (0, 0)
    d.index_map[0, 6] = 2  # first in raster order at +x, then negative-x offsets
    d.index_map[1, 0] = 2
    d.index_map[6, 0] = 2
    d.index_map[6, 6] = 3  # single pillar in the far corner
    for fmt in ("oas", "gds"):
        write_layout(d, tmp_path / f"t.{fmt}", fmt)
        for reader in (read_layout, read_layout_klayout):
            v = verify_against_design(reader(tmp_path / f"t.{fmt}"), d)
            assert v["exact"], (fmt, reader.__name__, v["problems"])


def test_verification_catches_one_nm_shift_and_swaps(tmp_path):
    import gdstk

    d = synthetic_design(n=10, n_atoms=6, seed=2)
    write_layout(d, tmp_path / "a.oas", "oas")
    lib = gdstk.read_oas(str(tmp_path / "a.oas"), unit=1e-9)
    top = [c for c in lib.cells if c.name == "METASURFACE"][0]
    ref = top.references[0]
    ref.origin = (ref.origin[0] + 1, ref.origin[1])  # shift one atom's pillars by 1 nm
    lib.write_oas(str(tmp_path / "b.oas"), validation="crc32")
    v = verify_against_design(read_layout(tmp_path / "b.oas"), d)
    assert not v["exact"] and any("off the" in p for p in v["problems"])
    # two pillars of different atoms swapped: counts per atom unchanged, exact check fails
    swapped = synthetic_design(n=10, n_atoms=6, seed=2)
    i, j = np.argwhere(swapped.index_map != swapped.index_map[0, 0])[0]
    swapped.index_map[0, 0], swapped.index_map[i, j] = swapped.index_map[i, j], swapped.index_map[0, 0]
    v = verify_against_design(read_layout(tmp_path / "a.oas"), swapped)
    assert not v["exact"] and v["mismatched_cells"] == 2


def test_design_rules_pass_and_fail(tmp_path):
    d = synthetic_design(n=20, n_atoms=5, seed=3)
    write_layout(d, tmp_path / "r.oas", "oas")
    lc = read_layout(tmp_path / "r.oas")
    wmin = int(np.round(min(d.atoms.wx.min(), d.atoms.wy.min()) * 1e9))
    gap = int(700 - np.round(max(d.atoms.wx.max(), d.atoms.wy.max()) * 1e9))
    ok = drc_check(lc, wmin, gap, 20)
    assert ok["passed"] and ok["geometric_window"]["pillars_in_window"] == 400
    bad = drc_check(lc, wmin + 1, gap + 1, 20)
    assert not bad["passed"]
    assert bad["geometric_window"]["width_violations"] > 0 and bad["geometric_window"]["space_violations"] > 0


def test_layout_cli_end_to_end_and_bad_files(tmp_path, repo):
    rec = tmp_path / "small.toml"
    rec.write_text(f'[design]\nlibrary = "{repo / "library" / "paper.npz"}"\nwavelength_nm = 1550.0\n'
                   'period_um = 0.7\naperture_mm = 0.05\nclear_aperture = "circle"\n')
    assert run_cli("design", rec).returncode == 0
    p = run_cli("layout", tmp_path / "small", "--format", "both", "--json")
    assert p.returncode == 0, p.stderr
    assert len(json.loads(p.stdout)["layouts"]) == 2
    for f in ("layout.oas", "layout.gds"):
        p = run_cli("layout", "verify", tmp_path / "small" / f, "--klayout", "--json")
        assert p.returncode == 0, p.stdout + p.stderr
        r = json.loads(p.stdout)
        assert r["passed"] and r["klayout"]["exact"] and r["gdstk"]["exact"]
    p = run_cli("layout", "preview", tmp_path / "small" / "layout.oas")
    assert p.returncode == 0 and (tmp_path / "small" / "layout-preview.png").exists()
    good = (tmp_path / "small" / "layout.oas").read_bytes()
    cases = {"trunc.oas": good[: len(good) // 2], "foreign.oas": b"not a layout at all",
             "flip.oas": good[:40] + bytes([good[40] ^ 0xFF]) + good[41:],
             "trunc.gds": (tmp_path / "small" / "layout.gds").read_bytes()[:1000]}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        p = run_cli("layout", "verify", tmp_path / name, "--design", tmp_path / "small")
        assert p.returncode == 2, (name, p.stderr)
        assert len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr


def test_layout_options_validated():
    with pytest.raises(InputError, match="off the pillar layer"):
        LayoutOptions(layer=3, outline_layer=3)
    with pytest.raises(InputError, match="grid-nm"):
        LayoutOptions(grid_nm=0)


@pytest.mark.parametrize("fmt", ["oas", "gds"])
def test_one_top_cell_even_when_atoms_go_unused(tmp_path, fmt):
    """A mask shop expects one top cell: atoms the layout does not place get no cell (their rectangles stay
    in the provenance's atom table), and both readers still read the layout back exactly."""
    import klayout.db as kdb

    d = synthetic_design(n=2, n_atoms=9)  # 4 pillars, at most 4 of the 9 atoms placed
    used = set(np.unique(d.index_map).tolist())
    assert len(used) < 9
    write_layout(d, tmp_path / f"l.{fmt}", fmt)
    ly = kdb.Layout()
    ly.read(str(tmp_path / f"l.{fmt}"))
    tops = [c.name for c in ly.top_cells()]
    assert tops == ["METASURFACE"], tops
    atom_cells = sorted(c.name for c in ly.each_cell() if c.name.startswith("ATOM_"))
    assert atom_cells == [f"ATOM_{a:03d}" for a in sorted(used)]
    for reader in (read_layout, read_layout_klayout):
        v = verify_against_design(reader(tmp_path / f"l.{fmt}"), d)
        assert v["exact"], v["problems"]


def test_layout_library_in_a_micrometre_host(demo_products, tmp_path):
    """#32: the metasurface placed into a 1 um host library (gdsfactory's and most masks' unit) keeps its
    size: KLayout reads the host and finds the metasurface 2 mm right of the chip origin at its true size
    (before: 1000x too large, +-250,000 um for the 0.5 mm demo)."""
    import gdstk
    import klayout.db as kdb

    from metadesign.design.store import load_design
    from metadesign.layouts import layout_library

    d = load_design(demo_products["design"])
    nm = layout_library(d)
    (x0, y0), (x1, y1) = nm.top_level()[0].bounding_box()  # nm
    um = layout_library(d, unit=1e-6)
    assert um.unit == 1e-6
    host = gdstk.Library("MASK", unit=1e-6, precision=1e-9)
    chip = host.new_cell("CHIP")
    chip.add(gdstk.Reference(um.top_level()[0], origin=(2000, 0)))  # 2 mm, in um
    host.add(*um.cells)
    host.write_oas(str(tmp_path / "mask.oas"))
    ly = kdb.Layout()
    ly.read(str(tmp_path / "mask.oas"))
    box = ly.top_cell().dbbox()  # um
    assert box.width() == pytest.approx((x1 - x0) * 1e-3, abs=2e-3)
    assert box.center().x == pytest.approx(2000 + (x0 + x1) / 2 * 1e-3, abs=2e-3)
    assert 0.4 < box.width() / 1000 < 0.6  # the 0.5 mm demo aperture, in mm


def test_the_metasurface_is_a_gdsfactory_component_placed_in_micrometres(demo_products):
    """#32: gdsfactory users get the written layout as a Component: one instance per pillar (none
    flattened), micrometre coordinates on the layout's 1 nm grid (the aperture's extent, checked against
    the design's), and it places into a chip like any cell."""
    gf = pytest.importorskip("gdsfactory")
    from metadesign.design.store import load_design
    from metadesign.layouts import metasurface_component

    d = load_design(demo_products["design"])
    c = metasurface_component(demo_products["layout"])
    n_pillars = int((d.index_map != (d.empty if d.empty is not None else -1)).sum())
    assert len(c.insts) == n_pillars
    half = d.spec.n_cells * d.spec.period / 2 * 1e6  # um
    box = c.dbbox(c.kcl.layer(1, 0))
    assert abs(box.right - half) < 0.36 and abs(box.left + half) < 0.36  # within half a period
    assert abs(box.top - half) < 0.36 and abs(box.bottom + half) < 0.36
    chip = gf.Component()
    ref = chip.add_ref(c)
    ref.dmove((2000.0, 0.0))
    assert abs(chip.dbbox(chip.kcl.layer(1, 0)).center().x - 2000.0) < 0.5
    assert metasurface_component(demo_products["layout"]).name == c.name  # named by content

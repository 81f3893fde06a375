"""The streaming OASIS verifier (#35): the file read once in bounded memory, every pillar against the
design, every record and the CRC, the design rules on every neighbour pair.  References: the OASIS
definitions written out here, KLayout's independent reading, and a brute-force count on the design's
own index map."""

import json
import shutil

import numpy as np
import pytest
from conftest import SMALL_TILED_RECIPE, leb128, run_main

from metadesign.design.recipe import load_design_recipe
from metadesign.execution import Execution
from metadesign.layouts import oasis as O
from metadesign.layouts import tiled
from metadesign.layouts.reader import verify_tiled
from metadesign.layouts.rules import DesignRules
from metadesign.layouts.stream import gdelta_decode, verify_stream
from metadesign.layouts.writer import layout_geometry, snap_widths


def test_gdeltas_decode_what_the_definition_encodes():
    """Form 1 in all eight directions, form 2 with either sign of dx and dy, runs of odd integers (the
    case the vectorised start-finding must get right), and bytes after the list that must not be read."""
    rng = np.random.default_rng(3)
    dirs = [(1, 0), (0, 1), (-1, 0), (0, -1), (1, 1), (-1, 1), (-1, -1), (1, -1)]
    raw, want = b"", []
    for _ in range(3000):
        if rng.random() < 0.5:
            d = int(rng.integers(8))
            m = int(rng.integers(1, 300))
            raw += leb128(m << 4 | d << 1)
            want.append((dirs[d][0] * m, dirs[d][1] * m))
        else:
            dx, dy = int(rng.integers(-5000, 5000)), int(rng.integers(-5000, 5000))
            raw += leb128(abs(dx) << 2 | (dx < 0) << 1 | 1) + leb128(abs(dy) << 1 | (dy < 0))
            want.append((dx, dy))
    buf = np.frombuffer(raw + b"\x81\x83\x85\x00" * 4, np.uint8)  # trailing odd integers: not g-deltas
    dx, dy, end = gdelta_decode(buf, np.flatnonzero(buf < 128), 0, len(want))
    np.testing.assert_array_equal(np.stack([dx, dy], 1), np.array(want))
    assert end == len(raw)
    # the writer's encoder, decoded again
    ex, ey = rng.integers(-40, 40, 500), rng.integers(-3, 4, 500)
    b = np.frombuffer(O.gdelta_grid(ex, ey), np.uint8)
    gx, gy, end = gdelta_decode(b, np.flatnonzero(b < 128), 0, 500)
    np.testing.assert_array_equal(gx, ex)
    np.testing.assert_array_equal(gy, ey)
    assert end == len(b)


@pytest.fixture(scope="module")
def small(tmp_path_factory, repo):
    tmp = tmp_path_factory.mktemp("stream")
    rec = tmp / "small.toml"
    rec.write_text(SMALL_TILED_RECIPE.format(lib=repo / "library" / "paper.npz"))
    recipe = load_design_recipe(rec)
    tiled.build_tiled(recipe, tmp / "good", tile=64)
    return tmp, recipe


def _altered(small, name, monkeypatch, change):
    """The small design written tiled with ``change(block, empty)`` applied to what the writer encodes,
    while design.npz keeps the design: a layout that differs from its design as ``change`` says."""
    tmp, recipe = small
    real = tiled.encode_stripe
    state = {"done": False}

    def encode(plan, blk, r0):
        if not state["done"] and r0 == 64:  # the second stripe: inside the circle
            blk = blk.copy()
            change(blk, plan.empty)
            state["done"] = True
        return real(plan, blk, r0)

    monkeypatch.setattr(tiled, "encode_stripe", encode)
    tiled.build_tiled(recipe, tmp / name, tile=64)
    monkeypatch.undo()
    assert state["done"]
    return tmp / name / "layout.oas", tmp / name / "design.npz"


def test_a_good_layout_passes_and_agrees_with_klayout(small):
    tmp, _ = small
    lay, des = tmp / "good" / "layout.oas", tmp / "good" / "design.npz"
    s = verify_stream(lay, des)
    assert s["exact"] and s["drc"]["passed"], s["problems"]
    assert s["signature"] == {"scheme": "crc32", "ok": True}
    two = verify_stream(lay, des, run=Execution(workers=2))  # stripes on two processes: the same report
    drop = ("seconds", "scan_seconds", "workers")
    assert {k: v for k, v in two.items() if k not in drop} == {k: v for k, v in s.items() if k not in drop}
    k = verify_tiled(lay, des, sample_tiles=4)
    assert k["exact"] and s["pillars"] == k["pillars_klayout"] == k["pillars_design"] == s["pillars_design"]
    with np.load(des) as z:
        im = z["index_map"]
    empty = json.loads(lay.with_suffix(".oas.json").read_text())["provenance"]["empty_index"]
    assert s["pillars"] == int(np.count_nonzero(im != empty)) > 10_000


def test_changed_pillars_are_caught_by_both_readers(small, monkeypatch):
    def drop(blk, empty):
        j, i = np.argwhere(blk != empty)[len(np.argwhere(blk != empty)) // 2]
        blk[j, i] = empty

    def move(blk, empty):
        full, free = np.argwhere(blk != empty), np.argwhere(blk == empty)
        (j, i), (q, p) = full[0], free[0]
        blk[q, p], blk[j, i] = blk[j, i], empty

    def swap_atom(blk, empty):  # another atom the design uses (its cell exists in the file)
        j, i = np.argwhere(blk != empty)[100]
        blk[j, i] = next(int(a) for a in np.unique(blk) if a not in (empty, blk[j, i]))

    for name, change, words in (("drop", drop, "per-atom pillar counts"), ("move", move, "cells differ"),
                                ("atom", swap_atom, "cells differ")):
        lay, des = _altered(small, name, monkeypatch, change)
        s = verify_stream(lay, des)
        assert not s["exact"] and s["signature"]["ok"], name  # a well-formed file: geometry, not the CRC
        assert any(words in p for p in s["problems"]), (name, s["problems"])
        assert s["mismatched_cells"] == (2 if name == "move" else 1) or name == "drop"
        k = verify_tiled(lay, des, sample_tiles=10**6)  # KLayout, every tile
        assert not k["exact"], name


def test_damaged_files_are_caught(small, tmp_path):
    tmp, _ = small
    lay, des = tmp / "good" / "layout.oas", tmp / "good" / "design.npz"
    data = bytearray(lay.read_bytes())
    flipped = tmp_path / "flipped.oas"
    data[len(data) // 3] ^= 0x10
    flipped.write_bytes(bytes(data))
    shutil.copy(lay.with_suffix(".oas.json"), tmp_path / "flipped.oas.json")
    s = verify_stream(flipped, des)
    assert not s["exact"] and (s["signature"]["ok"] is False or any("malformed" in p for p in s["problems"]))
    cut = tmp_path / "cut.oas"
    cut.write_bytes(lay.read_bytes()[:len(data) // 2])
    shutil.copy(lay.with_suffix(".oas.json"), tmp_path / "cut.oas.json")
    s = verify_stream(cut, des)
    assert not s["exact"] and any("truncated" in p or "no END" in p for p in s["problems"]), s["problems"]
    # a file of another tiling than the one it is streamed with: its own record says so
    s = verify_stream(lay, des, tile=128)
    assert not s["exact"]


def test_design_rules_count_every_violating_pair(small):
    """A stricter gap rule than the design meets: the violations counted while streaming equal a brute-force
    count over the design's index map (every horizontal and vertical neighbour pair)."""
    tmp, _ = small
    lay, des = tmp / "good" / "layout.oas", tmp / "good" / "design.npz"
    with np.load(des) as z:
        im, wx, wy = z["index_map"].astype(np.int64), z["atom_wx_m"], z["atom_wy_m"]
    empty = int(json.loads(lay.with_suffix(".oas.json").read_text())["provenance"]["empty_index"])
    ok = s0 = verify_stream(lay, des)
    gap = int(ok["drc"]["min_gap_nm"]) + 20
    s = verify_stream(lay, des, DesignRules(min_feature_nm=int(ok["drc"]["min_feature_nm"]) + 1, min_gap_nm=gap))
    assert not s["drc"]["passed"] and s["exact"]  # the geometry is as designed; the rule fails
    p_nm, _ = layout_geometry(im.shape[0], 0.7e-6)
    w = np.stack([snap_widths(wx, 1)[0], snap_widths(wy, 1)[0]], 1)
    filled = im != empty
    brute = 0
    for ax, k in ((1, 0), (0, 1)):
        a, b = (im[:, :-1], im[:, 1:]) if ax == 1 else (im[:-1, :], im[1:, :])
        m = (a != empty) & (b != empty)
        brute += int(np.count_nonzero(p_nm - (w[a[m], k] + w[b[m], k]) / 2 < gap))
    assert s["drc"]["space_violations"] == brute > 0
    assert s["drc"]["width_violations"] == int(np.count_nonzero(filled & (w[np.where(filled, im, 0), :].min(-1)
                                                                           < int(s0["drc"]["min_feature_nm"]) + 1)))


def test_the_verify_command_streams(small, capsys):
    tmp, _ = small
    lay = tmp / "good" / "layout.oas"
    rc, out, _ = run_main(["layout", "verify", str(lay), "--stream", "--json"], capsys)
    rep = json.loads(out)
    assert rc == 0 and rep["passed"] and rep["reader"] == "stream"
    rc, _, err = run_main(["layout", "verify", str(lay), "--stream", "--tile", "0"], capsys)
    assert rc == 2 and len(err) == 1 and "--tile" in err[0]


def test_one_entry_point_chooses_the_method_and_returns_one_report(small, monkeypatch, capsys):
    """``layouts.verify``: a tiled layout takes KLayout's sampled path while KLayout's read fits in memory,
    the stream when it would not (the 2.5 cm case: ~11 GB through KLayout), and an explicit method is
    run as asked; every method gives a VerifyReport, and the command prints which one ran and why."""
    from metadesign.layouts import VerifyOptions, VerifyReport, verify
    from metadesign.layouts import verification as V

    tmp, _ = small
    lay = tmp / "good" / "layout.oas"
    lines = []
    rep = verify(lay, run=Execution(log=lines.append))
    assert isinstance(rep, VerifyReport) and rep.method == "tiled" and rep.passed
    assert lines == [f"layout verify: tiled ({rep.reason})"] and "KLayout" in rep.reason
    assert rep.pillars == rep.pillars_design and 0 < rep.pillars_checked <= rep.pillars
    d = rep.to_dict()
    assert d["method"] == "tiled" and d["passed"] and d["sampled_tiles"] == rep.details["sampled_tiles"]
    # a machine on which KLayout's read of this file would not fit: every pillar streamed instead
    need = V.klayout_memory(lay)
    monkeypatch.setattr(V, "available_memory", lambda: int(need / V.MEMORY_FRACTION) - 1)
    rep = verify(lay)
    assert rep.method == "stream" and rep.passed and "more than" in rep.reason
    assert rep.pillars_checked == rep.pillars == rep.details["pillars"] == rep.pillars_design
    rc, out, err = run_main(["layout", "verify", str(lay)], capsys)
    assert rc == 0 and out.splitlines()[0].startswith("layout verify: stream (a tiled layout whose KLayout read")
    assert "PASS (streamed:" in out.splitlines()[1]
    rc, out, _ = run_main(["layout", "verify", str(lay), "--json"], capsys)
    assert rc == 0 and json.loads(out)["method"] == "stream"
    # asked for: run as asked, whatever the memory
    for method, options in (("tiled", VerifyOptions(sample_tiles=2)), ("readback", VerifyOptions())):
        rep = verify(lay, method=method, options=options)
        assert rep.method == method and rep.passed and rep.reason == "asked for", method
    assert rep.pillars_checked == rep.pillars == rep.pillars_design  # the read-back checks every pillar


def _run_verify(args, capsys):
    rc, out, err = run_main(["layout", "verify", *map(str, args)], capsys)
    assert not any("Traceback" in e for e in err), err
    return rc, out, err


def test_bad_paths_are_one_line_errors_before_the_work(small, tmp_path, capsys):
    tmp, _ = small
    good = tmp / "good"
    text = tmp_path / "notes.oas"
    text.write_text("not a layout at all\n")
    gds = tmp_path / "layout.gds"
    gds.write_bytes(b"\x00\x06\x00\x02\x02\x58" + bytes(100))  # a GDSII HEADER record
    shutil.copy(good / "layout.oas.json", tmp_path / "layout.gds.json")
    for args in ([good, "--stream"], [good, "--stream", "--tile", "64"], [good], [text, "--stream"], [text],
                 [gds, "--stream", "--design", good], [tmp_path / "missing.oas", "--stream"]):
        before = sorted(p.name for p in tmp_path.iterdir())
        rc, out, err = _run_verify(args, capsys)
        assert rc == 2 and len(err) == 1 and not out, (args, err, out)
        assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written
    assert "is a folder" in _run_verify([good, "--stream"], capsys)[2][0]
    assert "not an OASIS" in _run_verify([text, "--stream"], capsys)[2][0]
    assert "GDSII" in _run_verify([gds, "--stream", "--design", good], capsys)[2][0]


def test_a_damaged_file_never_passes_any_method(small, tmp_path, capsys):
    """Truncated, or one byte flipped (in the tiles, in the middle, in the top cell's records at the end):
    exit 1 (verification failed) or 2 (not a readable OASIS file), never 0, from every method."""
    tmp, _ = small
    lay, des = tmp / "good" / "layout.oas", tmp / "good" / "design.npz"
    data = lay.read_bytes()
    cases = {"cut-half": data[:len(data) // 2], "cut-end": data[:-10]}
    for at in (len(data) // 3, len(data) // 2, 2 * len(data) // 3, len(data) - 1000, len(data) - 300):
        b = bytearray(data)
        b[at] ^= 0x10
        cases[f"flip-{at}"] = bytes(b)
    for name, raw in cases.items():
        f = tmp_path / f"{name}.oas"
        f.write_bytes(raw)
        shutil.copy(lay.with_suffix(".oas.json"), tmp_path / f"{name}.oas.json")
        for extra in ([], ["--stream"], ["--all"], ["--sample-tiles", "3"]):
            rc, out, err = _run_verify([f, "--design", des, *extra], capsys)
            assert rc in (1, 2), (name, extra, rc, out)
            assert rc == 1 or len(err) == 1, (name, extra, err)
            if rc == 1:
                assert "FAIL" in out, (name, extra, out)

"""Centimetre apertures (#26): the streamed OASIS encoder against KLayout and gdstk, the streamed design
file against the whole-array one (same bytes), tiled layouts read back exactly, worker-count
independence, and the sampled verification catching a wrong tile."""

import json
import zipfile
import zlib

import gdstk
import numpy as np
import pytest
from conftest import SMALL_TILED_RECIPE, leb128, run_cli

from metadesign.design.recipe import load_design_recipe
from metadesign.design.store import load_design, run_design
from metadesign.execution import Execution
from metadesign.io import StreamedArray, iter_npz_rows, read_npz, write_npz
from metadesign.layouts import oasis as O
from metadesign.layouts import read_layout, read_layout_klayout, verify_against_design
from metadesign.layouts.reader import verify_tiled
from metadesign.layouts.tiled import build_tiled


def test_unsigned_integers_and_gdeltas_match_the_definition():
    rng = np.random.default_rng(0)
    v = np.concatenate([[0, 1, 127, 128, 16383, 16384, 2**35], rng.integers(0, 2**40, 500)])
    assert O.uints(v) == b"".join(leb128(int(x)) for x in v)
    dx, dy = rng.integers(-300, 300, 400), rng.integers(-3, 3, 400)
    dx[:50], dy[:50] = np.abs(dx[:50]) + 1, 0  # steps along +x: form 1
    ref = b""
    for a, b in zip(dx.tolist(), dy.tolist()):
        if b == 0 and a > 0:
            ref += leb128(a << 4)  # direction 0 (east), bit 0 = 0
        else:
            ref += leb128((abs(a) << 2) | ((a < 0) << 1) | 1) + leb128((abs(b) << 1) | (b < 0))
    assert O.gdelta_grid(dx, dy) == ref


def test_streamed_oasis_reads_back_in_klayout_and_gdstk(tmp_path):
    import klayout.db as kdb

    rng = np.random.default_rng(1)
    ix = rng.integers(-50, 50, 300)
    iy = rng.integers(-50, 50, 300)
    keep = np.unique(iy * 1000 + ix, return_index=True)[1]
    ix, iy = ix[np.sort(keep)], iy[np.sort(keep)]
    path = tmp_path / "t.oas"
    with open(path, "wb") as fh:
        w = O.OasisWriter(fh)
        a = w.cellname("A")
        w.cellname("TOP")
        w.cell("A")
        w.records(O.rectangle_record(1, 0, 201, 300, -101, -150))
        w.cell("TOP")
        w.raw(O.property_record(b"metadesign", b'{"k": 1}'))
        w.records(O.placement_record(a, int(ix[0]) * 700, int(iy[0]) * 700, ix, iy, 700)
                  + O.text_record(b"label", 11, 0, -5, -7))
        w.close()
    ok, _ = gdstk.oas_validate(str(path))
    assert ok is True  # the CRC32 of END matches
    data = path.read_bytes()
    assert data.startswith(O.MAGIC) and zlib.crc32(data[:-4]) == int.from_bytes(data[-4:], "little")
    ly = kdb.Layout(False)
    ly.read(str(path))
    top = ly.cell("TOP")
    assert top.property("metadesign") == '{"k": 1}'
    got = set()
    for inst in top.each_inst():
        for t in inst.cell_inst.each_trans():
            got.add((t.disp.x, t.disp.y))
    assert got == {(int(x) * 700, int(y) * 700) for x, y in zip(ix, iy)}
    box = next(ly.cell("A").shapes(ly.find_layer(1, 0)).each()).bbox()
    assert (box.left, box.bottom, box.width(), box.height()) == (-101, -150, 201, 300)
    lib = gdstk.read_oas(str(path), unit=1e-9)
    ref = [r for c in lib.cells if c.name == "TOP" for r in c.references][0]
    assert ref.repetition.size == len(ix)


def test_streamed_npz_has_the_bytes_of_the_whole_array(tmp_path):
    a = np.random.default_rng(2).integers(0, 250, (301, 77)).astype(np.uint8)
    write_npz(tmp_path / "a.npz", {"index_map": a, "meta": np.arange(3)})
    blocks = (a[i:i + 40] for i in range(0, 301, 40))
    write_npz(tmp_path / "b.npz", {"index_map": StreamedArray(a.shape, a.dtype, blocks), "meta": lambda: np.arange(3)})
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    back = np.concatenate([b for _, b in iter_npz_rows(tmp_path / "b.npz", "index_map", 64)])
    np.testing.assert_array_equal(back, a)
    with pytest.raises(ValueError):  # a stream shorter than its shape never becomes a file
        write_npz(tmp_path / "c.npz", {"x": StreamedArray((10, 3), np.uint8, [np.zeros((4, 3), np.uint8)])})
    assert not (tmp_path / "c.npz").exists()


@pytest.fixture(scope="module")
def tiled_case(tmp_path_factory, repo):
    tmp = tmp_path_factory.mktemp("tiled")
    rec = tmp / "small.toml"
    rec.write_text(SMALL_TILED_RECIPE.format(lib=repo / "library" / "paper.npz"))
    recipe = load_design_recipe(rec)
    d, _ = run_design(recipe, tmp / "whole")
    return tmp, recipe, d


@pytest.fixture(scope="module")
def tiled64(tiled_case):
    """The small design built tiled (64-cell tiles, hierarchy "tiles", in process) once, with its report."""
    tmp, recipe, _ = tiled_case
    return tmp / "t64", build_tiled(recipe, tmp / "t64", tile=64)


@pytest.mark.parametrize("hierarchy,workers", [("tiles", 1), ("flat", 2)])
def test_tiled_design_and_layout_equal_the_whole_array_path(tiled_case, tiled64, hierarchy, workers):
    tmp, recipe, d = tiled_case
    if (hierarchy, workers) == ("tiles", 1):
        out, rep = tiled64
    else:
        out = tmp / f"{hierarchy}-{workers}"
        rep = build_tiled(recipe, out, tile=64, hierarchy=hierarchy, run=Execution(workers=workers))
    tiled, whole = read_npz(out / "design.npz"), read_npz(tmp / "whole" / "design.npz")
    assert sorted(tiled) == sorted(whole)  # the same arrays (the index map deflated in pieces by the workers)
    for k in whole:
        np.testing.assert_array_equal(tiled[k], whole[k], err_msg=k)
    with zipfile.ZipFile(out / "design.npz") as zf:
        assert zf.testzip() is None  # every entry's CRC (the index map's combined from the pieces')
    assert rep["pillars"] == int(np.count_nonzero(d.index_map != d.empty)) == rep["metrics"]["n_cells_in_aperture"]
    n = d.spec.n_cells
    assert rep["tiles"] == (-(-n // 64)) ** 2
    for reader in (read_layout, read_layout_klayout):
        v = verify_against_design(reader(out / "layout.oas"), d)
        assert v["exact"], v["problems"]
    lib = gdstk.read_oas(str(out / "layout.oas"))
    assert [c.name for c in lib.top_level()] == ["METASURFACE"]


def test_tiled_bytes_do_not_depend_on_the_worker_count_or_the_scheduler(tiled_case, tiled64):
    from dask.distributed import LocalCluster

    tmp, recipe, _ = tiled_case
    ref = tiled64[0]  # the in-process build
    build_tiled(recipe, tmp / "w2", tile=64, run=Execution(workers=2))
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}) as cl:
        build_tiled(recipe, tmp / "dask", tile=64, run=Execution(scheduler=cl.scheduler_address))
    for w in ("w2", "dask"):
        for f in ("design.npz", "layout.oas", "metrics.json"):
            assert (ref / f).read_bytes() == (tmp / w / f).read_bytes(), (w, f)
    side = [json.loads((d / "layout.oas.json").read_text()) for d in (ref, tmp / "w2", tmp / "dask")]
    for s in side:
        s.pop("file"), s.pop("design")
    assert side[0] == side[1] == side[2]


def test_sampled_verification_passes_and_catches_a_changed_tile(tiled_case, tiled64):
    tmp, recipe, d = tiled_case
    out = tiled64[0]
    rep = verify_tiled(out / "layout.oas", out / "design.npz", sample_tiles=25, seed=3)
    assert rep["exact"] and rep["drc"]["passed"], rep["problems"]
    assert rep["pillars_klayout"] == rep["pillars_design"] and rep["sampled_fraction"] == pytest.approx(1.0)
    # a design whose one pillar differs: the count still agrees, the exact read-back does not
    im = d.index_map.copy()
    r, c = np.argwhere(im != d.empty)[len(im) // 2]
    im[r, c] = (im[r, c] + 1) % len(d.atoms)
    from metadesign.design.store import save_design

    save_design(tmp / "other", d.__class__(d.spec, d.atoms, im, d.offsets, d.metrics, d.meta, d.empty))
    bad = verify_tiled(out / "layout.oas", tmp / "other" / "design.npz", sample_tiles=25, seed=3)
    assert not bad["exact"] and bad["mismatched_cells"] == 1


def test_layout_tiled_cli(tiled_case, tmp_path):
    tmp, recipe, _ = tiled_case
    p = run_cli("layout", "tiled", recipe.source, "-o", tmp_path / "cli", "--tile", "64", "--json", "-j", "1")
    assert p.returncode == 0, p.stderr
    rep = json.loads(p.stdout)
    assert rep["tiles"] == 25 and (tmp_path / "cli" / "layout.oas").exists()
    p = run_cli("layout", "verify", tmp_path / "cli" / "layout.oas", "--json")
    assert p.returncode == 0, p.stderr
    v = json.loads(p.stdout)
    assert v["passed"] and len(v["sampled_tiles"]) == 8
    assert load_design(tmp_path / "cli").index_map.shape == (recipe.spec.n_cells,) * 2
    p = run_cli("layout", "tiled", recipe.source, "-o", tmp_path / "bad", "--tile", "40")
    assert p.returncode == 2 and "--tile" in p.stderr and not (tmp_path / "bad").exists()


def test_npz_rows_reads_any_row_window():
    from metadesign.io import NpzRows

    import tempfile
    from pathlib import Path

    a = np.arange(50 * 7, dtype=np.uint16).reshape(50, 7)
    with tempfile.TemporaryDirectory() as tmp:
        write_npz(Path(tmp) / "a.npz", {"x": a})
        r = NpzRows(Path(tmp) / "a.npz", "x")
        assert r.shape == (50, 7)
        for s in (slice(0, 10), slice(10, 13), slice(20, 50), slice(5, 6), slice(40, 99)):  # forward, back, past
            np.testing.assert_array_equal(r[s], a[s])
        r.close()


def test_tiled_device_pupil_equals_the_whole_layouts(tiled_case, tiled64):
    from metadesign.layouts import write_layout
    from metadesign.sensing.model import AsFabricated, IndexRows

    tmp, recipe, d = tiled_case
    write_layout(d, tmp / "whole" / "layout.oas")
    whole = AsFabricated.from_files(tmp / "whole" / "layout.oas")
    tiled = AsFabricated.from_files(tiled64[0] / "layout.oas")
    assert isinstance(tiled.layout.index_map, IndexRows)  # streamed, never loaded whole
    pa, pb = whole.pupil(0.05, 32), tiled.pupil(0.05, 32)
    np.testing.assert_array_equal(pa.G, pb.G)
    np.testing.assert_array_equal(whole.layout.index_map, tiled.layout.index_map[0:d.spec.n_cells])


def test_coarse_pupil_row_tiles_do_not_change_the_pupil(tiled_case, tiled64, monkeypatch):
    """The memory bound of a large aperture (one block row per tile) sums the same blocks."""
    import metadesign.sensing.forward as F
    from metadesign.sensing.model import AsFabricated

    fab = AsFabricated.from_files(tiled64[0] / "layout.oas")
    ref = fab.pupil(0.05, 32)
    block = fab.pupil_block(32)
    npad = -(-fab.n_cells // block) * block
    monkeypatch.setattr(F, "TILE_BYTES", block * npad * 16)  # one block row per tile
    tiles = []
    real = fab.layout.index_map.__class__.__getitem__
    monkeypatch.setattr(fab.layout.index_map.__class__, "__getitem__",
                        lambda self, k: tiles.append(k.stop - k.start) or real(self, k))
    one = fab.pupil(0.05, 32)
    assert max(tiles) <= block and len(tiles) > 16
    np.testing.assert_allclose(one.G, ref.G, rtol=0, atol=1e-6 * np.abs(ref.G).max())


def test_a_failed_tiled_build_leaves_the_previous_files_and_resumes(tiled_case, monkeypatch):
    import metadesign.layouts.tiled as T

    tmp, recipe, _ = tiled_case
    out = tmp / "fail"
    build_tiled(recipe, out, tile=64)
    before = {f: (out / f).read_bytes() for f in ("design.npz", "layout.oas", "layout.oas.json")}
    assert sorted(p.name for p in out.iterdir()) == ["design.npz", "layout.oas", "layout.oas.json", "metrics.json"]
    (out / "design.npz").unlink()  # a recipe change would rebuild: here the same recipe, interrupted
    real = T._stripe

    def dies_at_the_third_stripe(plan, r0):
        if r0 >= 128:
            raise RuntimeError("worker killed")
        return real(plan, r0)

    monkeypatch.setattr(T, "_stripe", dies_at_the_third_stripe)
    with pytest.raises(RuntimeError):
        build_tiled(recipe, out, tile=64)
    assert not (out / "design.npz").exists() and (out / "layout.oas").read_bytes() == before["layout.oas"]
    part = [p for p in out.iterdir() if p.name.startswith(".tiled-partial")]
    assert len(part) == 1 and len(list(part[0].glob("stripe-*.npz"))) == 2  # rows 0 and 64 were kept
    monkeypatch.setattr(T, "_stripe", real)
    rep = build_tiled(recipe, out, tile=64)
    assert rep["stripes_reused"] == 2
    assert {f: (out / f).read_bytes() for f in before} == before  # the same bytes as the uninterrupted run
    assert not any(p.name.startswith(".tiled-partial") for p in out.iterdir())


def test_pieces_deflated_apart_join_into_one_zip_entry(tmp_path):
    """Workers' pieces (sync-flushed raw deflate) concatenated, their CRCs combined: a zip that zipfile,
    numpy and Info-ZIP's reader (when installed) check and read, zip64 records included."""
    import shutil
    import subprocess

    from metadesign.deflate import DeflatedArray, crc32_combine, deflate_piece

    rng = np.random.default_rng(3)
    for _ in range(100):  # the combination against zlib on the concatenation
        a, b = rng.bytes(int(rng.integers(0, 5000))), rng.bytes(int(rng.integers(0, 5000)))
        assert crc32_combine(zlib.crc32(a), zlib.crc32(b), len(b)) == zlib.crc32(a + b)
    arr = np.repeat(rng.integers(0, 300, (97, 1)), 41, axis=1).astype(np.uint16)
    cuts = [0, 1, 30, 31, 64, 97]
    pieces = [deflate_piece(arr[a:b].tobytes(), lvl) for (a, b), lvl in zip(zip(cuts[:-1], cuts[1:]), (1, 6, 9, 1, 3))]
    path = tmp_path / "x.npz"
    write_npz(path, {"index_map": DeflatedArray(arr.shape, arr.dtype, iter(pieces)), "small": np.arange(7.0),
                     "meta": lambda: np.array("{}")})
    with zipfile.ZipFile(path) as zf:
        assert zf.testzip() is None
        assert [i.filename for i in zf.infolist()] == ["index_map.npy", "meta.npy", "small.npy"]
    got = read_npz(path)
    np.testing.assert_array_equal(got["index_map"], arr)
    np.testing.assert_array_equal(got["small"], np.arange(7.0))
    if shutil.which("unzip"):
        assert subprocess.run(["unzip", "-tq", str(path)], capture_output=True).returncode == 0
    short = [deflate_piece(arr[:50].tobytes(), 1)]  # fewer bytes than the shape: refused, nothing written
    with pytest.raises(ValueError, match="pieces hold"):
        write_npz(tmp_path / "y.npz", {"index_map": DeflatedArray(arr.shape, arr.dtype, iter(short))})
    assert not (tmp_path / "y.npz").exists()


def test_sigkill_while_assembling_resumes_to_the_same_bytes(tiled_case, tiled64, tmp_path):
    """SIGKILL in the second phase (every stripe kept, the design's pieces half concatenated): nothing of
    the interrupted files is left, the stripes are, and the rerun assembles the bytes of an uninterrupted
    build without computing a stripe again.  (The first phase's interruption: the test above.)"""
    import os
    import signal
    import subprocess
    import sys

    from conftest import REPO

    tmp, recipe, _ = tiled_case
    out = tmp_path / "killed"
    code = f"""
import os, signal
import metadesign.layouts.tiled as T
from metadesign.design.recipe import load_design_recipe
real = T.DeflatedArray
class Dying:  # the design's index map: SIGKILL after its second piece reached the file
    def __init__(self, shape, dtype, pieces):
        def gen():
            for k, p in enumerate(pieces):
                if k == 2:
                    os.kill(os.getpid(), signal.SIGKILL)
                yield p
        self.inner = real(shape, dtype, gen())
T.DeflatedArray = lambda shape, dtype, pieces: Dying(shape, dtype, pieces).inner
T.build_tiled(load_design_recipe(r"{recipe.source}"), __import__("pathlib").Path(r"{out}"), tile=64)
"""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True)
    assert p.returncode == -signal.SIGKILL, p.stderr.decode()[-2000:]
    assert not (out / "design.npz").exists() and not (out / "layout.oas").exists()
    part = [q for q in out.iterdir() if q.name.startswith(".tiled-partial")]
    n_stripes = -(-recipe.spec.n_cells // 64)
    assert len(part) == 1 and len(list(part[0].glob("stripe-*.npz"))) == n_stripes  # phase 1 complete
    rep = build_tiled(recipe, out, tile=64)
    assert rep["stripes_reused"] == n_stripes
    for f in ("design.npz", "layout.oas", "metrics.json"):
        assert (out / f).read_bytes() == (tiled64[0] / f).read_bytes(), f
    assert sorted(q.name for q in out.iterdir()) == ["design.npz", "layout.oas", "layout.oas.json", "metrics.json"]


def test_parallel_pupil_equals_the_serial_one(tiled_case, tiled64):
    """Block-row shares on two worker processes, each reading its own rows of the streamed design: the
    same pupil bit for bit (disjoint sums); with jitter it stays one stream in one process."""
    from metadesign.sensing.model import AsFabricated
    from metadesign.sensing.transmission import Perturbation

    fab = AsFabricated.from_files(tiled64[0] / "layout.oas")
    one, two = fab.pupil(0.05, 32), fab.pupil(0.05, 32, workers=2)
    np.testing.assert_array_equal(one.G, two.G)
    assert one.n_clamped == two.n_clamped
    pert = Perturbation.from_nm(3.0, jitter_nm=2.0, seed=5)
    np.testing.assert_array_equal(fab.pupil(0.05, 32, pert).G, fab.pupil(0.05, 32, pert, workers=2).G)


def test_sigkill_of_the_whole_job_in_the_stripe_phase_resumes_to_the_same_bytes(tiled_case, tiled64, tmp_path):
    """The CLI on 2 spawned workers, killed from outside (SIGKILL to its whole process group: the main
    process and both workers at once) once some stripes are kept and others are being computed: no file of
    the build is left, the kept stripes are; the rerun computes only the missing ones and writes the bytes of
    an uninterrupted build.  (Stripes are slowed by a ``sitecustomize`` in every process of the killed run,
    so that the kill lands inside the phase.)"""
    import os
    import signal
    import subprocess
    import sys
    import time

    from conftest import REPO

    tmp, recipe, _ = tiled_case
    out = tmp_path / "killed"
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(
        "import time\nimport metadesign.layouts.tiled as T\n_real = T._stripe\n"
        "def _slow(plan, r0):\n    time.sleep(0.5)\n    return _real(plan, r0)\nT._stripe = _slow\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(hook), str(REPO)]))
    cmd = [sys.executable, "-m", "metadesign", "layout", "tiled", str(recipe.source), "-o", str(out),
           "--tile", "64", "-j", "2"]
    p = subprocess.Popen(cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    n_stripes = -(-recipe.spec.n_cells // 64)
    t0, kept = time.time(), []
    while time.time() - t0 < 120 and p.poll() is None:
        kept = list(out.glob(".tiled-partial*/stripe-*.npz"))
        if len(kept) >= 2:
            break
        time.sleep(0.02)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait(timeout=60)
    assert p.returncode == -signal.SIGKILL, p.stderr.read().decode()[-2000:]
    assert 2 <= len(kept) < n_stripes
    assert not (out / "design.npz").exists() and not (out / "layout.oas").exists()
    kept = sorted(q.name for q in out.glob(".tiled-partial*/stripe-*.npz"))
    assert len(kept) < n_stripes
    r = subprocess.run(cmd + ["--json"], env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    import json

    assert json.loads(r.stdout)["stripes_reused"] == len(kept)
    for f in ("design.npz", "layout.oas", "metrics.json"):
        assert (out / f).read_bytes() == (tiled64[0] / f).read_bytes(), f
    assert sorted(q.name for q in out.iterdir()) == [".metadesign.json", "design.npz", "layout.oas", "layout.oas.json",
                                                     "metrics.json"]  # the product layer's record, no partial folder


def test_another_jobs_stripes_are_never_reused(tiled_case, tiled64, tmp_path):
    """A stripe that a worker of another (killed) job wrote late, under its own job's folder, is discarded
    with that folder, never taken for this job's; half-written stripe files of this job's are removed."""
    from metadesign.io import write_npz

    tmp, recipe, _ = tiled_case
    out = tmp_path / "other"
    out.mkdir()
    stale = out / ".tiled-partial-0123456789abcdef"
    stale.mkdir()
    write_npz(stale / "stripe-0000000.npz", {"design": np.zeros(3, np.uint8)})
    build_tiled(recipe, out, tile=64)
    for f in ("design.npz", "layout.oas", "metrics.json"):
        assert (out / f).read_bytes() == (tiled64[0] / f).read_bytes(), f
    assert not any(p.name.startswith(".tiled-partial") for p in out.iterdir())

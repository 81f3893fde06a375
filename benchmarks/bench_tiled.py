"""Centimetre apertures (issue #26): the tiled design + OASIS path against the whole-array one, on the
paper's 5 mm device, and (``--wide``) the 2.5 cm device of ``layouts/wide-25mm.toml``.

Each run is a fresh process (``metadesign design`` + ``layout write``, or ``layout tiled``); its peak
memory is the sum over its process tree (main + workers), sampled every 50 ms.  Printed: wall time,
peak memory, OASIS size, throughput (pillars per second per core, for the design kernel and the OASIS
encoder alone, one core), the tiled/whole ratio, the 5 mm -> 2.5 cm scaling, and projections for a
10 cm aperture (2e10 pillars) on one machine and on a 64-worker Dask cluster.

    python benchmarks/bench_tiled.py [--wide] [--json]
"""

from __future__ import annotations

import os

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_k] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
MD = [sys.executable, "-m", "metadesign"]


def run_tree(cmd: list[str]) -> tuple[float, float]:
    """(wall seconds, peak resident bytes summed over the process tree) of ``cmd``."""
    import psutil

    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=REPO)
    proc = psutil.Process(p.pid)
    peak = 0
    while p.poll() is None:
        try:
            rss = proc.memory_info().rss + sum(c.memory_info().rss for c in proc.children(recursive=True))
            peak = max(peak, rss)
        except psutil.Error:
            pass
        time.sleep(0.05)
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr.read().decode()[-2000:]}")
    return time.perf_counter() - t0, peak


def kernels(recipe_path: Path, rows: int = 512) -> dict:
    """One core: the discretizer kernel and the OASIS encoder on ``rows`` rows of the device."""
    import numpy as np

    from metadesign.design.build import DesignStream, map_rows
    from metadesign.design.recipe import load_design_recipe
    from metadesign.design.store import select_recipe_atoms
    from metadesign.layouts.tiled import TiledPlan, encode_stripe
    from metadesign.layouts.writer import layout_geometry
    from metadesign.library.store import load_library

    rec = load_design_recipe(recipe_path)
    lib = load_library(rec.library_path)
    atoms = select_recipe_atoms(rec, lib)
    st = DesignStream(rec.spec, atoms, rec.metric, rec.optimise_offsets, rec.tile_rows)
    n = rec.spec.n_cells
    p_nm, x0 = layout_geometry(n, rec.spec.period)
    plan = TiledPlan(rec.spec, atoms, rec.metric, st.offsets, np.dtype(st.dtype).str, st.empty, rec.tile_rows,
                     rows, p_nm, x0, "tiles", 1)
    r0 = (n // 2 // rows) * rows
    plan.mapper()  # the look-up table is built once per worker, not per stripe
    from metadesign import jit

    def run():
        t = time.perf_counter()
        maps = [map_rows(rec.spec, atoms, plan.mapper(), st.offsets, st.dtype, st.empty, s, s + 256)
                for s in range(r0, r0 + rows, 256)]
        t_design = time.perf_counter() - t
        blk = np.concatenate([m[0] for m in maps])
        t = time.perf_counter()
        b = encode_stripe(plan, blk, r0)
        return blk, [m[1] for m in maps], b, t_design, time.perf_counter() - t

    compiled = jit.enabled()
    if compiled:
        small = map_rows(rec.spec, atoms, plan.mapper(), st.offsets, st.dtype, st.empty, r0, r0 + 2)[0]
        encode_stripe(plan, small, r0)  # compiled (or loaded from numba's cache) before the clock starts
    old = os.environ.get("METADESIGN_JIT")
    os.environ["METADESIGN_JIT"] = "0"  # the numpy twins, measured in the same run
    try:
        blk0, st0, b0, t_design0, t_layout0 = run()
    finally:
        if old is None:
            del os.environ["METADESIGN_JIT"]
        else:
            os.environ["METADESIGN_JIT"] = old
    blk, sums, b, t_design, t_layout = run()
    same = (np.array_equal(blk, blk0) and b == b0 and all(
        all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(p, q)) for p, q in zip(sums, st0)))
    cells = blk.size
    from metadesign.deflate import DeflatedArray, deflate_piece
    from metadesign.io import write_npz
    from metadesign.layouts.tiled import DESIGN_DEFLATE_LEVEL

    levels = {}
    for lvl in sorted({1, 6, DESIGN_DEFLATE_LEVEL}):  # the worker's piece of the design file, size vs time
        t = time.perf_counter()
        piece = deflate_piece(blk.tobytes(), lvl)
        levels[lvl] = {"seconds_per_pillar": (time.perf_counter() - t) / cells,
                       "ratio": len(piece.data) / piece.size}
        if lvl == DESIGN_DEFLATE_LEVEL:
            ours = piece
    reps = max(1, int(2e8 // max(1, len(ours.data))))  # the assembler: pieces concatenated, CRCs combined
    with tempfile.TemporaryDirectory(dir=REPO) as tmp:
        t = time.perf_counter()
        write_npz(Path(tmp) / "a.npz", {"index_map": DeflatedArray((reps * blk.shape[0], blk.shape[1]), blk.dtype,
                                                                   (ours for _ in range(reps)))})
        t_asm = time.perf_counter() - t
    return {"compiled": compiled, "same_as_numpy": same,
            "numpy": {"design_pillars_per_s_core": cells / t_design0, "oasis_pillars_per_s_core": cells / t_layout0},
            "design_pillars_per_s_core": cells / t_design, "oasis_pillars_per_s_core": cells / t_layout,
            "oasis_bytes_per_pillar": len(b) / cells, "deflate_levels": levels,
            "deflate_pillars_per_s_core": 1 / levels[DESIGN_DEFLATE_LEVEL]["seconds_per_pillar"],
            "design_deflate_level": DESIGN_DEFLATE_LEVEL,
            "writer_seconds_per_pillar": t_asm / (reps * cells)}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--wide", action="store_true", help="also the 2.5 cm device (about 5 min, 2 GB)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    rep: dict = {"workers": a.workers}
    paper = REPO / "layouts" / "paper-5mm.toml"
    with tempfile.TemporaryDirectory(dir=REPO) as tmp:
        tmp = Path(tmp)
        t_d, m_d = run_tree([*MD, "design", "build", str(paper), "-o", str(tmp / "whole")])
        t_l, m_l = run_tree([*MD, "layout", "write", str(tmp / "whole"), "-o", str(tmp / "whole" / "layout")])
        rep["paper_whole"] = {"seconds": t_d + t_l, "design_seconds": t_d, "layout_seconds": t_l,
                              "peak_bytes": max(m_d, m_l), "oasis_bytes": (tmp / "whole" / "layout.oas").stat().st_size}
        for w in (1, a.workers):
            t, m = run_tree([*MD, "layout", "tiled", str(paper), "-o", str(tmp / f"tiled{w}"), "-j", str(w)])
            rep[f"paper_tiled_{w}"] = {"seconds": t, "peak_bytes": m,
                                       "oasis_bytes": (tmp / f"tiled{w}" / "layout.oas").stat().st_size}
        import numpy as np

        from metadesign.io import read_npz

        whole, tiled = read_npz(tmp / "whole" / "design.npz"), read_npz(tmp / "tiled1" / "design.npz")
        rep["paper_design_same_arrays"] = sorted(whole) == sorted(tiled) and all(
            np.array_equal(whole[k], tiled[k]) for k in whole)
        rep["paper_design_same_bytes_1_and_2_workers"] = (tmp / "tiled1" / "design.npz").read_bytes() == \
            (tmp / f"tiled{a.workers}" / "design.npz").read_bytes()
        lay5 = str(tmp / "tiled1" / "layout.oas")
        for w in sorted({1, a.workers}):  # the streaming verifier (#35): every pillar, bounded memory
            t, m = run_tree([*MD, "layout", "verify", lay5, "--stream", "-j", str(w)])
            rep[f"paper_verify_stream_{w}"] = {"seconds": t, "peak_bytes": m}
        t, m = run_tree([*MD, "layout", "verify", lay5])  # KLayout: count of every pillar, 8 sampled tiles
        rep["paper_verify_klayout"] = {"seconds": t, "peak_bytes": m}
        if a.wide:
            wide = REPO / "layouts" / "wide-25mm.toml"
            t, m = run_tree([*MD, "layout", "tiled", str(wide), "-o", str(tmp / "wide"), "-j", str(a.workers)])
            rep["wide_tiled"] = {"seconds": t, "peak_bytes": m,
                                 "oasis_bytes": (tmp / "wide" / "layout.oas").stat().st_size,
                                 "pillars": json.loads((tmp / "wide" / "layout.oas.json").read_text())["pillars"]}
            t, m = run_tree([*MD, "layout", "verify", str(tmp / "wide" / "layout.oas"), "--stream", "-j",
                             str(a.workers)])
            rep["wide_verify_stream"] = {"seconds": t, "peak_bytes": m}
    rep["kernels_paper"] = kernels(paper)
    n5 = 7142 ** 2
    w5 = rep[f"paper_tiled_{a.workers}"]
    rep["tiled_over_whole_1_worker"] = rep["paper_tiled_1"]["seconds"] / rep["paper_whole"]["seconds"]
    rep["tiled_over_whole_workers"] = w5["seconds"] / rep["paper_whole"]["seconds"]
    rate5 = n5 / w5["seconds"]
    rep["paper_pillars_per_s"] = rate5
    if a.wide:
        wt = rep["wide_tiled"]
        rep["wide_pillars_per_s"] = wt["pillars"] / wt["seconds"]
        rep["scaling_wide_over_paper_rate"] = rep["wide_pillars_per_s"] / rate5
        rate, bpp = rep["wide_pillars_per_s"], wt["oasis_bytes"] / wt["pillars"]
    else:
        rate, bpp = rate5, w5["oasis_bytes"] / n5
    k = rep["kernels_paper"]
    per_core = 1 / (1 / k["design_pillars_per_s_core"] + 1 / k["oasis_pillars_per_s_core"]
                    + 1 / k["deflate_pillars_per_s_core"])
    n10 = 142857 ** 2
    rep["projection_10cm"] = {
        "pillars": n10, "oasis_bytes": n10 * bpp, "one_machine_minutes": n10 / rate / 60}
    # 64 workers make stripes (mapped, encoded, deflated) at 64x the per-core rate; the one assembler only
    # concatenates their bytes
    serial = k["writer_seconds_per_pillar"]
    rep["projection_10cm"]["dask_64_minutes"] = n10 * max(1 / (64 * per_core), serial) / 60
    rep["projection_10cm"]["writer_seconds_per_pillar"] = serial
    if a.json:
        print(json.dumps(rep, indent=1))
        return 0
    G = 1e9
    pw = rep["paper_whole"]
    print("tiled design + OASIS (issue #26); peak memory = the whole process tree")
    print(f"  paper 5 mm, whole array (design + layout write): {pw['seconds']:.1f} s "
          f"({pw['design_seconds']:.1f} + {pw['layout_seconds']:.1f}), peak {pw['peak_bytes'] / G:.2f} GB, "
          f"OASIS {pw['oasis_bytes'] / 1e6:.1f} MB")
    for w in sorted({1, a.workers}):
        r = rep[f"paper_tiled_{w}"]
        print(f"  paper 5 mm, tiled, {w} worker(s): {r['seconds']:.1f} s "
              f"({r['seconds'] / pw['seconds']:.2f}x the whole path), peak {r['peak_bytes'] / G:.2f} GB, "
              f"OASIS {r['oasis_bytes'] / 1e6:.1f} MB")
    print(f"  design file: the same arrays on both paths: {rep['paper_design_same_arrays']}; the same bytes on 1 "
          f"and {a.workers} workers: {rep['paper_design_same_bytes_1_and_2_workers']}")
    kv = rep["paper_verify_klayout"]
    for w in sorted({1, a.workers}):
        r = rep[f"paper_verify_stream_{w}"]
        print(f"  paper 5 mm, layout verify --stream -j {w} (every pillar, every record, CRC, DRC on every pair): "
              f"{r['seconds']:.1f} s ({n5 / r['seconds'] / 1e6:.1f} M pillars/s), peak {r['peak_bytes'] / G:.2f} GB; "
              f"KLayout count + 8 sampled tiles: {kv['seconds']:.1f} s, {kv['peak_bytes'] / G:.2f} GB "
              f"({r['seconds'] / kv['seconds']:.2f}x its time)")
    print(f"  one core: design kernel {k['design_pillars_per_s_core'] / 1e6:.2f} M pillars/s, OASIS encoder "
          f"{k['oasis_pillars_per_s_core'] / 1e6:.2f} M pillars/s ({k['oasis_bytes_per_pillar']:.2f} B/pillar)"
          f" = {1e9 / k['design_pillars_per_s_core']:.0f} + {1e9 / k['oasis_pillars_per_s_core']:.0f} ns per pillar "
          f"({'compiled' if k['compiled'] else 'numpy: numba absent or METADESIGN_JIT=0'}); the numpy twins "
          f"{1e9 / k['numpy']['design_pillars_per_s_core']:.0f} + {1e9 / k['numpy']['oasis_pillars_per_s_core']:.0f} ns "
          f"({k['design_pillars_per_s_core'] / k['numpy']['design_pillars_per_s_core']:.1f}x"
          f" and {k['oasis_pillars_per_s_core'] / k['numpy']['oasis_pillars_per_s_core']:.1f}x), the same map, sums "
          f"and bytes: {k['same_as_numpy']}")
    print("  the design file's piece on the worker (deflate): " + ", ".join(
        f"level {lv}: {v['seconds_per_pillar'] * 1e9:.1f} ns/pillar, {v['ratio']:.2f} of the raw bytes"
        for lv, v in k["deflate_levels"].items()) + f" (used: level {k['design_deflate_level']}); the assembler "
        f"(concatenation + CRC combination): {k['writer_seconds_per_pillar'] * 1e9:.2f} ns/pillar")
    if a.wide:
        wt = rep["wide_tiled"]
        print(f"  2.5 cm, tiled, {a.workers} workers: {wt['pillars']:,} pillars in {wt['seconds'] / 60:.1f} min, "
              f"peak {wt['peak_bytes'] / G:.2f} GB, OASIS {wt['oasis_bytes'] / 1e6:.0f} MB; "
              f"{rep['wide_pillars_per_s'] / 1e6:.2f} M pillars/s = {rep['scaling_wide_over_paper_rate']:.2f}x "
              "the 5 mm rate (1.00 = linear)")
        wv = rep["wide_verify_stream"]
        print(f"  2.5 cm, layout verify --stream -j {a.workers}: {wv['seconds'] / 60:.1f} min, peak "
              f"{wv['peak_bytes'] / G:.2f} GB ({wt['pillars'] / wv['seconds'] / 1e6:.1f} M pillars/s)")
    p = rep["projection_10cm"]
    print(f"  10 cm (2.0e10 pillars): OASIS ~{p['oasis_bytes'] / G:.1f} GB; {p['one_machine_minutes']:.0f} min on "
          f"this machine; ~{p['dask_64_minutes']:.1f} min on 64 Dask workers (the assembler's "
          f"{p['writer_seconds_per_pillar'] * 1e9:.2f} ns/pillar does not bound it)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

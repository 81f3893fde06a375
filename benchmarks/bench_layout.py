"""Layout benchmark on the full paper design (51 M pillars).

Prints OASIS write time / peak RSS / size, verify time / peak RSS, the GDS
time and size (with --gds: full scale, several GB; otherwise measured on a
2048 x 2048 crop and extrapolated), and the ratio against a naive
one-polygon-per-pillar writer measured on a 1024 x 1024 crop and
extrapolated.  Goals: OASIS write <= 10 s and <= 2 GB; verify <= 60 s.

    python benchmarks/bench_layout.py [--gds] [--json]
"""

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
ENV = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(REPO))


def timed(args):
    """Run the CLI under /usr/bin/time-like accounting: (seconds, peak RSS GB, stdout)."""
    code = ("import resource, sys, time\nfrom metadesign.cli import main\nt = time.perf_counter()\n"
            "rc = main(sys.argv[1:])\n"
            "print('@@', time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n"
            "sys.exit(rc)")
    p = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, env=ENV)
    if p.returncode:
        raise SystemExit(f"metadesign {' '.join(map(str, args))} failed:\n{p.stderr}")
    line = [ln for ln in p.stderr.splitlines() if ln.startswith("@@")][-1].split()
    return float(line[1]), float(line[2]) / 1024**2, p.stdout, p.stderr


def naive_oas(design, crop, path):
    import gdstk

    lib = gdstk.Library(unit=1e-9, precision=1e-9)
    top = lib.new_cell("TOP")
    wx = np.round(design.atoms.wx * 1e9)
    wy = np.round(design.atoms.wy * 1e9)
    im = design.index_map[:crop, :crop]
    for iy in range(crop):
        for ix in range(crop):
            a = im[iy, ix]
            x, y = ix * 700, iy * 700
            top.add(gdstk.rectangle((x - wx[a] // 2, y - wy[a] // 2), (x - wx[a] // 2 + wx[a], y - wy[a] // 2 + wy[a])))
    lib.write_oas(str(path), compression_level=1)


def main() -> int:
    from metadesign.design.store import Design, load_design
    from metadesign.layouts import write_layout

    design_dir = REPO / "layouts" / "paper-5mm"
    if not (design_dir / "design.npz").exists():
        subprocess.run([sys.executable, "-m", "metadesign", "design", str(REPO / "layouts" / "paper-5mm.toml")],
                       env=ENV, check=True, capture_output=True)
    res = {}
    with tempfile.TemporaryDirectory(dir=REPO) as tmp:
        tmp = Path(tmp)
        out = tmp / "paper"
        t, rss, so, se = timed(["layout", design_dir, "-o", out, "--json"])
        rep = json.loads(so)["layouts"][0]
        res.update(oas_write_s=t, oas_write_rss_gb=rss, oas_mb=rep["bytes"] / 1e6, pillars=rep["pillars"])
        t, rss, so, se = timed(["layout", "verify", out.with_suffix(".oas"), "--design", design_dir, "--json"])
        v = json.loads(so)
        res.update(verify_s=t, verify_rss_gb=rss, verify_exact=v["gdstk"]["exact"], drc_passed=v["drc"]["passed"])
        d = load_design(design_dir)
        n = d.spec.n_cells
        if "--gds" in sys.argv:
            t, rss, so, se = timed(["layout", design_dir, "-o", tmp / "paper_gds", "--format", "gds", "--json"])
            res.update(gds_write_s=t, gds_write_rss_gb=rss,
                       gds_mb=json.loads(so)["layouts"][0]["bytes"] / 1e6, gds_extrapolated=False)
        else:
            from metadesign.design import SupercellSpec
            c = 2048
            spec = SupercellSpec(d.spec.wavelength, d.spec.period, c, d.spec.supercell, d.spec.channels_x,
                                 d.spec.channels_y)
            sub = Design(spec, d.atoms, np.ascontiguousarray(d.index_map[:c, :c]), d.offsets, d.metrics, d.meta, None)
            t0 = time.perf_counter()
            r = write_layout(sub, tmp / "crop.gds", "gds")
            f = n * n / (c * c)
            res.update(gds_write_s=(time.perf_counter() - t0) * f, gds_mb=r["bytes"] / 1e6 * f, gds_extrapolated=True)
        crop = 1024
        t0 = time.perf_counter()
        naive_oas(d, crop, tmp / "naive.oas")
        t_naive = (time.perf_counter() - t0) * n * n / crop**2
        res.update(naive_extrapolated_s=t_naive, ratio_naive_over_ours=t_naive / res["oas_write_s"])
    if "--json" in sys.argv:
        print(json.dumps(res, indent=2))
    else:
        print(f"paper layout: {res['pillars']:,} pillars")
        print(f"  OASIS write   {res['oas_write_s']:.1f} s (goal 10 s), peak RSS {res['oas_write_rss_gb']:.2f} GB "
              f"(goal 2 GB), {res['oas_mb']:.1f} MB")
        print(f"  verify        {res['verify_s']:.1f} s (goal 60 s), peak RSS {res['verify_rss_gb']:.2f} GB, "
              f"exact {res['verify_exact']}, DRC {res['drc_passed']}")
        ex = " (extrapolated from a 2048^2 crop)" if res["gds_extrapolated"] else ""
        print(f"  GDS write     {res['gds_write_s']:.1f} s, {res['gds_mb']:.0f} MB{ex}")
        print(f"  naive one-polygon-per-pillar OASIS writer: {res['naive_extrapolated_s']:.0f} s extrapolated from "
              f"1024^2 -> ours is {res['ratio_naive_over_ours']:.1f}x faster")
    return 0


if __name__ == "__main__":
    sys.exit(main())

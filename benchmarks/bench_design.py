"""Design + discretizer benchmark: the full 51 M-cell paper design.

Runs `metadesign design layouts/paper-5mm.toml` in a child process and prints
its wall time and peak RSS (goal: <= 30 s and <= 3 GB on 2 cores), plus the
exact-lookup statistics.

    python benchmarks/bench_design.py [--json]

It then repeats the design with a polygon clear aperture (an irregular octagon: cells selected with
shapely's vectorised predicate) and reports its time and memory against the same goals.
"""

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(REPO))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "metadesign", "design", str(REPO / "layouts" / "paper-5mm.toml"),
                            "-o", tmp, "--json"], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        if p.returncode:
            print(p.stderr, file=sys.stderr)
            return p.returncode
        m = json.loads(p.stdout)
        size = (Path(tmp) / "design.npz").stat().st_size
    rss_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2
    # the same design with a polygon clear aperture (child process of its own for its peak RSS)
    octagon = [[-2500, -1000], [-1000, -2500], [1200, -2500], [2500, -800], [2500, 1000], [900, 2500],
               [-1100, 2400], [-2500, 1100]]
    text = (REPO / "layouts" / "paper-5mm.toml").read_text().replace(
        'clear_aperture = "square"', f'clear_aperture = "polygon"\naperture_polygon_um = {octagon}')
    text = text.replace('"../library/paper.npz"', f'"{REPO / "library" / "paper.npz"}"')
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "poly.toml").write_text(text)
        code = ("import resource, sys, time, json\nfrom metadesign.cli import main\nt = time.perf_counter()\n"
                f"rc = main(['design', '{tmp}/poly.toml', '-o', '{tmp}/out', '--json'])\n"
                "print(json.dumps({'wall': time.perf_counter() - t, 'rss': "
                "resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2}), file=sys.stderr)\n")
        q = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
        poly = json.loads(q.stderr.strip().splitlines()[-1])
        poly["cells_in_aperture"] = json.loads(q.stdout)["n_cells_in_aperture"]
    res = {"cells": m["n_cells"], "wall_s": wall, "peak_rss_gb": rss_gb, "design_file_mb": size / 1e6,
           "discretize_s": m["seconds"]["total"], "lut_unsafe_fraction": m["lut_unsafe_fraction"],
           "rmse_rad": m["rmse_rad"], "goal_wall_s": 30, "goal_rss_gb": 3,
           "polygon": {"wall_s": poly["wall"], "peak_rss_gb": poly["rss"], "cells_in_aperture": poly["cells_in_aperture"]}}
    if "--json" in sys.argv:
        print(json.dumps(res, indent=2))
    else:
        print(f"paper design ({m['n_cells'] / 1e6:.1f} M cells): {wall:.1f} s wall (goal 30 s, ratio "
              f"{wall / 30:.2f}), peak RSS {rss_gb:.2f} GB (goal 3 GB, ratio {rss_gb / 3:.2f})")
        print(f"  discretize {m['seconds']['total']:.1f} s, design file {size / 1e6:.1f} MB, "
              f"exact-LUT cells resolved by fallback {100 * m['lut_unsafe_fraction']:.1f} %")
        print(f"  RMSE x {m['rmse_rad'][0]:.4f} y {m['rmse_rad'][1]:.4f} rad (paper: 0.7 rad)")
        print(f"polygon clear aperture (octagon, {poly['cells_in_aperture'] / 1e6:.1f} M cells inside): "
              f"{poly['wall']:.1f} s wall (goal 30 s, ratio {poly['wall'] / 30:.2f}), peak RSS {poly['rss']:.2f} GB "
              f"(ratio {poly['rss'] / 3:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""As-fabricated fidelity benchmark (issue #15), on one core per process:

* a 2 x 2 supercell solve at the library's resolution (nG ~800 at period 2p: the LPA check's unit of work),
  in the two mirror sectors and as the full coupled problem (the ratio is the sector solve's gain);
* a vertical unit cell and a tapered one (8 and 24 slices) at nG 200;
* the 4-D library build, measured on a small sweep on 2 local workers and on a Dask LocalCluster of 2
  single-threaded workers, and projected to the paper grid (81 widths, 3 heights x 3 angles).

    python benchmarks/bench_fidelity.py [--json]
"""

from __future__ import annotations

import os

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_k] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _t(fn, n=1):
    from metadesign.timing import repeat_seconds

    return repeat_seconds(fn, n)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    from metadesign.library.build import build_library
    from metadesign.library.rcwa import SolverSettings, Stack, solve_cell
    from metadesign.library.recipe import recipe_from_dict
    from metadesign.library.supercell import solve_supercell, solve_tapered

    st = Stack()
    W = [[(205e-9, 285e-9), (320e-9, 305e-9)], [(320e-9, 200e-9), (345e-9, 270e-9)]]
    out = {}
    out["supercell_sector_s"] = _t(lambda: solve_supercell(W, st, 800))
    out["supercell_full_s"] = _t(lambda: solve_supercell(W, st, 800, symmetric=False))
    s200 = SolverSettings(200)
    out["cell_vertical_s"] = _t(lambda: solve_cell(0.3e-6, 0.2e-6, st, s200), 3)
    out["cell_tapered8_s"] = _t(lambda: solve_tapered(0.3e-6, 0.2e-6, 88.0, 8, st, s200), 3)
    out["cell_tapered24_s"] = _t(lambda: solve_tapered(0.3e-6, 0.2e-6, 88.0, 24, st, s200))
    # a small 4-D build: 3 widths (6 unique pairs) x 2 heights x 2 angles = 24 cells
    d = tomllib.loads((REPO / "library" / "paper.toml").read_text())
    d["sweep"] = {"w_min_um": 0.30, "w_max_um": 0.32, "step_nm": 10.0}
    d["convergence"]["check_cells_um"] = [[0.30, 0.31]]
    d["fab_axes"] = {"heights_um": [1.17, 1.2], "sidewall_deg": [88.0, 90.0], "slices": 8, "reference_slices": 16}
    rec = recipe_from_dict(d, "bench")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        _, rep = build_library(rec, Path(tmp) / "a.npz", workers=2, chunk_size=2)
        out["build_24_cells_local2_s"] = rep["sweep_seconds"]
        out["build_24_cells_local2_total_s"] = time.perf_counter() - t0
        from dask.distributed import LocalCluster

        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cl:
            _, rep = build_library(rec, Path(tmp) / "b.npz", workers=1, chunk_size=2, scheduler=cl.scheduler_address)
            out["build_24_cells_dask2_s"] = rep["sweep_seconds"]
    # projection to the paper grid: 81 widths -> 3321 unique pairs, x 3 heights x 3 angles (90 and two tapers)
    pairs = 81 * 82 // 2
    vertical, tapered = pairs * 3, pairs * 3 * 2
    core_s = vertical * out["cell_vertical_s"] + tapered * out["cell_tapered8_s"]
    out["paper_4d_cells"] = vertical + tapered
    out["paper_4d_core_hours"] = core_s / 3600
    eff_local = (12 * out["cell_vertical_s"] + 12 * out["cell_tapered8_s"]) / out["build_24_cells_local2_s"] / 2
    eff_dask = (12 * out["cell_vertical_s"] + 12 * out["cell_tapered8_s"]) / out["build_24_cells_dask2_s"] / 2
    out["parallel_efficiency_local2"] = eff_local
    out["parallel_efficiency_dask2"] = eff_dask
    out["paper_4d_hours_local2"] = core_s / 3600 / 2 / eff_local
    out["paper_4d_hours_dask_64_workers"] = core_s / 3600 / 64 / eff_dask
    out["lpa_check_32_supercells_min_1core"] = 32 * out["supercell_sector_s"] / 60
    if a.json:
        print(json.dumps(out, indent=1))
    else:
        print(f"supercell (nG ~800, period 2p): {out['supercell_sector_s']:.2f} s in mirror sectors, "
              f"{out['supercell_full_s']:.2f} s full ({out['supercell_full_s'] / out['supercell_sector_s']:.1f}x)")
        print(f"unit cell nG 200: vertical {out['cell_vertical_s']:.3f} s, tapered 8 slices "
              f"{out['cell_tapered8_s']:.3f} s ({out['cell_tapered8_s'] / out['cell_vertical_s']:.1f}x), "
              f"24 slices {out['cell_tapered24_s']:.3f} s")
        print(f"4-D build, 24 cells: 2 local workers {out['build_24_cells_local2_s']:.1f} s (efficiency "
              f"{eff_local:.2f}), Dask LocalCluster 2 workers {out['build_24_cells_dask2_s']:.1f} s ({eff_dask:.2f})")
        print(f"paper 4-D library (81 widths x 3 heights x 3 angles, {out['paper_4d_cells']} cells): "
              f"{out['paper_4d_core_hours']:.1f} core-hours -> {out['paper_4d_hours_local2']:.1f} h on 2 local "
              f"workers, {out['paper_4d_hours_dask_64_workers'] * 60:.0f} min on 64 Dask workers")
        print(f"lpa-check, 32 supercells: {out['lpa_check_32_supercells_min_1core']:.1f} min on one core")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

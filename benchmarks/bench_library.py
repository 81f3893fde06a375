"""Unit-cell library benchmark.

Prints: seconds per cell (both polarisations) at the certified setting on one
core; the ratio against the naive path (grcwa's public API: one S-matrix per
RT_Solve/GetAmplitudes call, full coupled eigenproblem); the parallel speedup
on 2 processes; and the time of a 41 x 41 library build on 2 workers.

    python benchmarks/bench_library.py [--quick] [--json]
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
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from metadesign.library.build import build_library, solve_cells  # noqa: E402
from metadesign.library.rcwa import SolverSettings, Stack, permittivity_matrices, solve_cell  # noqa: E402
from metadesign.library.recipe import load_recipe, recipe_from_dict  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def naive_cell(wx, wy, stack: Stack, settings: SolverSettings):
    """Public grcwa API, same Li permittivity: RT_Solve and GetAmplitudes per polarisation."""
    import grcwa
    from grcwa import rcwa as g

    p = stack.period
    out = []
    for pol in ("x", "y"):
        obj = grcwa.obj(settings.n_harmonics, [1.0, 0.0], [0.0, 1.0], p / stack.wavelength, 0.0, 0.0, verbose=0)
        obj.Add_LayerUniform(0.0, stack.n_substrate**2)
        obj.Add_LayerGrid(stack.height / p, 1, 1)
        obj.Add_LayerUniform(0.0, stack.n_superstrate**2)
        obj.Init_Setup(Gmethod=0)
        exx, eyy, ezz = permittivity_matrices(obj.G, wx / p, wy / p, stack.n_pillar**2, 1.0, settings.factorization)
        epinv = np.linalg.inv(ezz)
        z = np.zeros_like(exx)
        ep2 = np.block([[eyy, z], [z, exx]])
        kp = g.MakeKPMatrix(obj.omega, 1, epinv, obj.kx, obj.ky)
        q, phi = g.SolveLayerEigensystem(obj.omega, obj.kx, obj.ky, kp, ep2)
        obj.kp_list[1], obj.q_list[1], obj.phi_list[1] = kp, q, phi
        obj.MakeExcitationPlanewave(1.0 if pol == "x" else 0.0, 0, 1.0 if pol == "y" else 0.0, 0, order=0)
        R, T = obj.RT_Solve(normalize=1, byorder=1)
        ai, bi = obj.GetAmplitudes(2, 0.0)
        out.append((R, T, ai))
    return out


def timeit(fn, n):
    fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="skip the 41 x 41 build")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    recipe = load_recipe(REPO / "library" / "paper.toml")
    stack, settings = recipe.stack, recipe.settings
    res: dict = {"n_harmonics_requested": settings.n_harmonics}
    rng = np.random.default_rng(0)
    cells = [tuple(c) for c in rng.uniform(0.1e-6, 0.5e-6, size=(8, 2))]

    it = iter(cells * 100)
    res["s_per_cell_1core"] = timeit(lambda: solve_cell(*next(it), stack, settings), 8)
    it2 = iter(cells * 100)
    res["s_per_cell_naive"] = timeit(lambda: naive_cell(*next(it2), stack, settings), 3)
    res["ratio_naive_over_ours"] = res["s_per_cell_naive"] / res["s_per_cell_1core"]

    many = [tuple(c) for c in rng.uniform(0.1e-6, 0.5e-6, size=(160, 2))]  # enough to amortise worker start-up
    t0 = time.perf_counter()
    solve_cells(many, stack, settings, workers=1)
    t1 = time.perf_counter() - t0
    t0 = time.perf_counter()
    solve_cells(many, stack, settings, workers=2)
    t2 = time.perf_counter() - t0
    res["parallel_speedup_2proc"] = t1 / t2

    if not a.quick:
        d = recipe.to_dict()
        d.pop("name")
        d["sweep"] = {"w_min_um": 0.1, "w_max_um": 0.5, "step_nm": 10.0}
        d["convergence"].pop("check_cells_um")
        with tempfile.TemporaryDirectory() as tmp:
            r41 = recipe_from_dict(d, "bench41")
            t0 = time.perf_counter()
            build_library(r41, Path(tmp) / "b41.npz", workers=2)
            res["build_41x41_2workers_s"] = time.perf_counter() - t0
    if a.json:
        print(json.dumps(res, indent=2))
    else:
        print(f"seconds per cell, 1 core (both pols)   {res['s_per_cell_1core']:.3f} s   (goal <= 0.25 s)")
        print(f"naive grcwa public-API path           {res['s_per_cell_naive']:.3f} s   "
              f"(ratio {res['ratio_naive_over_ours']:.1f}x)")
        print(f"parallel speedup, 2 processes          {res['parallel_speedup_2proc']:.2f}x")
        if "build_41x41_2workers_s" in res:
            print(f"41 x 41 library build, 2 workers       {res['build_41x41_2workers_s']:.1f} s   (goal <= 180 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Issue #34: is the certified (PEDS) model certified where the fab-tolerance study uses it?  Supercells
drawn from the paper design with every pillar biased (default -10 and +10 nm, the sweep's ends), solved at
the label table's converged truncation (nG 797), against the LPA, the committed coupling model and the PEDS
surrogate: per bias, mean and p90 of ``|t_model - t_converged| / rms|t|`` (the certification's measure) and
the mean signed residual with its standard error (a systematic offset is what moves a device's focused
power).  Not run by CI (~5 min on 2 workers):

    python benchmarks/crosscheck_peds_bias.py [layouts/paper-5mm] [--per 64] [--biases -10 10] [-j 2] [--json]"""

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("design", nargs="?", default=str(REPO / "layouts" / "paper-5mm"))
    ap.add_argument("--per", type=int, default=64, help="supercells per bias (64)")
    ap.add_argument("--biases", type=float, nargs="+", default=[-10.0, 10.0], help="nm (-10 10)")
    ap.add_argument("--seed", type=int, default=4242)
    ap.add_argument("-j", "--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if not (Path(a.design) / "design.npz").exists():
        print(f"{a.design}: no design.npz (make it: metadesign design layouts/paper-5mm.toml)", file=sys.stderr)
        return 2
    import torch

    torch.set_num_threads(1)
    from metadesign.design.store import load_design
    from metadesign.library.coupling import lpa_t, relative_error, unit_rms
    from metadesign.library.coupling_net import coupling_t, find_coupling
    from metadesign.library.peds import certified_t
    from metadesign.library.store import interpolate_t
    from metadesign.library.supercells import solve_table
    from metadesign.sensing.model import AsFabricated
    from metadesign.sensing.sampled import eligible_supercells, supercell_widths
    from metadesign.sensing.transmission import Perturbation

    fab = AsFabricated.from_design(load_design(a.design))
    lib = fab.lib
    ids = eligible_supercells(fab)
    rng = np.random.default_rng(a.seed)
    W = np.concatenate([supercell_widths(fab, ids[rng.integers(0, len(ids), a.per)], Perturbation.from_nm(b))
                        for b in a.biases])
    scratch = Path(tempfile.mkdtemp(prefix="crosscheck-peds-bias-"))
    try:
        t0 = time.perf_counter()
        t_conv, nG, _, _ = solve_table(W, lib.stack, 800, scratch / "converged", workers=a.workers)
        t_solve = time.perf_counter() - t0
        t_peds = certified_t(lib, W, scratch / "peds", workers=a.workers)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    tu = interpolate_t(lib, W[..., 0], W[..., 1])[0]
    pair, _, _ = find_coupling(lib)
    models = {"LPA": lpa_t(tu), "coupling model": coupling_t(pair, W, tu), "PEDS": t_peds}
    rms = unit_rms(tu)
    rep = {"n_harmonics": int(nG), "per_bias": a.per, "converged_seconds": t_solve, "rows": []}
    for j, b in enumerate(a.biases):
        s = slice(j * a.per, (j + 1) * a.per)
        for name, t in models.items():
            e = relative_error(t[s], t_conv[s], tu[s])
            r = (t[s] - t_conv[s]) / rms[s]
            m, se = r.mean(0), r.std(0) / np.sqrt(a.per)
            rep["rows"].append({"bias_nm": b, "model": name, "mean": float(e.mean()),
                                "p90": float(np.percentile(e, 90)),
                                "mean_residual_abs": [float(v) for v in np.abs(m)],
                                "mean_residual_se": [float(v) for v in np.abs(se)]})
    if a.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f"{len(W)} biased design supercells at nG {nG} ({t_solve:.0f} s on {a.workers} workers); "
          "error in units of rms|t| (goal 0.05 / 0.10)")
    print("  bias nm  model            mean    p90    |mean residual| x, y  (standard error)")
    for r in rep["rows"]:
        print(f"  {r['bias_nm']:+7.1f}  {r['model']:<15} {r['mean']:.3f}  {r['p90']:.3f}   "
              f"{r['mean_residual_abs'][0]:.3f}, {r['mean_residual_abs'][1]:.3f}  "
              f"({r['mean_residual_se'][0]:.3f}, {r['mean_residual_se'][1]:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The certified (PEDS) surrogate's cost per supercell, one core (#34): the numpy path (`certified_t`'s
low-fidelity solves, fresh, no chunk cache), the torch twin's batched forward, and its backward (the
gradient of one number with respect to all sixteen widths of every supercell), in the same run, on the
same random supercells; and the largest difference between the two paths' transmissions.

    python benchmarks/bench_peds_torch.py [--supercells 32] [--json]"""

import argparse
import json
import os
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
    ap.add_argument("--supercells", type=int, default=32)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from metadesign.library.peds import certified_t, find_peds, load_peds
    from metadesign.library.peds_torch import peds_t_torch
    from metadesign.library.store import load_library

    lib = load_library(REPO / "library" / "paper.npz")
    model = load_peds(find_peds(lib), lib)
    W = np.random.default_rng(7).uniform(0.12e-6, 0.55e-6, (a.supercells, 2, 2, 2))
    peds_t_torch(model, lib, torch.tensor(W[:2]))  # set-up (harmonic sets, symmetry bases) cached once
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        t_np = certified_t(lib, W, Path(tmp) / "p", model)
        t_numpy = time.perf_counter() - t0
    w = torch.tensor(W, requires_grad=True)
    t0 = time.perf_counter()
    t = peds_t_torch(model, lib, w)
    t_fwd = time.perf_counter() - t0
    t0 = time.perf_counter()
    (t.real.sum() + t.imag.sum()).backward()
    t_bwd = time.perf_counter() - t0
    n = a.supercells
    rep = {"supercells": n, "levels": list(model.harmonics), "numpy_s_per_supercell": t_numpy / n,
           "torch_forward_s_per_supercell": t_fwd / n, "torch_backward_s_per_supercell": t_bwd / n,
           "torch_over_numpy": t_fwd / t_numpy, "gradient_over_numpy_forward": (t_fwd + t_bwd) / t_numpy,
           "max_abs_difference": float(np.abs(t.detach().numpy() - t_np).max()),
           "gradient_finite": bool(torch.isfinite(w.grad).all())}
    if a.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f"PEDS surrogate, levels nG {model.harmonics}, {n} random supercells, one core:")
    print(f"  numpy (certified_t)         {rep['numpy_s_per_supercell']:.3f} s per supercell")
    print(f"  torch twin, forward         {rep['torch_forward_s_per_supercell']:.3f} s  "
          f"({rep['torch_over_numpy']:.2f}x numpy)")
    print(f"  torch twin, backward        {rep['torch_backward_s_per_supercell']:.3f} s  (value + gradient of all "
          f"16 widths: {rep['gradient_over_numpy_forward']:.2f}x a numpy forward)")
    print(f"  max |t_torch - t_numpy|     {rep['max_abs_difference']:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

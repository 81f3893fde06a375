"""Turbulence benchmark: per-sample cost (13 screens + split-step) on one core,
numpy and torch, against the bare FFT lower bound (13 propagation FFT pairs
plus 13 screen FFTs; goal: within 2x).

    python benchmarks/bench_turbulence.py [--json]
"""

import json
import os
import sys
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import scipy.fft as sfft  # noqa: E402


def best(fn, reps=40):
    from metadesign.timing import repeat_seconds

    return repeat_seconds(fn, reps, stat="min")  # best of reps: the least disturbed by the shared cores


def main() -> int:
    import torch

    torch.set_num_threads(1)
    from metadesign.turbulence.path import Scenario
    from metadesign.turbulence.propagate import Turbulence, split_step, split_step_torch

    sc = Scenario()
    tb = Turbulence(sc)
    n = sc.n_grid
    u = (np.random.default_rng(0).standard_normal((n, n)) + 1j).astype(np.complex64)
    t_pair = best(lambda: sfft.ifft2(sfft.fft2(u)))
    t_one = best(lambda: sfft.ifft2(u))
    bound = 13 * t_pair + 13 * t_one
    seeds = iter(range(10**6))
    t_screens = best(lambda: tb.screens(next(seeds)))
    ph = tb.screens(0)
    t_prop = best(lambda: split_step(tb.source, ph, tb.H, tb.absorber))
    t_sample = best(lambda: tb.sample(next(seeds)))
    src = torch.tensor(tb.source)
    pht = torch.tensor(ph)
    H = torch.tensor(tb.H)
    ab = torch.tensor(tb.absorber)
    t_torch = best(lambda: split_step_torch(src, pht, H, ab))
    t_torch_screens = t_screens + t_torch
    res = {"grid": n, "fft_pair_ms": t_pair * 1e3, "fft_bound_ms": bound * 1e3, "screens_ms": t_screens * 1e3,
           "split_step_numpy_ms": t_prop * 1e3, "sample_numpy_ms": t_sample * 1e3,
           "split_step_torch_ms": t_torch * 1e3, "sample_torch_ms": t_torch_screens * 1e3,
           "ratio_numpy": t_sample / bound, "ratio_torch": t_torch_screens / bound}
    if "--json" in sys.argv:
        print(json.dumps(res, indent=2))
    else:
        print(f"grid {n}^2, 13 screens, 1 core")
        print(f"  FFT pair {res['fft_pair_ms']:.2f} ms; lower bound (13 pairs + 13 screen FFTs) {res['fft_bound_ms']:.1f} ms")
        print(f"  screens {res['screens_ms']:.1f} ms, split step numpy {res['split_step_numpy_ms']:.1f} ms / torch "
              f"{res['split_step_torch_ms']:.1f} ms")
        print(f"  per sample: numpy {res['sample_numpy_ms']:.1f} ms ({res['ratio_numpy']:.2f}x bound), torch "
              f"{res['sample_torch_ms']:.1f} ms ({res['ratio_torch']:.2f}x bound); goal <= 2x")
    return 0


if __name__ == "__main__":
    sys.exit(main())

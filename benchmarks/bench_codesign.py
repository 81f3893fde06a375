"""Co-design (#33): the cost of rendering the eight PSFs through the diversity twin (forward + backward,
per sample, one thread) at the twin's approximations, against the U-Net's training step on the same
tensors, with each approximation's error against the exact twin; and the time of one Fisher matrix
(forward-mode Jacobian, 20 modes).  Goal: co-design at demo scale (5,760 samples x 12 epochs) within
~2 h on 2 cores, i.e. rendering + U-Net <= ~50 ms per sample on one thread.

    python benchmarks/bench_codesign.py [--dataset sensing/dataset-demo] [--batch 16] [--json]
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(REPO / "sensing" / "dataset-demo"))
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    import torch

    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.dataset import load_device, open_dataset
    from metadesign.reconstruction.model import UNetConfig, build_unet
    from metadesign.sensing.diversity import diversity_operators, lens_table
    from metadesign.sensing.fisher import crop_zernike_basis, zernike_fisher
    from metadesign.sensing.twin import twin_error
    from metadesign.sensing.twin_diversity import DiversityTwin

    torch.set_num_threads(1)
    dev = load_device(a.dataset)
    lenses = lens_table(open_dataset(a.dataset).attrs["provenance"]["channels"])
    pd = PSFDataset(a.dataset, "train")
    x = torch.from_numpy(np.stack([pd.get(i)["received"] for i in range(a.batch)]))
    rows = []
    for rebin, samples in ((1, None), (2, 3), (2, 2), (4, 2), (4, 1)):
        tw = DiversityTwin(diversity_operators(dev.pupil, dev.sensor, lenses, dev.geometry, rebin, samples))
        ts = []
        for _ in range(3):
            tw.zero_grad()
            t = time.perf_counter()
            tw(x).sum().backward()
            ts.append(time.perf_counter() - t)
        err = twin_error(dev.pupil, dev.sensor, dev.geometry, x[:8].numpy(), rebin, samples)
        rows.append({"rebin": rebin, "samples": samples, "ms_per_sample": 1e3 * min(ts) / a.batch,
                     "error_vs_exact": err})
    s = dev.sensor.tensor_size
    unet = build_unet(UNetConfig(8, 16, 5, s, dev.crop.size))
    inp = torch.randn(a.batch, 8, s, s)
    ts = []
    for _ in range(3):
        unet.zero_grad()
        t = time.perf_counter()
        unet(inp).sum().backward()
        ts.append(time.perf_counter() - t)
    unet_ms = 1e3 * min(ts) / a.batch
    c0, n, ng, dx, d2 = dev.geometry
    tw = DiversityTwin(diversity_operators(dev.pupil, dev.sensor, lenses, dev.geometry))
    basis = crop_zernike_basis(range(2, 22), c0, n, ng, dx, d2)
    t = time.perf_counter()
    zernike_fisher(tw, x[:1].numpy(), basis, 1e6)
    fisher_s = time.perf_counter() - t
    out = {"dataset": a.dataset, "pupil_n": dev.pupil_n, "tensor_size": s, "twin": rows,
           "unet_step_ms_per_sample": unet_ms, "fisher_seconds_20_modes": fisher_s,
           "ratio_twin_2x2_to_unet": rows[2]["ms_per_sample"] / unet_ms}
    if a.json:
        print(json.dumps(out, indent=1))
        return
    print(f"co-design on {a.dataset}: pupil {dev.pupil_n}^2, tensor 8 x {s}^2, one thread, batch {a.batch}")
    for r in rows:
        print(f"  twin rebin {r['rebin']} samples {r['samples'] or 'all'}: {r['ms_per_sample']:6.1f} ms/sample "
              f"(fwd+bwd), error vs exact {r['error_vs_exact']:.4f}")
    print(f"  U-Net (base 16) training step: {unet_ms:.1f} ms/sample; twin(2, 2) / U-Net = {out['ratio_twin_2x2_to_unet']:.2f}")
    print(f"  one Fisher matrix (20 modes, exact twin): {fisher_s:.1f} s")


if __name__ == "__main__":
    main()

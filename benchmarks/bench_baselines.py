"""Baselines benchmark: per sample on one CPU thread (CUDA too when present), on the demo dataset's device:

* the PSF path: numpy (sensor_frames + psf_tensor) vs the exact torch twin (forward; forward+backward),
  and the two approximate twins the retrieval iterates on (coarse: pupil rebin 4, 1 point per tensor
  pixel; fine: rebin 2, 2 x 2 points), with their error against the exact twin on received fields;
* one retrieval iteration (modal stage with 3 starts, zonal stage), in a batch of 1 and of 8;
* Shack-Hartmann processing (centroids + reconstruction) and the U-Net forward, for the latency table.

    python benchmarks/bench_baselines.py [--dataset sensing/dataset-demo] [--json]
"""

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _time(fn, n=5):
    from metadesign.timing import repeat_seconds

    return repeat_seconds(fn, n)


def measure(dataset: str, device: str = "cpu") -> dict:
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.dataset import load_device
    from metadesign.reconstruction.model import load_model
    from metadesign.reconstruction.retrieval import RetrievalConfig, RetrievalContext, retrieve
    from metadesign.reconstruction.shack_hartmann import ShackHartmann, SHConfig
    from metadesign.sensing.forward import sensor_frames
    from metadesign.sensing.sensor import psf_tensor
    from metadesign.sensing.twin import TorchTwin, crop_to_pupil, twin_error, twin_operators

    dev = load_device(dataset)
    cp, sensor, geom = dev.pupil, dev.sensor, dev.geometry
    c0, a, ng, dx, d2 = geom
    ds = PSFDataset(dataset, "test", gaussian_percent=5, limit=8)
    items = [ds.get(i) for i in range(len(ds))]
    rec = np.stack([s["received"] for s in items])
    out = {"device": device, "pupil_grid": int(cp.G.shape[-1]), "tensor": int(sensor.tensor_size)}
    e = crop_to_pupil(rec[0], ng, dx, d2, c0, cp.G.shape[-1])
    out["numpy_ms"] = 1e3 * _time(lambda: psf_tensor(sensor_frames(cp, sensor, e), sensor))
    d = torch.device(device)
    x1 = torch.from_numpy(rec[:1]).to(d)
    x8 = torch.from_numpy(rec).to(d)
    for name, (rb, q) in {"exact": (1, None), "fine": (2, 2), "coarse": (4, 1)}.items():
        tw = TorchTwin(twin_operators(cp, sensor, geom, rb, q), d)
        with torch.no_grad():
            out[f"twin_{name}_fwd_ms"] = 1e3 * _time(lambda: tw.from_crop(x1))
            out[f"twin_{name}_fwd_batch8_ms_per_sample"] = 1e3 * _time(lambda: tw.from_crop(x8)) / 8
        phi = torch.zeros((1, a, a), device=d, requires_grad=True)

        def step():
            tw.from_crop(x1 * torch.polar(torch.ones_like(phi), phi)).square().sum().backward()

        out[f"twin_{name}_fwd_bwd_ms"] = 1e3 * _time(step)
        if name != "exact":
            out[f"twin_{name}_rel_error"] = twin_error(cp, sensor, geom, rec, rb, q)
    out["twin_exact_vs_numpy"] = out["twin_exact_fwd_ms"] / out["numpy_ms"]
    psf = torch.from_numpy(np.stack([s["psf"] for s in items]))
    for its, label in (((1,), "modal"), ((), "zonal")):
        cfg = RetrievalConfig(modal_orders=(2,) if its else (2,), modal_iterations=10 if its else 0,
                              zonal_iterations=0 if its else 10, misfit="gaussian", noise_percent=5)
        ctx = RetrievalContext.build(dev, cfg, device)
        init = None if its else torch.zeros((1, a, a))
        out[f"retrieval_{label}_iteration_ms"] = 1e3 * _time(lambda: retrieve(psf[:1], ctx, cfg, init=init), 3) / 10
        init8 = None if its else torch.zeros((8, a, a))
        out[f"retrieval_{label}_iteration_batch8_ms_per_sample"] = \
            1e3 * _time(lambda: retrieve(psf, ctx, cfg, init=init8), 3) / 80
    sh = ShackHartmann.for_device(SHConfig(lenslets=5), dev)
    spots = sh.add_noise(sh.frames(rec[:1]), 5.0, np.random.default_rng(0))
    out["shack_hartmann_ms"] = 1e3 * _time(lambda: sh.reconstruct(*sh.centroids(spots, 5.0)), 20)
    model_path = REPO / "sensing" / "models" / "demo-unet.safetensors"
    if model_path.is_file():
        m, _ = load_model(model_path, device)
        with torch.no_grad():
            p1 = psf[:1].to(d)
            out["unet_ms"] = 1e3 * _time(lambda: m(p1), 20)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default=str(REPO / "sensing" / "dataset-demo"))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    import torch

    res = {"cpu": measure(a.dataset)}
    if torch.cuda.is_available():  # pragma: no cover - no GPU here
        res["cuda"] = measure(a.dataset, "cuda")
    if a.json:
        print(json.dumps(res, indent=2))
        return 0
    for dev, r in res.items():
        print(f"[{dev}] pupil {r['pupil_grid']}^2 -> 8 x {r['tensor']}^2, per sample, one thread")
        print(f"  numpy PSF path            {r['numpy_ms']:8.1f} ms")
        for n in ("exact", "fine", "coarse"):
            err = f", error vs exact {100 * r[f'twin_{n}_rel_error']:.1f} %" if n != "exact" else ""
            print(f"  twin {n:<7} forward {r[f'twin_{n}_fwd_ms']:7.1f} ms (batch 8: "
                  f"{r[f'twin_{n}_fwd_batch8_ms_per_sample']:.1f}), forward+backward {r[f'twin_{n}_fwd_bwd_ms']:7.1f} ms{err}")
        print(f"  exact twin / numpy        {r['twin_exact_vs_numpy']:8.2f}x")
        for s in ("modal", "zonal"):
            print(f"  retrieval {s} iteration  {r[f'retrieval_{s}_iteration_ms']:8.1f} ms (batch 8: "
                  f"{r[f'retrieval_{s}_iteration_batch8_ms_per_sample']:.1f} ms per sample)")
        print(f"  Shack-Hartmann processing {r['shack_hartmann_ms']:8.2f} ms")
        if "unet_ms" in r:
            print(f"  U-Net forward             {r['unet_ms']:8.2f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Dataset benchmark (stage 6a) on the paper layout: per-sample cost split into screens, split step,
transfer to the metasurface, PSF render and storage; against the turbulence sample plus the 8-PSF
render measured alone in the same run (goal: total <= 1.3x); 2 local workers vs 1 (goal >= 1.8x); a
Dask LocalCluster of 2 workers vs the local pool (goal: within 15 %); projections for the paper's set.

    python benchmarks/bench_dataset.py [--samples 256] [--json]
"""

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=256, help="samples per scale-out run (default 256)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    from metadesign.reconstruction.dataset import (
        ShardContext,
        build_dataset,
        ensure_layout,
        load_dataset_recipe,
        make_sample,
    )
    from metadesign.sensing.model import AsFabricated, load_sensing_recipe
    from metadesign.sensing.render import render_psf
    from metadesign.turbulence.scenario import load_scenario

    rec = load_dataset_recipe(REPO / "sensing" / "dataset-demo.toml")
    layout = ensure_layout(rec, print)
    fab = AsFabricated.from_files(layout)
    out = {}
    for ts in (64, 256):
        sr = load_sensing_recipe(rec.sensor)
        sr = replace(sr, sensor=replace(sr.sensor, tensor_size=ts))
        sc = load_scenario(rec.turbulence)
        cp = fab.pupil(sr.sensor.distance, sr.pupil_grid)
        ctx = ShardContext(cp, sr, sc, fab.n_cells * fab.period, "", 0, 10**6, 64, rec.rytov_range, None)
        chain = ctx.chain()
        make_sample(ctx, 0)  # warm-up
        rows = [make_sample(ctx, i)["timings"] for i in range(1, 21)]
        split = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
        # storage: one 64-sample shard written to a zarr store of this tensor size
        with tempfile.TemporaryDirectory() as tmp:
            import zarr

            s = make_sample(ctx, 1)
            g = zarr.open_group(tmp, mode="w")
            pa = g.create_array("psf", shape=(64, 8, ts, ts), chunks=(1, 8, ts, ts), shards=(64, 8, ts, ts),
                                dtype="float32")
            ra = g.create_array("received", shape=(64,) + s["received"].shape, chunks=(1,) + s["received"].shape,
                                shards=(64,) + s["received"].shape, dtype="complex64")
            t0 = time.perf_counter()
            pa[:] = np.repeat(s["psf"][None], 64, 0)
            ra[:] = np.repeat(s["received"][None], 64, 0)
            split["storage"] = (time.perf_counter() - t0) / 64
            bytes_per_sample = sum(p.stat().st_size for p in Path(tmp).rglob("*") if p.is_file()) / 64
        total = sum(split.values())
        # references, measured alone: one turbulence sample, one 8-PSF render of a given field
        tb = chain.at(0.4)
        t_turb = float(np.median([_t(lambda i=i: tb.sample(i)) for i in range(20)]))
        e_in = tb.to_metasurface(tb.sample(3).field, cp.G.shape[-1])
        t_psf = float(np.median([_t(lambda: render_psf(fab, sr, e_in, pupil=cp)) for _ in range(20)]))
        out[f"tensor_{ts}"] = {"per_sample_ms": {k: 1e3 * v for k, v in split.items()}, "total_ms": 1e3 * total,
                               "turbulence_sample_ms": 1e3 * t_turb, "psf_render_ms": 1e3 * t_psf,
                               "ratio_total_vs_turbulence_plus_psf": total / (t_turb + t_psf),
                               "bytes_per_sample": bytes_per_sample}
    # scale-out on the real builder: -j 1, -j 2, Dask LocalCluster(2)
    from dask.distributed import Client, LocalCluster

    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        r = rec.with_samples(a.samples)
        r = replace(r, shard_size=8)
        for j in (1, 2):
            rep = build_dataset(r, Path(tmp) / f"j{j}", workers=j)
            times[f"local_j{j}"] = rep["sweep_seconds"]
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                          env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}) as cl:
            with Client(cl) as client:
                client.run(lambda: __import__("metadesign.reconstruction.dataset"))  # warm the workers' imports
                rep = build_dataset(r, Path(tmp) / "dask", client=client)
                times["dask_2"] = rep["sweep_seconds"]
    speedup = times["local_j1"] / times["local_j2"]
    dask_vs = times["dask_2"] / times["local_j2"]
    t256 = out["tensor_256"]["total_ms"] / 1e3
    res = {**out, "scale_out_seconds": times, "samples": a.samples, "speedup_2_workers": speedup,
           "dask_over_local_pool": dask_vs,
           "projection_paper_100k_hours": {"one_2core_machine": 100_000 * t256 / 2 / 3600,
                                           "dask_64_cores": 100_000 * t256 / 64 / 3600},
           "paper_set_bytes": 100_000 * out["tensor_256"]["bytes_per_sample"]}
    if a.json:
        print(json.dumps(res, indent=2))
        return 0
    for ts in (64, 256):
        o = out[f"tensor_{ts}"]
        print(f"tensor 8x{ts}^2, paper layout, one core: per sample " + ", ".join(
            f"{k} {v:.1f} ms" for k, v in o["per_sample_ms"].items()) + f" = {o['total_ms']:.1f} ms")
        print(f"  vs turbulence sample {o['turbulence_sample_ms']:.1f} ms + 8-PSF render {o['psf_render_ms']:.1f} ms: "
              f"ratio {o['ratio_total_vs_turbulence_plus_psf']:.2f} (goal <= 1.3); "
              f"{o['bytes_per_sample'] / 1e3:.0f} kB per sample on disk")
    print(f"scale-out ({a.samples} samples, tensor 64): -j 1 {times['local_j1']:.1f} s, -j 2 {times['local_j2']:.1f} s "
          f"-> {speedup:.2f}x (goal >= 1.8, worker start-up included); Dask LocalCluster(2) {times['dask_2']:.1f} s "
          f"= {dask_vs:.2f}x the local pool (goal within 1.15)")
    p = res["projection_paper_100k_hours"]
    print(f"paper set (100,000 x 8 x 256^2): {p['one_2core_machine']:.1f} h on one 2-core machine, "
          f"{60 * p['dask_64_cores']:.0f} min on a 64-core Dask cluster; {res['paper_set_bytes'] / 1e9:.0f} GB")
    return 0


def _t(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


if __name__ == "__main__":
    sys.exit(main())

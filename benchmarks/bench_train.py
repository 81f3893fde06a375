"""Training benchmark (stage 6b): per training sample on CPU, one process and two concurrent processes,
split into data loading (with and without regenerating the 13 screens), U-Net forward+backward, the
end-to-end PiB loss forward+backward (split step, and the quadratic form with its one-off cost; loading
the stored operator when the dataset has them, `metadesign dataset operators`), the
phase loss; for the demo and the paper configuration (a few steps); CUDA when present.  Goals: the
end-to-end loss costs no more than the U-Net step at the demo configuration; the loader delivers >= 2x
the step rate; projection of the paper's 500 epochs x 90,000 samples.

    python benchmarks/bench_train.py [--dataset sensing/dataset-demo] [--json]
"""

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CONFIGS = {"demo": dict(base=16, depth=5, size=64, batch=32, steps=4),
           "paper": dict(base=64, depth=5, size=256, batch=4, steps=2)}


def measure(dataset: str, name: str, device: str = "cpu") -> dict:
    import torch

    torch.set_num_threads(1)
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.losses import PiB, phase_loss
    from metadesign.reconstruction.model import UNetConfig, build_unet

    c = CONFIGS[name]
    dev = torch.device(device)
    ds = PSFDataset(dataset, "train", gaussian_percent=5, screens=True, limit=64)
    c0, a = ds.crop()
    pib = PiB(ds.scenario(), c0, a, dev)
    t0 = time.perf_counter()
    items = [ds[i] for i in range(c["batch"])]
    t_load_screens = (time.perf_counter() - t0) / c["batch"]
    ds.screens = False
    t0 = time.perf_counter()
    [ds[i] for i in range(c["batch"])]
    t_load = (time.perf_counter() - t0) / c["batch"]
    from metadesign.reconstruction.operators import has_operators

    t_load_ops = None
    if has_operators(ds.info.attrs, "train"):  # the stored bucket operators (metadesign dataset operators)
        ds.operators = True
        [ds[i] for i in range(c["batch"], 2 * c["batch"])]  # warm the shard index
        t0 = time.perf_counter()
        [ds[i] for i in range(c["batch"])]
        t_load_ops = (time.perf_counter() - t0) / c["batch"]
        ds.operators = False
    b = {k: torch.stack([x[k] for x in items]).to(dev) for k in items[0]}
    x = b["psf"]
    if x.shape[-1] != c["size"]:
        x = torch.nn.functional.interpolate(x, size=(c["size"], c["size"]), mode="bilinear")
    m = build_unet(UNetConfig(8, c["base"], c["depth"], c["size"], a)).to(dev)
    torch.nn.init.normal_(m.head.weight, std=1e-3)
    from metadesign.timing import repeat_seconds

    sync = torch.cuda.synchronize if dev.type == "cuda" else None

    def timeit(fn, reps, batch=c["batch"]):
        return repeat_seconds(fn, reps, sync=sync) / batch

    def unet_step():
        m.zero_grad()
        m(x).sum().backward()

    phi0 = torch.zeros((c["batch"], a, a), device=dev, requires_grad=True)

    def pib_step():
        pib.loss(phi0, b["screens"])[0].backward()

    def phase_step():
        phase_loss(phi0, b["received"], pib.ap).backward()

    res = {"config": c, "params": sum(p.numel() for p in m.parameters()),
           "load_ms": 1e3 * t_load, "load_with_screens_ms": 1e3 * t_load_screens,
           "load_with_operator_ms": None if t_load_ops is None else 1e3 * t_load_ops,
           "unet_fwd_bwd_ms": 1e3 * timeit(unet_step, c["steps"]),
           "pib_loss_fwd_bwd_ms": 1e3 * timeit(pib_step, c["steps"]),
           "phase_loss_fwd_bwd_ms": 1e3 * timeit(phase_step, c["steps"])}
    # the quadratic form: one-off operator per sample, then a small matrix product
    t = time.perf_counter()
    A = pib.bucket_operator(b["screens"][:2])
    res["quadratic_operator_ms"] = 1e3 * (time.perf_counter() - t) / 2
    A = A.repeat(c["batch"] // 2, 1, 1)
    phq = torch.zeros((A.shape[0], a, a), device=dev, requires_grad=True)

    def quad_step():
        (-torch.log(pib.npib_quadratic(A, phq))).mean().backward()

    res["quadratic_loss_fwd_bwd_ms"] = 1e3 * timeit(quad_step, c["steps"], A.shape[0])
    res["quadratic_bytes_per_sample"] = int(A[0].numel() * 8)
    try:
        from torch.utils.flop_counter import FlopCounterMode

        with FlopCounterMode(display=False) as fc:
            m(x[:1]).sum().backward()
        res["unet_gflop_per_sample_fwd_bwd"] = fc.get_total_flops() / 1e9
    except Exception:  # noqa: BLE001 - optional
        pass
    return res


def _worker(args):
    os.environ.update(OMP_NUM_THREADS="1")
    return measure(*args)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--dataset", default=str(REPO / "sensing" / "dataset-demo"))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    out = {}
    for name in ("demo", "paper"):
        out[name] = {"one_process": measure(a.dataset, name)}
    with mp.get_context("spawn").Pool(2) as pool:
        two = pool.map(_worker, [(a.dataset, "demo")] * 2)
    out["demo"]["two_processes_each"] = two
    import torch

    if torch.cuda.is_available():
        for name in ("demo", "paper"):
            out[name]["cuda"] = measure(a.dataset, name, "cuda")
    d = out["demo"]["one_process"]
    step = d["unet_fwd_bwd_ms"] + d["pib_loss_fwd_bwd_ms"]
    out["goals"] = {
        "pib_loss_over_unet_step_demo": d["pib_loss_fwd_bwd_ms"] / d["unet_fwd_bwd_ms"],
        "pib_quadratic_over_unet_step_demo": d["quadratic_loss_fwd_bwd_ms"] / d["unet_fwd_bwd_ms"],
        "loader_rate_over_step_rate_pib": step / d["load_with_screens_ms"],
        "loader_rate_over_step_rate_quadratic": (d["unet_fwd_bwd_ms"] + d["quadratic_loss_fwd_bwd_ms"]) / d["load_ms"],
        "loader_rate_over_step_rate_stored": None if d["load_with_operator_ms"] is None else
        (d["unet_fwd_bwd_ms"] + d["quadratic_loss_fwd_bwd_ms"]) / d["load_with_operator_ms"],
        "two_process_throughput_ratio": sum(1 / (t["unet_fwd_bwd_ms"] + t["pib_loss_fwd_bwd_ms"]) for t in two)
        / (1 / step),
    }
    p = out["paper"]["one_process"]
    per = (p["unet_fwd_bwd_ms"] + p["pib_loss_fwd_bwd_ms"] + p["load_with_screens_ms"]) / 1e3
    out["projection_paper_500_epochs_90k"] = {
        "cpu_one_core_days": 500 * 90_000 * per / 86400,
        "gpu_estimate_hours_at_100_TFLOPs_30pct": 500 * 90_000 * p.get("unet_gflop_per_sample_fwd_bwd", 0) * 1e9
        / (0.3 * 100e12) / 3600,
        # with stored operators: the loss is a matrix product, the loader reads A (the demo's load time:
        # same grid, same A), plus the one-off operators (one adjoint split step per bucket pixel)
        "cpu_one_core_days_stored_operators": None if d["load_with_operator_ms"] is None else
        500 * 90_000 * (p["unet_fwd_bwd_ms"] + p["quadratic_loss_fwd_bwd_ms"]
                        + max(p["load_ms"], d["load_with_operator_ms"])) / 1e3 / 86400,
        "operators_one_off_core_hours": 90_000 * p["quadratic_operator_ms"] / 1e3 / 3600,
        "operators_disk_GB": 90_000 * p["quadratic_bytes_per_sample"] / 1e9,
    }
    if a.json:
        print(json.dumps(out, indent=2))
        return 0
    for name in ("demo", "paper"):
        r = out[name]["one_process"]
        print(f"{name} (base {r['config']['base']}, depth {r['config']['depth']}, {r['config']['size']}^2, "
              f"{r['params'] / 1e6:.1f} M params), per sample on 1 CPU core: load {r['load_ms']:.1f} ms "
              f"(+ screens: {r['load_with_screens_ms']:.1f} ms), U-Net fwd+bwd {r['unet_fwd_bwd_ms']:.1f} ms, "
              f"PiB loss fwd+bwd {r['pib_loss_fwd_bwd_ms']:.1f} ms (quadratic form {r['quadratic_loss_fwd_bwd_ms']:.2f} ms "
              f"after a one-off {r['quadratic_operator_ms']:.0f} ms, {r['quadratic_bytes_per_sample'] / 1e3:.0f} kB), "
              f"phase loss {r['phase_loss_fwd_bwd_ms']:.2f} ms"
              + (f"; U-Net {r['unet_gflop_per_sample_fwd_bwd']:.2f} GFLOP" if "unet_gflop_per_sample_fwd_bwd" in r else ""))
    g = out["goals"]
    print(f"goals (demo): PiB loss / U-Net step {g['pib_loss_over_unet_step_demo']:.2f} (goal <= 1; quadratic form "
          f"{g['pib_quadratic_over_unet_step_demo']:.3f}); loader rate / step rate {g['loader_rate_over_step_rate_pib']:.2f} "
          f"with screens regenerated (goal >= 2; {g['loader_rate_over_step_rate_quadratic']:.1f} with the quadratic "
          f"form in memory)")
    if g["loader_rate_over_step_rate_stored"] is None:
        print("stored operators: none in this dataset (metadesign dataset operators DATASET adds them)")
    else:
        print(f"stored operators (train.pib_operator = auto): load {d['load_with_operator_ms']:.1f} ms per sample, "
              f"loss {d['quadratic_loss_fwd_bwd_ms']:.2f} ms = {g['pib_quadratic_over_unet_step_demo']:.3f} x the U-Net "
              f"step (goal <= 1), loader rate / step rate {g['loader_rate_over_step_rate_stored']:.1f} (goal >= 2)")
    print(f"2 processes give {g['two_process_throughput_ratio']:.2f}x one (split-step PiB step)")
    pr = out["projection_paper_500_epochs_90k"]
    print(f"paper 500 epochs x 90,000: {pr['cpu_one_core_days']:.0f} days on one CPU core"
          + ("" if pr["cpu_one_core_days_stored_operators"] is None else
             f" ({pr['cpu_one_core_days_stored_operators']:.0f} with stored operators, after a one-off "
             f"{pr['operators_one_off_core_hours']:.1f} core-hours and {pr['operators_disk_GB']:.0f} GB)") + "; "
          f"~{pr['gpu_estimate_hours_at_100_TFLOPs_30pct']:.0f} h on one GPU at 30 % of 100 TFLOP/s (estimate from the "
          "U-Net's FLOPs; no GPU measured here)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

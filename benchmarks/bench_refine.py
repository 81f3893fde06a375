"""The learned refinement (#23): latency per frame of the U-Net and of the refiner (U-Net + K unrolled
steps through the twin) on one CPU thread, batch 1 and batch 8 (per frame), per step K, in torch and in
onnxruntime; and the training cost per sample (forward + backward with the PiB loss on stored
operators) against the U-Net's training step.  Goal: the refiner <= 25 ms per frame on one thread.

    python benchmarks/bench_refine.py [--refiner sensing/models/demo-refine.safetensors]
                                      [--dataset sensing/dataset-demo] [--runs 100] [--json]

Without a committed refiner, an untrained one (same architecture, steps from the recipe) around
demo-unet-long is timed: latency does not depend on the weights.
"""

import argparse
import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def _lat(fn, runs, warm=5):
    for _ in range(warm):
        fn()
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    ts = np.array(ts) * 1e3
    return {"median_ms": float(np.median(ts)), "p99_ms": float(np.percentile(ts, 99)), "runs": runs}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--refiner", default=str(REPO / "sensing" / "models" / "demo-refine.safetensors"))
    ap.add_argument("--dataset", default=str(REPO / "sensing" / "dataset-demo"))
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from metadesign.reconstruction.model import load_model
    from metadesign.reconstruction.refine import build_refiner, load_refiner
    from metadesign.reconstruction.train import load_train_recipe

    if Path(a.refiner).exists():
        ref, card = load_refiner(a.refiner)
        source = a.refiner
    else:
        from metadesign.reconstruction.dataset import load_device

        unet, _ = load_model(REPO / "sensing" / "models" / "demo-unet-long.safetensors")
        cfg = load_train_recipe(REPO / "sensing" / "train-demo-refine.toml").refine
        ref = build_refiner(unet, cfg, load_device(a.dataset)).eval()
        source = "untrained (train-demo-refine.toml architecture)"
    unet = ref.unet
    K = len(ref.steps)
    s = unet.config.input_size
    g = torch.Generator().manual_seed(0)
    x1 = torch.rand(1, 8, s, s, generator=g)
    x8 = torch.rand(8, 8, s, s, generator=g)
    res = {"refiner": source, "steps": K, "params_refiner": sum(p.numel() for p in ref.steps.parameters()),
           "params_unet": sum(p.numel() for p in unet.parameters()), "threads": 1}
    with torch.inference_mode():
        res["unet_batch1"] = _lat(lambda: unet(x1), a.runs)
        res["unet_batch8_per_frame_ms"] = _lat(lambda: unet(x8), max(5, a.runs // 8))["median_ms"] / 8
        res["refiner_batch1_by_k_ms"] = [_lat(lambda: ref(x1, k), a.runs)["median_ms"] for k in range(K + 1)]
        res["refiner_batch1"] = _lat(lambda: ref(x1), a.runs)
        res["refiner_batch8_per_frame_ms"] = _lat(lambda: ref(x8), max(5, a.runs // 8))["median_ms"] / 8
    try:
        import onnxruntime as ort

        with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            f = Path(tmp) / "r.onnx"
            torch.onnx.export(ref, (x1,), str(f), input_names=["psf"], output_names=["phase"],
                              dynamic_axes={"psf": {0: "batch"}, "phase": {0: "batch"}}, opset_version=17, dynamo=False)
            so = ort.SessionOptions()
            so.intra_op_num_threads = 1
            sess = ort.InferenceSession(str(f), so, providers=["CPUExecutionProvider"])
            xi, x8i = x1.numpy(), x8.numpy()
            res["onnxruntime_refiner_batch1"] = _lat(lambda: sess.run(None, {"psf": xi}), a.runs)
            res["onnxruntime_refiner_batch8_per_frame_ms"] = _lat(lambda: sess.run(None, {"psf": x8i}),
                                                                  max(5, a.runs // 8))["median_ms"] / 8
    except ImportError:
        pass
    # training cost per sample: the refiner's forward + backward with the PiB loss on stored operators
    # (batch 16), against the U-Net's own training step on the same batch
    try:
        from metadesign.reconstruction.data import PSFDataset
        from metadesign.reconstruction.losses import PiB

        ds = PSFDataset(a.dataset, "train", gaussian_percent=(0, 10), operators=True, limit=16)
        b = [ds[i] for i in range(16)]
        x = torch.stack([t["psf"] for t in b])
        A = torch.stack([t["A"] for t in b])
        c0, aa = ds.crop()
        pib = PiB(ds.scenario(), c0, aa)
        ref.train()
        params = [p for p in ref.parameters() if p.requires_grad]

        def step_ref():
            loss, _ = pib.loss(ref(x), A=A)
            torch.autograd.grad(loss, params)

        for p in unet.parameters():
            p.requires_grad_(True)
        uparams = list(unet.parameters())

        def step_unet():
            loss, _ = pib.loss(unet(x), A=A)
            torch.autograd.grad(loss, uparams)

        res["train_refiner_ms_per_sample"] = _lat(step_ref, 5, warm=1)["median_ms"] / 16
        res["train_unet_ms_per_sample"] = _lat(step_unet, 5, warm=1)["median_ms"] / 16
        for p in unet.parameters():
            p.requires_grad_(False)
        ref.eval()
    except Exception as exc:  # no dataset with stored operators here
        res["train_note"] = f"training cost not measured ({str(exc).splitlines()[0][:120]})"
    res["ratio_refiner_to_unet_batch1"] = res["refiner_batch1"]["median_ms"] / res["unet_batch1"]["median_ms"]
    res["goal_refiner_le_25ms"] = res["refiner_batch1"]["median_ms"] <= 25.0
    if a.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"refiner: {source}; K = {K}; {res['params_refiner']:,} step parameters (+ U-Net {res['params_unet']:,})")
    print(f"one CPU thread, batch 1: U-Net {res['unet_batch1']['median_ms']:.2f} ms, refiner "
          f"{res['refiner_batch1']['median_ms']:.2f} ms (p99 {res['refiner_batch1']['p99_ms']:.2f}; "
          f"{res['ratio_refiner_to_unet_batch1']:.2f}x the U-Net; goal <= 25 ms: "
          f"{'met' if res['goal_refiner_le_25ms'] else 'NOT met'})")
    print("  by K: " + ", ".join(f"K={k} {t:.2f} ms" for k, t in enumerate(res["refiner_batch1_by_k_ms"])))
    print(f"batch 8, per frame: U-Net {res['unet_batch8_per_frame_ms']:.2f} ms, refiner "
          f"{res['refiner_batch8_per_frame_ms']:.2f} ms")
    if "onnxruntime_refiner_batch1" in res:
        print(f"onnxruntime, one thread: refiner batch 1 {res['onnxruntime_refiner_batch1']['median_ms']:.2f} ms, "
              f"batch 8 {res['onnxruntime_refiner_batch8_per_frame_ms']:.2f} ms per frame")
    if "train_refiner_ms_per_sample" in res:
        print(f"training (PiB, stored operators, batch 16, one thread): refiner {res['train_refiner_ms_per_sample']:.1f} "
              f"ms/sample (U-Net frozen), U-Net step {res['train_unet_ms_per_sample']:.1f} ms/sample")
    else:
        print(res["train_note"])
    return 0


if __name__ == "__main__":
    sys.exit(main())

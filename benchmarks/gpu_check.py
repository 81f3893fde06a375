"""The accelerator check (issue #51): one short script (<= 8 min) for whatever CUDA device is present.

Batch-1 latency (median and p99 after warm-up, synchronised) of the committed robust U-Net, the learned
refinement and the real-time modal network, in fp32 and fp16 (autocast), eager and with CUDA graphs (a
static-shape capture replayed per frame; ``torch.compile`` when ``--compile``); the paper-scale U-Net (base
64, depth 5, 8 x 256 x 256 in) against the paper's 2.49 ms per inference on an RTX A6000; and the training
throughput (samples/s: forward, backward and an AdamW step of the paper-scale U-Net at batch 16, fp32 and
bf16 autocast; the network's share of a training step: the power-in-bucket loss's propagation is not in it).

Without a CUDA device it runs on the CPU at small size (``--small`` is implied: a base-8 paper-shape U-Net
on 64 x 64 inputs, a few runs) so that a test can run it; its figures then say "cpu" and are not the
accelerator's.  Results as JSON (``--json``) and, with ``-o DIR``, ``DIR/gpu_check.json``.

    python benchmarks/gpu_check.py [--runs 200] [--small] [--compile] [-o sensing/realtime-bench] [--json]
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

PAPER_MS = 2.49  # the paper's inference time per frame on an RTX A6000 (401.6 Hz)


def _lat(fn, runs: int, sync, warm: int = 10) -> dict:
    for _ in range(warm):
        fn()
    sync()
    ts = np.empty(runs)
    for i in range(runs):
        t = time.perf_counter()
        fn()
        sync()
        ts[i] = time.perf_counter() - t
    us = ts * 1e6
    return {"median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)), "max_us": float(us.max()),
            "runs": runs}


def _graph(model, x, dtype):
    """A CUDA graph of ``model(x)`` under ``dtype`` autocast: a replay per frame (static input buffer)."""
    import torch

    static = x.clone()
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s), torch.inference_mode(), torch.autocast("cuda", dtype=dtype, enabled=dtype != torch.float32):
        for _ in range(3):
            model(static)
    torch.cuda.current_stream().wait_stream(s)
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g), torch.inference_mode(), torch.autocast("cuda", dtype=dtype, enabled=dtype != torch.float32):
        model(static)
    return g.replay


def _models(small: bool, dev):
    """name -> (module, input size): the committed models (random weights where one is absent) and the
    paper-scale U-Net."""
    from metadesign.reconstruction.modal_net import ModalNet, ModalNetConfig
    from metadesign.reconstruction.model import UNetConfig, build_unet
    from metadesign.reconstruction.refine import load_network

    m = REPO / "sensing" / "models"
    out = {}
    for name, f in (("unet", "demo-unet-robust.safetensors"), ("refine", "demo-refine.safetensors"),
                    ("realtime", "realtime-w48.safetensors")):
        if (m / f).exists():
            net, _ = load_network(m / f, str(dev))
        elif name == "realtime":
            net = ModalNet(ModalNetConfig())
        else:
            continue
        cfg = net.unet.config if hasattr(net, "trajectory") else net.config
        out[name] = (net.to(dev).eval(), cfg.input_size)
    paper = UNetConfig(8, 8 if small else 64, 5, 64 if small else 256, 41)
    out["paper_unet"] = (build_unet(paper).to(dev).eval(), paper.input_size)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--small", action="store_true", help="small sizes and few runs (implied without CUDA)")
    ap.add_argument("--compile", action="store_true", help="also torch.compile (adds minutes of compilation)")
    ap.add_argument("-o", "--output", default=None)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    import torch

    cuda = torch.cuda.is_available()
    small = a.small or not cuda
    runs = 5 if small else a.runs
    if not cuda:
        torch.set_num_threads(1)
    dev = torch.device("cuda" if cuda else "cpu")
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    log = (lambda *x: print(*x, file=sys.stderr)) if a.json else print
    t_start = time.perf_counter()
    res = {"device": torch.cuda.get_device_name(0) if cuda else "cpu", "cuda": cuda, "small": small,
           "torch": torch.__version__, "paper_ms": PAPER_MS, "latency": {}}
    log(f"gpu_check on {res['device']}{' (small sizes: not an accelerator figure)' if small else ''}")
    dtypes = {"fp32": torch.float32, "fp16": torch.float16} if cuda else {"fp32": torch.float32}
    for name, (net, s) in _models(small, dev).items():
        x = torch.rand(1, 8, s, s, device=dev)
        x = 8 * x / x.sum()
        r = {}
        for dn, dt in dtypes.items():
            def eager(net=net, x=x, dt=dt):
                with torch.inference_mode(), torch.autocast(dev.type, dtype=dt, enabled=dt != torch.float32):
                    return net(x)
            r[f"{dn}_eager"] = _lat(eager, runs, sync)
            if cuda:
                try:
                    r[f"{dn}_cuda_graph"] = _lat(_graph(net, x, dt), runs, sync)
                except Exception as exc:  # noqa: BLE001 - a model that cannot be captured is a line in the report
                    r[f"{dn}_cuda_graph"] = {"error": str(exc).splitlines()[0][:160]}
            if a.compile:
                try:
                    comp = torch.compile(net)
                    t0 = time.perf_counter()
                    with torch.inference_mode():
                        comp(x)
                    r[f"{dn}_compile"] = {**_lat(lambda comp=comp, x=x: comp(x), runs, sync),
                                          "compile_s": time.perf_counter() - t0}
                except Exception as exc:  # noqa: BLE001
                    r[f"{dn}_compile"] = {"error": str(exc).splitlines()[0][:160]}
        best = min((v["median_us"] for v in r.values() if "median_us" in v), default=float("nan"))
        r["best_median_us"] = best
        res["latency"][name] = r
        log(f"  {name:11s} " + "  ".join(f"{k} {v['median_us']:.0f} us (p99 {v['p99_us']:.0f})" for k, v in r.items()
                                          if isinstance(v, dict) and "median_us" in v))
    p = res["latency"]["paper_unet"]["best_median_us"] / 1e3
    res["paper_unet_vs_paper"] = {"best_ms": p, "paper_ms": PAPER_MS, "speedup": PAPER_MS / p if p else None}
    log(f"  paper-scale U-Net: {p:.3f} ms per frame at batch 1 (paper: {PAPER_MS} ms on an RTX A6000)")
    res["training"] = _training(small, dev, sync, log)
    res["seconds"] = time.perf_counter() - t_start
    if a.output:
        from metadesign.io import atomic_write_text

        Path(a.output).mkdir(parents=True, exist_ok=True)
        atomic_write_text(Path(a.output) / "gpu_check.json", json.dumps(res, indent=1, sort_keys=True))
    if a.json:
        print(json.dumps(res, indent=1))
    return 0


def _training(small: bool, dev, sync, log) -> dict:
    """Samples/s of the paper-scale U-Net's training step (forward, backward, AdamW) at batch 16."""
    import torch

    from metadesign.reconstruction.model import UNetConfig, build_unet

    cfg = UNetConfig(8, 8 if small else 64, 5, 64 if small else 256, 41)
    net = build_unet(cfg).to(dev).train()
    torch.nn.init.normal_(net.head.weight, std=1e-2)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    b = 2 if small else 16
    x = torch.rand(b, 8, cfg.input_size, cfg.input_size, device=dev)
    target = torch.rand(b, 41, 41, device=dev)
    out = {"batch": b}
    kinds = {"fp32": torch.float32, "bf16": torch.bfloat16} if dev.type == "cuda" else {"fp32": torch.float32}
    for name, dt in kinds.items():
        def step(dt=dt):
            opt.zero_grad(set_to_none=True)
            with torch.autocast(dev.type, dtype=dt, enabled=dt != torch.float32):
                loss = ((net(x).float() - target) ** 2).mean()
            loss.backward()
            opt.step()
        lat = _lat(step, 3 if small else 30, sync, warm=2 if small else 5)
        out[name] = {"samples_per_s": b / (lat["median_us"] / 1e6), "step_ms": lat["median_us"] / 1e3}
        log(f"  training {name}: {out[name]['samples_per_s']:.1f} samples/s (batch {b})")
    return out


if __name__ == "__main__":
    sys.exit(main())

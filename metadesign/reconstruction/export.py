"""Deployment export: the U-Net as ONNX (dynamic batch axis), checked against torch in onnxruntime."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

__all__ = ["export_onnx", "onnx_parity"]


def export_onnx(model_path: str | Path, out: str | Path, opset: int = 17) -> dict:
    """Write ``out`` (atomically) from the safetensors model; returns the parity check on random inputs."""
    import torch

    from ..io import atomic_path
    from .model import load_model

    model, card = load_model(model_path)
    s = model.config.input_size
    x = torch.randn(2, 8, s, s)
    with atomic_path(out) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (x,), str(tmp), input_names=["psf"], output_names=["phase"],
                          dynamic_axes={"psf": {0: "batch"}, "phase": {0: "batch"}}, opset_version=opset,
                          dynamo=False)
    return {"file": str(out), "bytes": Path(out).stat().st_size, "opset": opset,
            "input": ["batch", 8, s, s], "output": ["batch", model.config.aperture_size, model.config.aperture_size],
            **onnx_parity(model, out)}


def onnx_parity(model, onnx_path, batches=(1, 3), seed: int = 0) -> dict:
    """Largest absolute difference between torch and onnxruntime outputs on random inputs (several batch
    sizes: the batch axis is dynamic)."""
    import onnxruntime as ort
    import torch

    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    s = model.config.input_size
    worst = 0.0
    for b in batches:
        x = rng.random((b, 8, s, s), dtype=np.float32)
        with torch.no_grad():
            ref = model(torch.from_numpy(x)).numpy()
        got = sess.run(None, {"psf": x})[0]
        worst = max(worst, float(np.abs(ref - got).max()))
    return {"max_abs_diff": worst, "batches": list(batches)}

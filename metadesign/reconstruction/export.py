"""Deployment export: the U-Net as ONNX (dynamic batch axis), checked against torch in onnxruntime."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..io import atomic_path
from ..validation import ValidationError
from .model import load_model

__all__ = ["export_onnx", "onnx_parity", "PARITY_TOL"]

#: largest |torch - onnxruntime| (rad) an export may show on random inputs (measured: 6e-6)
PARITY_TOL = 1e-3


def export_onnx(model_path: str | Path, out: str | Path, opset: int = 17) -> dict:
    """Write ``out`` (atomically) from the safetensors model; returns the parity check on random inputs."""
    import torch

    model, card = load_model(model_path)
    s = model.config.input_size
    x = torch.randn(2, 8, s, s)
    with atomic_path(out) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (x,), str(tmp), input_names=["psf"], output_names=["phase"],
                          dynamic_axes={"psf": {0: "batch"}, "phase": {0: "batch"}}, opset_version=opset,
                          dynamo=False)
    parity = onnx_parity(model, out)
    if not np.isfinite(parity["max_abs_diff"]) or parity["max_abs_diff"] > PARITY_TOL:
        Path(out).unlink(missing_ok=True)
        raise ValidationError(f"{out}: onnxruntime output differs from torch by {parity['max_abs_diff']:.3g} rad "
                              f"(tolerance {PARITY_TOL:g}); the export was removed")
    return {"file": str(out), "bytes": Path(out).stat().st_size, "opset": opset,
            "input": ["batch", 8, s, s], "output": ["batch", model.config.aperture_size, model.config.aperture_size],
            **parity}


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
        diff = float(np.abs(ref - got).max())  # NaN-aware: max(0, nan) would be 0
        worst = diff if not np.isfinite(diff) else max(worst, diff)
        if not np.isfinite(worst):
            break
    return {"max_abs_diff": worst, "batches": list(batches)}

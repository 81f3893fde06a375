"""Deployment export: the U-Net, or the refiner (U-Net + unrolled steps through the real-arithmetic twin
with its explicit adjoint: one feed-forward graph), as ONNX (dynamic batch axis), checked against torch
in onnxruntime."""

from __future__ import annotations

import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import __version__
from ..io import atomic_path
from ..validation import ValidationError
from .refine import load_network

__all__ = ["export_onnx", "onnx_parity", "contract", "PARITY_TOL"]

#: largest |torch - onnxruntime| (rad) an export may show on random inputs (measured: 6e-6)
PARITY_TOL = 1e-3


def export_onnx(model_path: str | Path, out: str | Path, opset: int = 17) -> dict:
    """Write ``out`` (atomically) from the safetensors model, with its preprocessing contract as ONNX
    metadata (:func:`contract`); returns the parity check on random inputs.  An export whose onnxruntime
    output is off (or NaN) is never written."""
    import json

    import onnx
    import torch

    model, card = load_network(model_path)
    s = model.config.input_size
    x = torch.randn(2, 8, s, s)
    meta = contract(model, card)
    with atomic_path(out) as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(model, (x,), str(tmp), input_names=["psf"], output_names=["phase"],
                              dynamic_axes={"psf": {0: "batch"}, "phase": {0: "batch"}}, opset_version=opset,
                              dynamo=False)
        m = onnx.load(str(tmp))
        for k, v in meta.items():
            m.metadata_props.add(key=k, value=v if isinstance(v, str) else json.dumps(v, sort_keys=True))
        m.doc_string = ("metadesign " + ("U-Net + learned refinement" if "refine" in card else "U-Net") +
                        ": 8 PSFs of a birefringent metasurface -> received phase (rad)")
        onnx.save(m, str(tmp))
        parity = onnx_parity(model, tmp)
        if not np.isfinite(parity["max_abs_diff"]) or parity["max_abs_diff"] > PARITY_TOL:
            raise ValidationError(f"{out}: onnxruntime output differs from torch by {parity['max_abs_diff']:.3g} "
                                  f"rad (tolerance {PARITY_TOL:g}); nothing written")
    return {"file": str(out), "bytes": Path(out).stat().st_size, "opset": opset,
            "input": ["batch", 8, s, s], "output": ["batch", model.config.aperture_size, model.config.aperture_size],
            "metadata": sorted(meta), **parity}


def contract(model, card: dict) -> dict:
    """The preprocessing contract a deployment needs, as ONNX metadata (strings; JSON where structured):
    what the input tensor is and how it is normalised, the channel order, the output's grid, sampling and
    units, and where the weights came from."""
    c = model.config
    crop = card.get("received_crop") or {}
    return {
        "metadesign.format": "metadesign.onnx/1",
        "metadesign.input": {"name": "psf", "shape": ["batch", 8, c.input_size, c.input_size], "dtype": "float32",
                             "channels": ["x-pol QI", "x-pol QII", "x-pol QIII", "x-pol QIV",
                                          "y-pol QI", "y-pol QII", "y-pol QIII", "y-pol QIV"],
                             "normalisation": card.get("input_normalisation")
                             or "each sample's 8 channels sum to 8",
                             "resampling": "each sensor quadrant area-resampled to S x S pixels (power conserved)",
                             "training_noise_percent": card.get("noise_percent")},
        "metadesign.output": {"name": "phase", "shape": ["batch", c.aperture_size, c.aperture_size],
                              "units": "rad", "dtype": "float32",
                              "meaning": card.get("output") or "received phase on the receiver-aperture crop",
                              "grid": {"size": c.aperture_size, "pitch_m": crop.get("dx_m"),
                                       "start": crop.get("start"), "n_grid": crop.get("n_grid"),
                                       "centring": crop.get("centring")},
                              "outside_aperture": "0"},
        "metadesign.architecture": card.get("architecture") or asdict(c),
        **({"metadesign.refine": {**card["refine"], "unet_sha256": card["unet"]["weights_sha256"]}}
           if "refine" in card else {}),
        "metadesign.weights_sha256": card.get("weights_sha256") or "",
        "metadesign.version": __version__,
    }


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

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
from ..sensing.device import Device
from ..sensing.sensor import CHANNELS, QUADRANTS, quadrant_slices
from ..validation import ValidationError
from .captures import spot_centroids
from .dataset_store import load_device, open_dataset
from .model import check_sizes
from .refine import load_network

__all__ = ["export_onnx", "onnx_parity", "contract", "PARITY_TOL"]

#: largest |torch - onnxruntime| (rad) an export may show on random inputs (measured: 6e-6)
PARITY_TOL = 1e-3


def export_onnx(model_path: str | Path, out: str | Path, opset: int = 17, dataset: str | Path | None = None) -> dict:
    """Write ``out`` (atomically) from the safetensors model, with its deployment contract as ONNX metadata
    (:func:`contract`; with ``dataset``, the one the model was trained on, the camera and device blocks a
    lab needs to turn raw frames into the input); returns the parity check on random inputs.  An export
    whose onnxruntime output is off (or NaN) is never written."""
    import json

    import onnx
    import torch

    model, card = load_network(model_path)
    s = model.config.input_size
    x = torch.randn(2, 8, s, s)
    dev = None
    if dataset is not None:
        dev = load_device(dataset)
        check_sizes(model.config, dev.sensor.tensor_size, dev.crop.size, f"model {model_path} on {dataset}")
    meta = contract(model, card, dev, open_dataset(dataset).attrs if dataset is not None else None)
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
    return {"file": str(out), "bytes": Path(out).stat().st_size, "opset": opset, "camera": dev is not None,
            "input": ["batch", 8, s, s], "output": ["batch", model.config.aperture_size, model.config.aperture_size],
            "metadata": sorted(meta), **parity}


def camera_contract(dev) -> dict:
    """Everything that turns two raw camera frames into the model's input tensor, for the sensor of device
    ``dev``: the frame geometry, the quadrant windows, the row and column orientation, the polarisation
    of each frame, the steps, and the flat-wavefront spot centroids a lab checks its orientation with."""
    sen = dev.sensor
    windows = {}
    for k, q in enumerate(QUADRANTS, 1):
        r, c = quadrant_slices(sen, k)
        windows[q] = {"rows": [r.start, r.stop], "cols": [c.start, c.stop]}
    flat = Device(dev.pupil, sen).frames()
    cen = spot_centroids(flat, sen)
    return {
        "frames": ["x-pol", "y-pol"],
        "frame_px": {"width": sen.width_px, "height": sen.height_px},
        "pixel_pitch_m": sen.pixel_pitch, "relay_magnification": sen.magnification,
        "orientation": "array[row, col] with the row index increasing with the metasurface's y and the column "
                       "index with its x (row 0 at y = -(height - 1) / 2 pixels): QI and QII are the first "
                       "half of the rows. A frame read top-down where the camera counts bottom-up is flipped: "
                       "check with flat_spot_centroids_px",
        "quadrant_windows": windows,
        "channels": list(CHANNELS),
        "flat_spot_centroids_px": {ch: [round(float(x), 3), round(float(y), 3)] for ch, (x, y) in zip(CHANNELS, cen)},
        "flat_spot_centroids_meaning": "(col, row) of each spot's thresholded centre of gravity (10 % of its "
                                       "quadrant's peak) for a flat wavefront: a capture's centroids within a "
                                       "few pixels of these means the frames are oriented and aligned",
        "steps": ["subtract the mean dark frame (counts) from each frame; no flat-field (the normalisation "
                  "removes a common gain); replace hot pixels by their neighbours' median",
                  "channel 4 p + k - 1 = quadrant window k (QI..QIV) of frame p (x-pol, y-pol)",
                  "area-resample each window to S x S: output pixel i covers input pixels [i, i + 1) n / S along "
                  "each axis, weighted by overlap (every input pixel's power lands once)",
                  "divide the 8 channels by their common total and multiply by 8 (the channels sum to 8)",
                  "float32, shape (batch, 8, S, S), input name 'psf'"],
        "tensor_size": sen.tensor_size,
        "sensor_distance_m": sen.distance,
    }


def contract(model, card: dict, dev=None, attrs: dict | None = None) -> dict:
    """The deployment contract, as ONNX metadata (strings; JSON where structured): what the input tensor is
    and how a raw camera frame becomes it (with ``dev``: the camera geometry, quadrant windows, orientation,
    steps, flat-spot centroids), the output's grid, sampling and units and how it becomes an SLM command,
    the wavelength, the training noise with its unit, and the device and weights it belongs to."""
    c = model.config
    crop = card.get("received_crop") or (attrs or {}).get("received_crop") or {}
    prov = (attrs or {}).get("provenance") or {}
    noise = card.get("noise") or {}
    extra = {}
    if dev is not None:
        extra["metadesign.camera"] = camera_contract(dev)
        extra["metadesign.wavelength_m"] = dev.wavelength
        extra["metadesign.device"] = {"layout_sha256": prov.get("layout_sha256"),
                                      "library_sha256": prov.get("library_sha256"),
                                      "design": prov.get("design"), "perturbation": prov.get("perturbation"),
                                      "dataset_recipe_hash": attrs.get("recipe_hash") if attrs else None}
    return {
        **extra,
        "metadesign.slm_command": {"phase_rad": "-phase (the conjugate of the received phase) on the output grid, "
                                                "0 outside the aperture; add the optics' own focusing phase",
                                   "grid": "metadesign.output.grid"},
        "metadesign.training_noise": {**noise, "unit": "gaussian_percent: % of each channel's peak; "
                                                       "photons_at_peak: photo-electrons at each channel's peak"},
        "metadesign.trained_for": (card.get("dataset") or card.get("trained_on") or {}),
        "metadesign.format": "metadesign.onnx/1",
        "metadesign.input": {"name": "psf", "shape": ["batch", 8, c.input_size, c.input_size], "dtype": "float32",
                             "channels": list(CHANNELS),
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

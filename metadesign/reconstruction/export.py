"""Deployment export: the U-Net, or the refiner (U-Net + unrolled steps through the real-arithmetic twin
with its explicit adjoint: one feed-forward graph), as ONNX (dynamic batch axis), checked against torch
in onnxruntime, with the complete deployment contract as its metadata (issue #52): everything a lab needs
with nothing but numpy and onnxruntime, the camera (frame, pitch, the relay's signed magnification, the
orientation, each channel's polarisation and focal length, the flat-frame calibration signature), the
wavelength and the device's identity, from the model's dataset or, without it, from the committed dataset
recipe its card names (:mod:`.contract_device`)."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .. import __version__
from ..io import atomic_path
from ..sensing.device import Device
from ..sensing.orientation import ORIENTATIONS, signature_record
from ..sensing.sensor import CHANNELS, QUADRANTS, quadrant_slices
from ..validation import ValidationError
from .contract_device import ContractDevice, contract_device
from .model import check_sizes
from .refine import load_network

__all__ = ["PARITY_TOL", "camera_contract", "contract", "export_onnx", "onnx_parity"]

#: largest |torch - onnxruntime| (rad) an export may show on random inputs (measured: 6e-6)
PARITY_TOL = 1e-3


def export_onnx(model_path: str | Path, out: str | Path, opset: int = 17, dataset: str | Path | None = None,
                log: Callable[[str], None] = lambda s: None, require_device: bool = True) -> dict:
    """Write ``out`` (atomically) from the safetensors model, with its deployment contract as ONNX metadata
    (:func:`contract`); returns the parity check on random inputs and where the device came from.  The
    device: ``dataset`` (the one the model was trained on: its recipe hash and layout must be the card's), else
    the committed dataset recipe the card names (:func:`~.contract_device.contract_device`).
    ``require_device=False``: a card that names no dataset gives a contract without the camera and device
    (the network alone; the stand-alone example refuses such a file).  An export whose onnxruntime output is
    off (or NaN) is never written."""
    import json

    import onnx
    import torch

    model, card = load_network(model_path)
    s = model.config.input_size
    x = torch.randn(2, 8, s, s)
    cd = None
    if dataset is not None or require_device or (card.get("dataset") or card.get("trained_on") or {}).get("path"):
        cd = contract_device(model_path, card, dataset, log)
        check_sizes(model.config, cd.device.sensor.tensor_size, cd.device.crop.size,
                    f"model {model_path} on {dataset or cd.source}")
    meta = contract(model, card, cd)
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
    sig = meta.get("metadesign.camera", {}).get("calibration_signature", {})
    return {"file": str(out), "bytes": Path(out).stat().st_size, "opset": opset, "camera": cd is not None,
            "device": meta.get("metadesign.device"), "device_source": cd.source if cd is not None else None,
            "signature_symmetric": sig.get("symmetric"),
            "input": ["batch", 8, s, s], "output": ["batch", model.config.aperture_size, model.config.aperture_size],
            "metadata": sorted(meta), **parity}


def _g(x: float) -> float:
    """A float to 12 significant digits (a dataset's stored sensor and a recipe's agree to these)."""
    return float(f"{float(x):.12g}")


def camera_contract(cd: ContractDevice) -> dict:
    """Everything that turns two raw camera frames into the model's input tensor, for the device of ``cd``:
    the frame geometry, the relay's signed magnification, the orientation and the orientations a lab may
    declare, the quadrant windows, each channel's polarisation and focal length (its defocus), the flat-frame
    calibration signature (:mod:`metadesign.sensing.orientation`) the frames are checked against, and the
    steps."""
    dev = cd.device
    sen = dev.sensor
    windows = {}
    for k, q in enumerate(QUADRANTS, 1):
        r, c = quadrant_slices(sen, k)
        windows[q] = {"rows": [r.start, r.stop], "cols": [c.start, c.stop]}
    flat = Device(dev.pupil, sen).frames()
    optics = []
    for i, ch in enumerate(CHANNELS):
        p, k = divmod(i, 4)
        f, ox, oy = (float(v) for v in cd.lenses[p, k])
        optics.append({"channel": ch, "polarisation": "xy"[p], "quadrant": QUADRANTS[k], "focal_length_m": _g(f),
                       "defocus_m": _g(f - sen.distance), "spot_offset_m": [_g(ox), _g(oy)]})
    return {
        "frames": ["x-pol", "y-pol"],
        "frame_px": {"width": sen.width_px, "height": sen.height_px},
        "pixel_pitch_m": _g(sen.pixel_pitch), "relay_magnification": _g(sen.magnification),
        "relay_magnification_meaning": "signed: positive is an erect image (what the orientation below defines); "
                                       "a relay with a negative magnification (one inverting stage) delivers "
                                       "frames rotated by 180 degrees: declare the orientation rot180",
        "orientation": "array[row, col] with the row index increasing with the metasurface's y and the column "
                       "index with its x (row 0 at y = -(height - 1) / 2 pixels): QI and QII are the first "
                       "half of the rows, x-pol frame first. Frames that arrive otherwise (read bottom-up, "
                       "through an inverting relay, mirrored, with the polarisation frames swapped) are put back "
                       "as the declared orientation says before anything else; calibration_signature tells "
                       "which one a flat frame is in",
        "orientations": list(ORIENTATIONS),
        "orientations_meaning": "what a lab may declare: the frames as they arrive are the contract's turned by "
                                "it (flip-ud: rows reversed; rot180: both axes; swap-pol+...: the x-pol and y-pol "
                                "frames exchanged as well); putting them back applies its inverse",
        "quadrant_windows": windows,
        "channels": list(CHANNELS),
        "channel_optics": optics,
        "channel_optics_meaning": "per channel: the polarisation of its frame, its quadrant, the focal length of "
                                  "its lens (defocus_m: focal length - sensor distance; the diversity ladder), "
                                  "and the spot's offset on the focal plane (m)",
        "calibration_signature": signature_record(flat),
        "calibration": "a flat-wavefront capture (a collimated beam filling the aperture; darks subtracted, "
                       "frames averaged) is compared with calibration_signature in every orientation (its "
                       "meaning says how): refused when it matches another orientation than the declared one, or "
                       "none; then the spots' shift (px) and scale are measured and the quadrant windows follow "
                       "them",
        "steps": ["put the frames back in the contract's orientation (the declared one's inverse)",
                  ("subtract the mean dark frame (counts) from each frame; no flat-field (the normalisation "
                   "removes a common gain); replace hot pixels by their neighbours' median"),
                  ("channel 4 p + k - 1 = quadrant window k (QI..QIV) of frame p (x-pol, y-pol), the windows "
                   "moved by the flat frame's measured shift and scaled about the frame centre by its scale"),
                  ("area-resample each window to S x S: output pixel i covers input pixels [i, i + 1) n / S along "
                   "each axis, weighted by overlap (every input pixel's power lands once)"),
                  "divide the 8 channels by their common total and multiply by 8 (the channels sum to 8)",
                  "float32, shape (batch, 8, S, S), input name 'psf'"],
        "tensor_size": sen.tensor_size,
        "sensor_distance_m": _g(sen.distance),
    }


def _crop_record(card: dict, cd: ContractDevice | None) -> dict:
    if card.get("received_crop"):
        return card["received_crop"]
    if cd is None or cd.device.crop is None:
        return {}
    c = cd.device.crop
    return {"start": c.start, "size": c.size, "n_grid": c.n_grid, "dx_m": c.dx,
            "centring": "FFT-centred grid: x = (i - n/2) dx; crop rows/cols start..start+size"}


def contract(model, card: dict, cd: ContractDevice | None = None) -> dict:
    """The deployment contract, as ONNX metadata (strings; JSON where structured): what the input tensor is
    and how two raw camera frames become it (with the device ``cd``: the camera block of
    :func:`camera_contract`, the wavelength, the device's identity), the output's grid, sampling and units and
    how it becomes an SLM command, the training noise with its unit, and the weights it belongs to."""
    c = model.config
    crop = _crop_record(card, cd)
    noise = card.get("noise") or {}
    extra = {}
    if cd is not None:
        extra["metadesign.camera"] = camera_contract(cd)
        extra["metadesign.wavelength_m"] = _g(cd.device.wavelength)
        extra["metadesign.device"] = cd.identity
    return {
        **extra,
        "metadesign.slm_command": {"phase_rad": "-phase (the conjugate of the received phase) on the output grid, "
                                                "0 outside the aperture; add the optics' own focusing phase",
                                   "grid": "metadesign.output.grid"},
        "metadesign.training_noise": {**noise, "unit": "gaussian_percent: % of each channel's peak; "
                                                       "photons_at_peak: photo-electrons at each channel's peak"},
        "metadesign.trained_for": (card.get("dataset") or card.get("trained_on") or {}),
        "metadesign.format": "metadesign.onnx/2",
        "metadesign.input": {"name": "psf", "shape": ["batch", 8, c.input_size, c.input_size], "dtype": "float32",
                             "channels": list(CHANNELS),
                             "normalisation": card.get("input_normalisation")
                             or "each sample's 8 channels sum to 8",
                             "resampling": "each sensor quadrant area-resampled to S x S pixels (power conserved)",
                             "training_noise_percent": card.get("noise_percent"),
                             **({"window": {"size": c.window, "offset": (c.input_size - c.window) // 2,
                                            "meaning": "the network reads only rows and columns offset.."
                                                       "offset+size-1 of each channel, renormalised to sum 8 over "
                                                       "the 8 channels: the camera stage may compute only that "
                                                       "square (metadesign.sensing.sensor.FrameTensor window) and "
                                                       "leave the rest 0; the normalisation above does not matter"}}
                                if getattr(c, "window", 0) else {})},
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

"""Reconstruct the received phase from two raw camera frames with onnxruntime alone.

No torch and no metadesign: everything needed to turn the frames into the model's input is in the ONNX
file's metadata (``metadesign export MODEL -o model.onnx --dataset DATASET`` writes it): the camera
geometry, the quadrant windows, the orientation, the steps, and the flat-wavefront spot centroids to
check the orientation with.

    python examples/deploy_onnx.py model.onnx frame_x.fits frame_y.fits [--dark dark.fits] [-o phase.npy]

Requires numpy, onnxruntime and (for FITS frames) astropy.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import onnxruntime as ort


def load(onnx_path: str) -> tuple[ort.InferenceSession, dict]:
    """The session and the deployment contract (the metadata, JSON decoded)."""
    sess = ort.InferenceSession(onnx_path, providers=["CPUExecutionProvider"])
    meta = {}
    for k, v in sess.get_modelmeta().custom_metadata_map.items():
        try:
            meta[k] = json.loads(v)
        except ValueError:
            meta[k] = v
    if "metadesign.camera" not in meta:
        raise SystemExit(f"{onnx_path}: no camera contract (export it with --dataset)")
    return sess, meta


def area_weights(n_in: int, n_out: int) -> np.ndarray:
    """Output pixel i covers input pixels [i, i + 1) n_in / n_out, weighted by overlap."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    j = np.arange(n_in)[None, :]
    return np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0.0, None)


def input_tensor(frames: list[np.ndarray], camera: dict, dark: np.ndarray | None = None) -> np.ndarray:
    """Two frames [x-pol, y-pol] (height, width) -> the (1, 8, S, S) float32 input, following the steps."""
    S = int(camera["tensor_size"])
    out = np.empty((8, S, S), np.float32)
    for p, frame in enumerate(frames):
        f = np.asarray(frame, np.float64)
        if f.shape != (camera["frame_px"]["height"], camera["frame_px"]["width"]):
            raise SystemExit(f"frame {p}: {f.shape[::-1]} pixels, the camera has "
                             f"{camera['frame_px']['width']} x {camera['frame_px']['height']}")
        if dark is not None:
            f = f - dark
        for k, q in enumerate(("QI", "QII", "QIII", "QIV")):
            w = camera["quadrant_windows"][q]
            win = f[w["rows"][0]:w["rows"][1], w["cols"][0]:w["cols"][1]]
            ry, rx = area_weights(win.shape[0], S), area_weights(win.shape[1], S)
            out[4 * p + k] = (ry @ win @ rx.T).astype(np.float32)
    return (out * (8.0 / out.sum(dtype=np.float64))).astype(np.float32)[None]


def reconstruct(onnx_path: str, frames: list[np.ndarray], dark: np.ndarray | None = None) -> np.ndarray:
    """The received phase (rad) on the contract's output grid; the SLM command is its negative."""
    sess, meta = load(onnx_path)
    x = input_tensor(frames, meta["metadesign.camera"], dark)
    return sess.run(None, {"psf": x})[0][0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("onnx")
    ap.add_argument("frame_x")
    ap.add_argument("frame_y")
    ap.add_argument("--dark")
    ap.add_argument("-o", "--output", default="phase.npy")
    a = ap.parse_args()
    from astropy.io import fits

    frames = [np.asarray(fits.getdata(f), np.float64) for f in (a.frame_x, a.frame_y)]
    dark = np.asarray(fits.getdata(a.dark), np.float64) if a.dark else None
    phi = reconstruct(a.onnx, frames, dark)
    np.save(a.output, phi)
    print(f"wrote {a.output}: received phase {phi.shape}, rms {phi[phi != 0].std():.3f} rad; SLM command: -phase")


if __name__ == "__main__":
    main()

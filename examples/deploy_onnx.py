"""Reconstruct the received phase from two raw camera frames with onnxruntime alone.

No torch and no metadesign: everything needed to turn the frames into the model's input is in the ONNX
file's metadata (``metadesign export MODEL -o model.onnx`` writes it): the camera geometry, the relay, the
quadrant windows, the orientation, each channel's polarisation and focal length, the steps, and the
flat-wavefront calibration signature.  A flat-wavefront capture is required: it is checked against the
signature in every orientation (a frame flipped up-down, rotated by 180 degrees by an inverting relay,
mirrored, or with its polarisation frames swapped is refused in one line naming what is wrong, unless
``--orientation`` declares it, when every frame is put back first), and the spots' shift and scale on it
move the quadrant windows.

    python examples/deploy_onnx.py model.onnx frame_x.fits frame_y.fits --flat flat_x.fits flat_y.fits \\
        [--orientation flip-ud] [--dark dark.fits] [-o phase.npy]

Requires numpy, onnxruntime and (for FITS frames) astropy.  The signature kernel below is a copy of
``metadesign.sensing.orientation`` (a test holds the two equal).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import onnxruntime as ort

# ----------------------------------------------------------------------------- orientations
GEOMETRY = {
    "identity": lambda f: f,
    "flip-ud": lambda f: f[..., ::-1, :],
    "flip-lr": lambda f: f[..., :, ::-1],
    "rot180": lambda f: f[..., ::-1, ::-1],
    "transpose": lambda f: np.swapaxes(f, -1, -2),
    "rot90": lambda f: np.rot90(f, 1, axes=(-2, -1)),
    "rot270": lambda f: np.rot90(f, -1, axes=(-2, -1)),
    "anti-transpose": lambda f: np.rot90(np.swapaxes(f, -1, -2), 2, axes=(-2, -1)),
}
INVERSE = {"rot90": "rot270", "rot270": "rot90"}
WORDS = {"identity": "as the contract says", "flip-ud": "flipped up-down (a relay that inverts the rows?)",
         "flip-lr": "mirrored left-right (a relay that inverts the columns?)",
         "rot180": "rotated by 180 degrees (a single relay inverts the image?)",
         "transpose": "transposed (rows and columns exchanged)", "rot90": "rotated by 90 degrees (counter-clockwise)",
         "rot270": "rotated by 90 degrees (clockwise)", "anti-transpose": "transposed about the anti-diagonal"}
TURNED = ("transpose", "rot90", "rot270", "anti-transpose")
ORIENTATIONS = tuple(list(GEOMETRY) + ["swap-pol" if g == "identity" else f"swap-pol+{g}" for g in GEOMETRY])


def split(name: str) -> tuple[bool, str]:
    swap = name.startswith("swap-pol")
    return swap, (name[len("swap-pol+"):] if "+" in name else ("identity" if swap else name))


def describe(name: str) -> str:
    swap, geo = split(name)
    if swap:
        return "its two polarisation frames are swapped" + ("" if geo == "identity" else " and it is " + WORDS[geo])
    return "it is " + WORDS[geo]


def orient(frames: np.ndarray, name: str) -> np.ndarray:
    swap, geo = split(name)
    f = GEOMETRY[geo](np.asarray(frames))
    return np.ascontiguousarray(f[::-1] if swap else f)


def correct(frames: np.ndarray, name: str) -> np.ndarray:
    """Frames that arrived in orientation ``name`` put back in the contract's orientation."""
    swap, geo = split(name)
    f = np.asarray(frames)
    return np.ascontiguousarray(GEOMETRY[INVERSE.get(geo, geo)](f[::-1] if swap else f))


def relative(declared: str, candidate: str) -> str:
    lab = np.arange(18).reshape(2, 3, 3)
    g = correct(orient(lab, declared), candidate)
    return next(n for n in ORIENTATIONS if np.array_equal(orient(lab, n), g))


# ----------------------------------------------------------------------------- the calibration signature
def windows(shape):
    h2, w2 = shape[0] // 2, shape[1] // 2
    for k in range(4):
        yield (slice(0, h2) if k < 2 else slice(h2, shape[0])), (slice(0, w2) if k % 2 == 0 else slice(w2, shape[1]))


def integral(a: np.ndarray) -> np.ndarray:
    c = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    c[1:, 1:] = a.cumsum(0).cumsum(1)
    return c


def box_sums(c: np.ndarray, n: int) -> np.ndarray:
    n = int(min(n, c.shape[0] - 1, c.shape[1] - 1))
    return c[n:, n:] - c[:-n, n:] - c[n:, :-n] + c[:-n, :-n]


def frame_noise(frame: np.ndarray) -> float:
    d = np.diff(np.asarray(frame, np.float64), axis=-1)
    mad = np.median(np.abs(d - np.median(d)))
    return float((1.4826 * mad if mad > 0 else np.sqrt(np.mean(d**2))) / np.sqrt(2))


def moments(w, yy, xx):
    s = w.sum()
    if not s > 0:
        return None
    cx, cy = (w * xx).sum() / s, (w * yy).sum() / s
    return cx, cy, (w * (xx - cx) ** 2).sum() / s, (w * (yy - cy) ** 2).sum() / s


def signature(frames: np.ndarray, prm: dict) -> np.ndarray:
    """(8, 3 + 2 B) per channel: centroid offset (dx, dy) and size (px), log ensquared energies, their errors."""
    f = np.asarray(frames, np.float64)
    b, thr, boxes = int(prm["smooth_px"]), float(prm["threshold"]), [int(n) for n in prm["boxes_px"]]
    out = np.zeros((8, 3 + 2 * len(boxes)))
    for p in range(2):
        sigma = frame_noise(f[p])
        for k, (r, c) in enumerate(windows(f.shape[-2:])):
            win = f[p][r, c] - np.median(f[p][r, c])
            ii = integral(win)
            ee = np.array([max(box_sums(ii, n).max(), 1e-300) for n in boxes])
            out[4 * p + k, 3:] = np.r_[np.log(ee), sigma * np.asarray(boxes) / ee]
            q = box_sums(integral(np.pad(win, b // 2)), b) / (b * b)
            w = np.clip(q - thr * q.max(), 0.0, None)
            yy, xx = np.indices(w.shape, dtype=np.float64)
            m = moments(w, yy, xx)
            if m is None:
                continue
            for _ in range(2):
                rad = 2.5 * np.sqrt(m[2] + m[3]) + 2.0
                m = moments(np.where((xx - m[0]) ** 2 + (yy - m[1]) ** 2 <= rad * rad, w, 0.0), yy, xx) or m
            out[4 * p + k, :3] = (m[0] - (w.shape[1] - 1) / 2, m[1] - (w.shape[0] - 1) / 2, np.sqrt(m[2] + m[3]))
    return out


def chi2(sig: np.ndarray, ref: np.ndarray, floor: float) -> float:
    nb = (sig.shape[1] - 3) // 2
    d = sig[:, 3:3 + nb] - ref[:, 3:3 + nb]
    w = 1.0 / (sig[:, 3 + nb:] ** 2 + ref[:, 3 + nb:] ** 2 + floor**2)
    d = d - (w * d).sum(axis=1, keepdims=True) / w.sum(axis=1, keepdims=True)
    return float((d**2 * w).sum() / (d.shape[0] * (nb - 1)))


def centres(sig: np.ndarray, shape) -> np.ndarray:
    out = np.empty((8, 2))
    for p in range(2):
        for k, (r, c) in enumerate(windows(shape)):
            out[4 * p + k] = (sig[4 * p + k, 0] + (c.start + c.stop - 1) / 2 - (shape[1] - 1) / 2,
                              sig[4 * p + k, 1] + (r.start + r.stop - 1) / 2 - (shape[0] - 1) / 2)
    return out


def diagnose(flat: np.ndarray, rec: dict, declared: str = "identity") -> dict:
    """Which orientation the flat frames (2, H, W) arrived in against the signature record, whether that is
    the declared one (``problem``: the one line that refuses them), and the spots' shift and scale."""
    nb = len(rec["boxes_px"])
    prm = {k: rec[k] for k in ("smooth_px", "threshold", "boxes_px")}
    exp = np.concatenate([np.asarray(rec["channels"], np.float64), np.zeros((8, nb))], axis=1)
    shape = (rec["frame_px"]["height"], rec["frame_px"]["width"])
    f = np.asarray(flat, np.float64)
    names = [n for n in ORIENTATIONS if (f.shape[-2:][::-1] if split(n)[1] in TURNED else f.shape[-2:]) == shape]
    if not names:
        raise SystemExit(f"flat frame of {f.shape[-1]} x {f.shape[-2]} pixels: the camera has {shape[1]} x {shape[0]}")
    scores = sorted(((chi2(signature(correct(f, n), prm), exp, rec["floor"]), n) for n in names), key=lambda t: t[0])
    (c0, best), (c1, second) = scores[0], scores[1]
    matching = [n for c, n in scores if c <= rec["chi2_max"]]
    sym = set(rec.get("symmetric", ()))

    def consistent(a):
        return all(m == a or relative(a, m) in sym for m in matching)

    problem = None
    if not matching:
        problem = (f"the flat frame does not match the device's calibration signature in any orientation (closest "
                   f"{best}, chi2 {c0:.3g} > {rec['chi2_max']:g}): another device, sensor or relay, or not a "
                   "flat-wavefront frame")
    elif not (declared in matching and consistent(declared)):
        if not consistent(best):
            problem = (f"the flat frame's orientation is ambiguous ({best} chi2 {c0:.3g}, {second} {c1:.3g}): "
                       "average more flat frames")
        elif declared == "identity":
            problem = f"frame orientation: {describe(best)}: pass --orientation {best}"
        else:
            problem = f"frame orientation: declared {declared}, but {describe(best)} (pass --orientation {best})"
    # the spots' similarity (shift, scale) once the declared orientation is undone; weights 1 / size^4
    sig = signature(correct(f, declared if declared in names else best), prm)
    ref, meas = centres(exp, shape), centres(sig, shape)
    w = 1.0 / np.maximum(exp[:, 2], 1.0) ** 4
    w = w / w.sum()
    rm, mm = (w[:, None] * ref).sum(0), (w[:, None] * meas).sum(0)
    s = float((w[:, None] * (ref - rm) * (meas - mm)).sum() / (w[:, None] * (ref - rm) ** 2).sum())
    t = mm - s * rm
    return {"best": best, "chi2": c0, "runner_up": second, "runner_up_chi2": c1, "problem": problem,
            "shift_px": (float(t[0]), float(t[1])), "scale": s}


# ----------------------------------------------------------------------------- the model and its input
def load(onnx_path: str) -> tuple[ort.InferenceSession, dict]:
    """The session and the deployment contract (the metadata, JSON decoded)."""
    sess = ort.InferenceSession(onnx_path, providers=["CPUExecutionProvider"])
    meta = {}
    for k, v in sess.get_modelmeta().custom_metadata_map.items():
        try:
            meta[k] = json.loads(v)
        except ValueError:
            meta[k] = v
    if "calibration_signature" not in meta.get("metadesign.camera", {}):
        raise SystemExit(f"{onnx_path}: no camera contract with a calibration signature (export it again with "
                         "`metadesign export MODEL -o FILE.onnx`)")
    return sess, meta


def area_weights(n_in: int, n_out: int, lo: float = 0.0, hi: float | None = None) -> np.ndarray:
    """(n_out, n_in): output pixel i covers input coordinates [lo + i (hi - lo) / n_out, lo + (i + 1) (hi - lo) /
    n_out) of the n_in input pixels (pixel j covers [j, j + 1)), weighted by overlap; outside them, nothing."""
    hi = float(n_in) if hi is None else hi
    edges = lo + np.arange(n_out + 1) * ((hi - lo) / n_out)
    j = np.arange(n_in)[None, :]
    return np.clip(np.minimum(edges[1:, None], j + 1) - np.maximum(edges[:-1, None], j), 0.0, None)


def input_tensor(frames, camera: dict, dark: np.ndarray | None = None, orientation: str = "identity",
                 shift_px=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """Two frames [x-pol, y-pol] as they arrived (height, width) -> the (1, 8, S, S) float32 input, following the
    steps: put back from ``orientation``, dark-subtracted, each quadrant window moved by ``shift_px`` (columns,
    rows) and scaled by ``scale`` about the frame centre, area-resampled, normalised."""
    S = int(camera["tensor_size"])
    H, W = camera["frame_px"]["height"], camera["frame_px"]["width"]
    f = np.stack([np.asarray(x, np.float64) - (0.0 if dark is None else dark) for x in frames])
    f = correct(f, orientation)
    if f.shape[-2:] != (H, W):
        raise SystemExit(f"frames of {f.shape[-1]} x {f.shape[-2]} pixels (put back from {orientation}): the camera has "
                         f"{W} x {H}")
    out = np.empty((8, S, S), np.float32)
    for p in range(2):
        for k, q in enumerate(("QI", "QII", "QIII", "QIV")):
            w = camera["quadrant_windows"][q]
            (r0, r1), (c0, c1) = w["rows"], w["cols"]
            ry = area_weights(H, S, H / 2 + scale * (r0 - H / 2) + shift_px[1], H / 2 + scale * (r1 - H / 2) + shift_px[1])
            rx = area_weights(W, S, W / 2 + scale * (c0 - W / 2) + shift_px[0], W / 2 + scale * (c1 - W / 2) + shift_px[0])
            out[4 * p + k] = (ry @ f[p] @ rx.T).astype(np.float32)
    return (out * (8.0 / out.sum(dtype=np.float64))).astype(np.float32)[None]


def calibrate(meta: dict, flat, dark: np.ndarray | None = None, orientation: str = "identity") -> dict:
    """The flat frames [x-pol, y-pol] (as they arrived) checked against the contract's calibration signature:
    exits with the one line that names what is wrong, else returns the verdict with the spots' shift and scale."""
    cam = meta["metadesign.camera"]
    if orientation not in ORIENTATIONS:
        raise SystemExit(f"--orientation: expected one of {', '.join(ORIENTATIONS)}, got {orientation!r}")
    f = np.stack([np.asarray(x, np.float64) - (0.0 if dark is None else dark) for x in flat])
    v = diagnose(f, cam["calibration_signature"], orientation)
    if v["problem"]:
        raise SystemExit(f"flat frame: {v['problem']}")
    if abs(v["scale"] - 1) > 0.2:
        raise SystemExit(f"flat frame: the spots are scaled by {v['scale']:.3f} against the contract's (relay "
                         f"magnification {cam['relay_magnification']:g}): another relay?")
    return v


def reconstruct(onnx_path: str, frames, flat, dark: np.ndarray | None = None,
                orientation: str = "identity") -> tuple[np.ndarray, dict]:
    """The received phase (rad) on the contract's output grid (the SLM command is its negative), and the flat's
    verdict."""
    sess, meta = load(onnx_path)
    v = calibrate(meta, flat, dark, orientation)
    x = input_tensor(frames, meta["metadesign.camera"], dark, orientation, v["shift_px"], v["scale"])
    return sess.run(None, {"psf": x})[0][0], v


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("onnx")
    ap.add_argument("frame_x")
    ap.add_argument("frame_y")
    ap.add_argument("--flat", nargs=2, required=True, metavar=("FLAT_X", "FLAT_Y"),
                    help="a flat-wavefront capture (x-pol, y-pol frames) to check the orientation and alignment with")
    ap.add_argument("--orientation", default="identity", help="how the frames arrive: " + ", ".join(ORIENTATIONS))
    ap.add_argument("--dark")
    ap.add_argument("-o", "--output", default="phase.npy")
    a = ap.parse_args()
    from astropy.io import fits

    def read(path):
        return np.asarray(fits.getdata(path), np.float64) if path.lower().endswith((".fits", ".fit", ".fts")) \
            else np.load(path, allow_pickle=False).astype(np.float64)

    frames = [read(f) for f in (a.frame_x, a.frame_y)]
    flat = [read(f) for f in a.flat]
    dark = read(a.dark) if a.dark else None
    phi, v = reconstruct(a.onnx, frames, flat, dark, a.orientation)
    np.save(a.output, phi)
    print(f"flat: orientation {v['best']} (chi2 {v['chi2']:.2g}; next {v['runner_up']} {v['runner_up_chi2']:.2g}), "
          f"spots shifted ({v['shift_px'][0]:+.2f}, {v['shift_px'][1]:+.2f}) px, scale {v['scale']:.4f}: windows moved")
    print(f"wrote {a.output}: received phase {phi.shape}, rms {phi[phi != 0].std():.3f} rad; SLM command: -phase")


if __name__ == "__main__":
    main()

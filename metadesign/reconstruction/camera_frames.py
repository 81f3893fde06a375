"""Camera frames of a capture import (:mod:`.captures`): reading them (PNG / TIFF / FITS / ``.npy``) and their
CSV lists, dark frames' hot pixels, the 8 spots' centroids, and the relay's alignment fitted against the
reference device's flat frames (:func:`calibrate`), then each frame resampled into a PSF tensor
(:func:`aligned_tensor`)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..sensing.camera import Alignment
from ..sensing.sensor import area_resample, quadrant_slices
from ..validation import ValidationError

__all__ = ["read_frame", "read_manifest", "spot_centroids", "fit_alignment", "aligned_tensor", "hot_pixel_map",
           "fix_hot_pixels", "calibrate", "FITS_SUFFIXES", "IMAGE_SUFFIXES"]

FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz")
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy", *FITS_SUFFIXES)


def read_frame(path: Path, what: str = "frame") -> tuple[np.ndarray, float | None]:
    """A 2D frame as float64 and the full scale of its integer type (None for float data)."""
    path = Path(path)
    if not path.is_file():
        raise ValidationError(f"{path}: no such {what}")
    name = path.name.lower()
    suf = next((s for s in IMAGE_SUFFIXES if name.endswith(s)), path.suffix.lower())
    if suf not in IMAGE_SUFFIXES:
        raise ValidationError(f"{path}: {what}: expected .png, .tif/.tiff, .npy or FITS (.fits, .fit, .fts, "
                              f".fits.gz), got {suf or 'no suffix'}")
    try:
        if suf == ".npy":
            a = np.load(path, allow_pickle=False)
        elif suf in FITS_SUFFIXES:
            a = _read_fits(path)
        else:
            from PIL import Image

            with Image.open(path) as im:
                a = np.asarray(im)
    except Exception as exc:  # Pillow and numpy raise many kinds on damaged files
        raise ValidationError(f"{path}: unreadable {what} ({exc.__class__.__name__}: {str(exc)[:80]})") from None
    if a.ndim != 2 or not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise ValidationError(f"{path}: {what}: expected a 2D real image, got {a.dtype} {a.shape}")
    full = float(np.iinfo(a.dtype).max) if np.issubdtype(a.dtype, np.integer) else None
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise ValidationError(f"{path}: {what}: holds NaN or infinite values")
    return a, full


def _read_fits(path: Path) -> np.ndarray:
    """The first 2-D image of a FITS file (primary HDU or an image extension), BZERO/BSCALE applied
    (unsigned 16-bit frames come back as uint16, as cameras write them)."""
    from astropy.io import fits

    with fits.open(path, memmap=False) as hdus:
        for h in hdus:
            if getattr(h, "data", None) is not None and h.is_image and np.ndim(h.data) == 2:
                return np.array(h.data)
    raise ValueError("no 2-D image in any HDU")


def read_manifest(path: Path, need: tuple[str, ...], what: str = "manifest") -> list[dict]:
    path = Path(path)
    if not path.is_file():
        raise ValidationError(f"{path}: no such {what}")
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ValidationError(f"{path}: unreadable {what} ({exc})") from None
    if not rows:
        raise ValidationError(f"{path}: {what} lists no rows")
    missing = [c for c in need if c not in rows[0]]
    if missing:
        raise ValidationError(f"{path}: {what} lacks the column(s) {', '.join(missing)} (needs {', '.join(need)})")
    base = path.parent
    for n, r in enumerate(rows, 2):
        for c in need:
            if c in ("frame_x", "frame_y", "frame_raw", "slm_phase"):
                v = (r.get(c) or "").strip()
                if not v:
                    raise ValidationError(f"{path}: line {n}: empty {c}")
                p = Path(v)
                p = p if p.is_absolute() else base / p
                if not p.is_file():
                    raise ValidationError(f"{path}: line {n}: {c} {v}: no such file")
                r[c] = p
    return rows


def hot_pixel_map(dark: np.ndarray, sigma: float = 8.0) -> np.ndarray:
    """Pixels of a (mean) dark frame above its median by ``sigma`` robust sigmas (1.4826 MAD; at least
    one count)."""
    med = np.median(dark)
    mad = 1.4826 * np.median(np.abs(dark - med))
    return dark > med + sigma * max(mad, 1.0)


def fix_hot_pixels(frame: np.ndarray, hot: np.ndarray) -> np.ndarray:
    """Hot pixels replaced by the median of their non-hot 3 x 3 neighbours."""
    if not hot.any():
        return frame
    out = frame.copy()
    H, W = frame.shape
    for r, c in zip(*np.nonzero(hot)):
        r0, r1, c0, c1 = max(r - 1, 0), min(r + 2, H), max(c - 1, 0), min(c + 2, W)
        nb = frame[r0:r1, c0:c1][~hot[r0:r1, c0:c1]]
        out[r, c] = np.median(nb) if nb.size else 0.0
    return out


def spot_centroids(frames: np.ndarray, sensor, threshold: float = 0.1) -> np.ndarray:
    """(8, 2) spot centres (col, row) in frame pixels: thresholded centre of gravity in each nominal
    quadrant window of each polarisation frame (channel order of the tensor)."""
    out = np.empty((8, 2))
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            q = np.asarray(frames[p][r, c], np.float64)
            q = np.clip(q - threshold * q.max(), 0, None)
            s = q.sum()
            if not s > 0:
                raise ValidationError(f"calibration: no spot in polarisation {'xy'[p]} quadrant {k} of the flat "
                                      "capture (dark frame, or a wrong sensor)")
            yy, xx = np.indices(q.shape)
            out[4 * p + k - 1] = ((q * xx).sum() / s + c.start, (q * yy).sum() / s + r.start)
    return out


def fit_alignment(reference: np.ndarray, measured: np.ndarray, shape: tuple[int, int], mode: str = "similarity"):
    """Least-squares :class:`Alignment` mapping ``reference`` centres (N, 2) onto ``measured`` ones, and
    the residuals (N,) in pixels."""
    c = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
    P, Q = reference - c, measured - c
    if mode == "shift":
        t = (Q - P).mean(axis=0)
        al = Alignment(float(t[0]), float(t[1]))
    elif mode == "similarity":
        # x' = a x - b y + tx ; y' = b x + a y + ty
        n = len(P)
        A = np.zeros((2 * n, 4))
        A[0::2] = np.c_[P[:, 0], -P[:, 1], np.ones(n), np.zeros(n)]
        A[1::2] = np.c_[P[:, 1], P[:, 0], np.zeros(n), np.ones(n)]
        a, b, tx, ty = np.linalg.lstsq(A, Q.reshape(-1), rcond=None)[0]
        al = _checked(lambda: Alignment.from_matrix(np.array([[a, -b], [b, a]]), (tx, ty)))
    else:
        raise ValidationError(f"--fit: expected shift or similarity, got {mode!r}")
    res = np.linalg.norm(al.forward(reference, shape) - measured, axis=1)
    return al, res


def _checked(make):
    """An alignment from ``make()``, its range errors as one calibration line."""
    try:
        return make()
    except ValueError as exc:
        raise ValidationError(f"calibration: the fitted relay misalignment is out of range ({exc}); "
                              "check the flat captures and the reference") from None


def _warp(frames: np.ndarray, alignment) -> tuple[np.ndarray, np.ndarray]:
    """Frames (2, H, W) sampled (bilinear) at ``T(p)`` for every nominal pixel ``p``, and the mask of the
    nominal pixels whose ``T(p)`` lies on the camera."""
    from scipy.ndimage import map_coordinates

    H, W = frames.shape[-2:]
    rr, cc = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    q = alignment.forward(np.stack([cc, rr], -1).reshape(-1, 2), (H, W))
    seen = ((q[:, 0] >= -0.5) & (q[:, 0] <= W - 0.5) & (q[:, 1] >= -0.5) & (q[:, 1] <= H - 0.5)).reshape(H, W)
    out = np.stack([map_coordinates(f, [q[:, 1], q[:, 0]], order=1, mode="constant").reshape(H, W) for f in frames])
    return out, seen


def calibrate(flat: np.ndarray, reference: np.ndarray, sensor, mode: str = "similarity", threshold: float = 0.1,
              iterations: int = 6):
    """The relay :class:`Alignment` from a flat capture (2, H, W) and the reference model's flat frames.

    A centre of gravity in a fixed window is pulled toward the window's centre when the spot moves, by an
    amount that depends on the spot (broad, defocused spots with crosstalk halos suffer most), so the fit
    is iterated: the capture is warped into nominal coordinates by the current estimate, its centroids are
    compared with the reference's (masked alike where the warp left the frame), and the small similarity
    between them is composed into the estimate.  Returns (alignment, residuals of the last fit (px),
    first-pass measured centres)."""
    shape = flat.shape[-2:]
    c_ref = spot_centroids(reference, sensor, threshold)
    c_first = spot_centroids(flat, sensor, threshold)
    al, res = fit_alignment(c_ref, c_first, shape, mode)
    for _ in range(iterations):
        warped, seen = _warp(flat, al)
        c_meas = spot_centroids(warped, sensor, threshold)
        c_r = spot_centroids(reference * seen, sensor, threshold)
        step, res = fit_alignment(c_r, c_meas, shape, mode)
        al = _checked(lambda: al.then(step))
        if np.abs(step.forward(c_r, shape) - c_r).max() < 1e-3:
            break
    return al, res, c_first


def aligned_tensor(frames: np.ndarray, sensor, alignment, tensor_size: int) -> tuple[np.ndarray, float]:
    """(8, S, S) tensor of captured ``frames`` (2, H, W): each nominal quadrant window sampled (bilinear) at
    its transformed position on the camera, area-resampled to S x S; and the fraction of window pixels that
    fell outside the frame."""
    from scipy.ndimage import map_coordinates

    H, W = frames.shape[-2:]
    out = np.empty((8, tensor_size, tensor_size), np.float32)
    outside = 0.0
    for k in range(1, 5):
        r, c = quadrant_slices(sensor, k)
        rr, cc = np.meshgrid(np.arange(r.start, r.stop), np.arange(c.start, c.stop), indexing="ij")
        q = alignment.forward(np.stack([cc, rr], -1).reshape(-1, 2), (H, W))
        outside += float(np.mean((q[:, 0] < -0.5) | (q[:, 0] > W - 0.5) | (q[:, 1] < -0.5) | (q[:, 1] > H - 0.5)))
        for p in range(2):
            win = map_coordinates(frames[p], [q[:, 1], q[:, 0]], order=1, mode="constant", cval=0.0)
            out[4 * p + k - 1] = area_resample(win.reshape(rr.shape), tensor_size)
    return out, outside / 4

"""Import of camera captures into a metadesign dataset (``metadesign dataset import``).

Inputs (paths in the CSVs are relative to the CSV):

* ``FOLDER/manifest.csv``: columns ``sample, frame_x, frame_y, slm_phase`` and optionally ``rytov`` (empty
  or absent: unknown, stored as NaN and reported so), ``split`` (train / val / test) and ``slm_extent_mm``.
  One frame per polarisation per sample (the paper rotates a polariser between captures): 16-bit PNG or
  TIFF, FITS (the first 2-D image HDU, BZERO/BSCALE applied), or ``.npy`` (any real dtype), ``width x
  height`` of the reference sensor (640 x 512 for the paper's).  ``slm_phase``: the phase the SLM applied, as ``.npy`` in radians or as a 16-bit image with
  ``--phase-per-count`` rad per count (default ``2 pi / 65536``: the full range is one wave), either on
  the receiver crop of the reference's turbulence grid (A x A samples spanning ``A dx``: ``dataset show
  REFERENCE`` prints both) or, with ``slm_extent_mm`` (the map's side length), on any square grid centred on
  the aperture, resampled area-weighted onto the crop; another size without an extent is refused.
* ``--calibration FLAT.csv``: flat-wavefront captures (columns ``frame_x, frame_y``; averaged).
* ``--dark FILE ...``: dark frames (averaged): subtracted from every frame; pixels brighter than the dark
  median by ``--hot-sigma`` robust sigmas are hot and replaced by the median of their non-hot neighbours.
* ``--reference DATASET``: the synthetic dataset of the design the model was trained on: its sensor, tensor
  size, turbulence path and receiver crop are the import's, and its device renders the reference flat
  frames whose spot centroids the calibration is fitted against.

Calibration: the thresholded centre of gravity of each of the 8 spots (per polarisation frame, per
quadrant window) in the mean flat capture and in the reference render; the relay misalignment is the
similarity transform (shift, rotation, magnification; ``--fit shift`` for shift only) that maps the
reference centres onto the measured ones in least squares, iterated on the capture warped back into
nominal coordinates (:func:`calibrate`) (convention: :class:`metadesign.sensing.camera.
Alignment`).  Every frame is then resampled (bilinear) at the transformed nominal quadrant windows, area-
resampled to the tensor size and normalised as synthetic data (8 channels sum to 8).

Saturation: a frame with pixels at or above ``--saturation`` counts (default: the full scale of its
integer type; hot pixels excepted) is flagged (``flags`` array, bit 0) and reported; ``--saturated drop``
leaves such samples out, ``error`` refuses the import.  Negative raw counts (a signed or BZERO-less FITS
file: a camera cannot count below zero) are clipped at zero, with a warning and their number in the report
(``negative_counts_clipped``); nothing else is clipped.

Output: the same zarr format as ``dataset build`` with ``propagation = "slm"``: ``received`` is the SLM
field ``exp(i phi) x aperture``, and the end-to-end loss and the evaluation back-propagate through the SLM
phase as the receiver-plane screen of the reference path, the other screens being vacuum
(:meth:`PSFDataset.screens_of`).  The store is written to ``OUT.partial`` and renamed when complete: a
failed import leaves nothing behind."""

from __future__ import annotations

import csv
import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..execution import SERIAL, Execution
from ..io import atomic_write_text
from ..plotting import save_figure
from ..tasks import content_key, file_key
from ..outputs import product
from ..sensing.camera import Alignment
from ..sensing.forward import sensor_frames
from ..sensing.sensor import area_resample, quadrant_slices
from ..validation import ValidationError
from .dataset_build import normalise_psf
from .dataset_recipe import split_labels
from .dataset_store import DATASET_FORMAT, consolidate, create_store, load_device, open_dataset, open_store

__all__ = ["read_frame", "read_manifest", "spot_centroids", "fit_alignment", "aligned_tensor", "hot_pixel_map",
           "fix_hot_pixels", "import_captures", "ImportOptions", "calibrate"]

FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz")
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy", *FITS_SUFFIXES)
RYTOV_MAX = 5.0  # the largest Rytov number a dataset recipe takes


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
            if c in ("frame_x", "frame_y", "slm_phase"):
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


@dataclass(frozen=True)
class ImportOptions:
    fit: str = "similarity"
    hot_sigma: float = 8.0
    saturation: float | None = None  # counts; default: the integer type's full scale
    saturated: str = "flag"  # flag | drop | error
    phase_per_count: float = 2 * np.pi / 65536
    split: tuple[float, float, float] = (0.9, 0.05, 0.05)
    seed: int = 0
    threshold: float = 0.1
    shard_size: int = 64
    overwrite: bool = False  # replace an existing output (how the import runs: not in the recipe hash)

    def hashed(self) -> dict:
        """The options that shape the store's bytes (its recipe hash): all but ``overwrite``."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "overwrite"}


def _phase(path: Path, crop, per_count: float, extent_m: float | None = None) -> np.ndarray:
    """The SLM phase of ``path`` on the receiver crop (``crop``: a :class:`~metadesign.sensing.device.
    ReceiverCrop`).  A map of the crop's own size is the crop; a map of another size needs its side length
    ``extent_m`` (the manifest's ``slm_extent_mm``): it is then resampled area-weighted (the field
    ``exp(i phi)`` averaged over each crop sample's footprint, then sampled bilinearly at the crop's
    coordinates, both grids centred on the aperture)."""
    from scipy.ndimage import map_coordinates, uniform_filter

    arr, full = read_frame(path, "SLM phase")
    if full is not None:
        arr = arr * per_count
    if arr.shape[0] != arr.shape[1]:
        raise ValidationError(f"{path}: SLM phase: expected a square map, got {arr.shape[1]} x {arr.shape[0]}")
    m, a = arr.shape[0], crop.size
    if extent_m is None:
        if m != a:
            raise ValidationError(f"{path}: SLM phase: {m} x {m} samples, but the receiver crop is {a} x {a} samples "
                                  f"spanning {crop.extent * 1e3:.6g} mm (pitch {crop.dx * 1e3:.6g} mm): give the map "
                                  "on that grid, or its side length in the manifest column slm_extent_mm")
        return arr
    if extent_m < crop.aperture:
        raise ValidationError(f"{path}: SLM phase: slm_extent_mm {extent_m * 1e3:.6g} does not cover the receiver "
                              f"aperture ({crop.aperture * 1e3:.6g} mm)")
    pitch = extent_m / m
    f = np.cos(arr) + 1j * np.sin(arr)
    box = crop.dx / pitch
    if box > 1.5:  # the map is finer than the crop: average the field over each crop sample
        k = int(round(box))
        f = uniform_filter(f.real, k, mode="nearest") + 1j * uniform_filter(f.imag, k, mode="nearest")
    u = crop.coords() / pitch + (m - 1) / 2  # crop coordinates in map-index units (both centred on the axis)
    yy, xx = np.meshgrid(u, u, indexing="ij")
    re = map_coordinates(f.real, [yy, xx], order=1, mode="nearest")
    im = map_coordinates(f.imag, [yy, xx], order=1, mode="nearest")
    return np.arctan2(im, re)


def _read_counts(path, what, neg: dict | None):
    """A frame's counts with negative values clipped at zero (a camera counts photo-electrons: a negative
    count is a signed-integer or BZERO artefact of the file); their number goes into ``neg``."""
    f, full = read_frame(path, what)
    bad = f < 0
    if bad.any():
        f = np.where(bad, 0, f)
        if neg is not None:
            neg["pixels"] = neg.get("pixels", 0) + int(bad.sum())
            neg.setdefault("frames", []).append(str(path))
    return f, full


def _mean_frames(paths, shape, what, dark=None, hot=None, neg=None):
    acc = np.zeros(shape)
    for p in paths:
        f, _ = _read_counts(p, what, neg)
        if f.shape != shape:
            raise ValidationError(f"{p}: {what}: {f.shape[1]} x {f.shape[0]} pixels, the sensor has "
                                  f"{shape[1]} x {shape[0]}")
        acc += f
    acc /= len(paths)
    if dark is not None:
        acc = acc - dark
    if hot is not None:
        acc = fix_hot_pixels(acc, hot)
    return acc


def import_captures(folder: str | Path, out: str | Path, calibration: str | Path, reference: str | Path,
                    darks: list | None = None, options: ImportOptions = ImportOptions(),
                    run: Execution = SERIAL) -> dict:
    """Import a capture folder into a dataset at ``out`` (see the module docstring); returns a report.
    ``run``: its progress (per sample) and log; ``options.overwrite`` replaces an existing ``out``."""
    folder, out = Path(folder), Path(out)
    if options.saturated not in ("flag", "drop", "error"):
        raise ValidationError(f"--saturated: expected flag, drop or error, got {options.saturated!r}")
    if out.exists() and not options.overwrite:
        raise ValidationError(f"{out}: exists (use --overwrite to replace it)")
    with product(out, "dataset", {"captures": folder, "--calibration": calibration, "--reference": reference,
                                  **{f"--dark {d}": d for d in (darks or [])}},
                 scratch=(out.with_name(out.name + ".partial"),)):
        return _import(folder, out, calibration, reference, darks, options, run)


def _split_column(rows: list[dict], manifest: Path, options: "ImportOptions") -> np.ndarray:
    """Split labels from the manifest's split column (all rows), else a seeded permutation."""
    labels = {"train": 0, "val": 1, "test": 2}
    if "split" in rows[0] and all((r.get("split") or "").strip() for r in rows):
        bad = next((r for r in rows if r["split"].strip() not in labels), None)
        if bad is not None:
            raise ValidationError(f"{manifest}: sample {bad['sample']}: split {bad['split']!r} is not train, val or test")
        return np.array([labels[r["split"].strip()] for r in rows], np.uint8)
    return split_labels(options.seed, len(rows), options.split)


def _manifest_numbers(rows: list[dict], manifest: Path) -> tuple[list[float], list[float | None]]:
    """Per row: the Rytov number (NaN: unknown) and the SLM map's side (m; None: on the receiver crop)."""
    rytov_all = []
    for r in rows:
        try:
            txt = (r.get("rytov") or "").strip()
            v = float(txt) if txt else float("nan")  # empty: unknown
        except ValueError:
            raise ValidationError(f"{manifest}: sample {r['sample']}: rytov {r.get('rytov')!r} is not a number") from None
        if txt and not (np.isfinite(v) and 0 <= v <= RYTOV_MAX):
            raise ValidationError(f"{manifest}: sample {r['sample']}: rytov: expected a number in [0, {RYTOV_MAX:g}] "
                                  f"or empty (unknown), got {txt}")
        rytov_all.append(v)
    slm_extent: list[float | None] = []  # side of each SLM phase map (m), when not on the receiver crop
    for r in rows:
        txt = (r.get("slm_extent_mm") or "").strip()
        try:
            v = float(txt) if txt else None
        except ValueError:
            v = float("nan")
        if v is not None and not (np.isfinite(v) and 0 < v <= 1e5):
            raise ValidationError(f"{manifest}: sample {r['sample']}: slm_extent_mm: expected a side length in "
                                  f"(0, 100000] mm or empty, got {txt!r}")
        slm_extent.append(None if v is None else v * 1e-3)
    return rytov_all, slm_extent


def _sample_frames(r: dict, shape, options: "ImportOptions", dark, hot, neg=None) -> tuple[list[np.ndarray], bool]:
    """A sample's two frames, checked, dark-subtracted and hot-pixel-fixed, and whether one saturated."""
    fr, sat = [], False
    for p in "xy":
        f, full = _read_counts(r[f"frame_{p}"], f"frame_{p} of sample {r['sample']}", neg)
        if f.shape != shape:
            raise ValidationError(f"{r[f'frame_{p}']}: frame_{p} of sample {r['sample']}: {f.shape[1]} x "
                                  f"{f.shape[0]} pixels, the sensor has {shape[1]} x {shape[0]}")
        level = options.saturation if options.saturation is not None else full
        if level is not None:
            s = f >= level
            if hot is not None:
                s &= ~hot
            sat |= bool(s.any())
        if dark is not None:
            f = f - dark
        if hot is not None:
            f = fix_hot_pixels(f, hot)
        fr.append(f)
    return fr, sat


@dataclass
class _Camera:
    """What every frame of an import goes through: the sensor's (rows, columns), the mean dark frame and
    the hot pixels (None without darks), the negative counts clipped so far, the fitted alignment."""

    shape: tuple[int, int]
    dark: np.ndarray | None
    hot: np.ndarray | None
    neg: dict
    alignment: object


@dataclass
class _Converted:
    """Pass 1 of an import: the manifest rows kept, the saturated samples, the kept rows' tensors, powers,
    SLM fields and Rytov numbers, and the largest fraction of a quadrant window outside the frame."""

    kept: list
    flagged: list
    psf: list
    power: list
    rec: list
    rytov: np.ndarray
    outside_max: float


def _convert(rows: list[dict], manifest: Path, ref, tensor_size: int, cam: _Camera, options: ImportOptions,
             progress) -> _Converted:
    """Pass 1: every frame read, checked, converted (a failure writes nothing)."""
    rytov_all, slm_extent = _manifest_numbers(rows, manifest)
    ap = ref.crop.aperture_mask()
    kept, flagged, psf, power, rec, outside_max = [], [], [], [], [], 0.0
    for j, r in enumerate(rows):
        fr, sat = _sample_frames(r, cam.shape, options, cam.dark, cam.hot, cam.neg)
        if sat:
            if options.saturated == "error":
                raise ValidationError(f"{r['frame_x'].parent}: sample {r['sample']}: saturated frame "
                                      f"(--saturated error)")
            flagged.append(r["sample"])
            if options.saturated == "drop":
                continue
        phi = _phase(r["slm_phase"], ref.crop, options.phase_per_count, slm_extent[j])
        t, outside = aligned_tensor(np.stack(fr), ref.sensor, cam.alignment, tensor_size)
        outside_max = max(outside_max, outside)
        x, pw = normalise_psf(t)
        if not pw > 0:
            raise ValidationError(f"{r['frame_x']}: sample {r['sample']}: no light after dark subtraction")
        psf.append(x)
        power.append(pw)
        rec.append(np.where(ap, np.cos(phi) + 1j * np.sin(phi), 0).astype(np.complex64))
        kept.append(j)
        if progress:
            progress(j + 1, len(rows))
    if not kept:
        raise ValidationError(f"{manifest}: every sample is saturated (--saturated drop left none)")
    return _Converted(kept, flagged, psf, power, rec, np.array([rytov_all[j] for j in kept], np.float32),
                      outside_max)


def _store_attrs(name: str, parts: dict, conv: _Converted, split: np.ndarray, ref_info, options: ImportOptions,
                 sources: dict) -> dict:
    """The imported store's attributes: ``parts`` (what its recipe hash covers), the reference's scenario,
    sensor and crop, the saturated samples; ``sources``: the captures' and the reference's paths."""
    n, rytov = len(conv.kept), conv.rytov
    prov_ref = ref_info.attrs["provenance"]
    return {
        "format": DATASET_FORMAT, "version": __version__, "complete": False, "recipe_hash": content_key(parts),
        "name": name, "samples": n, "shard_size": options.shard_size,
        "n_shards": (n + options.shard_size - 1) // options.shard_size, "tensor_size": ref_info.tensor_size,
        "root_seed": options.seed,
        "split_fractions": [float(np.mean(split == v)) for v in range(3)],
        "rytov": {"range": [float(np.nanmin(rytov)), float(np.nanmax(rytov))] if np.isfinite(rytov).any() else None,
                  "values": None, "unknown": int(np.isnan(rytov).sum())},
        "propagation": "slm",
        "provenance": {**parts, **sources,
                       "scenario": prov_ref["scenario"], "sensor": prov_ref["sensor"],
                       "pupil_grid": prov_ref.get("pupil_grid"), "layout_sha256": prov_ref.get("layout_sha256"),
                       "library_sha256": prov_ref.get("library_sha256"), "perturbation": None,
                       "saturated": conv.flagged, "saturated_policy": options.saturated},
        "received_crop": ref_info.attrs["received_crop"],
        "normalisation": "psf: each sample's 8 channels sum to 8 (psf_power holds the raw total, dark-subtracted "
                         "counts)",
        "seeds": "captured data: no screens; the SLM phase is the receiver-plane screen (propagation = slm)",
        "split_labels": {"0": "train", "1": "val", "2": "test"},
    }


def _fill_store(path: Path, conv: _Converted, rows: list[dict]) -> None:
    """Pass 2: the converted samples into the created store at ``path``, with each one's saturation flag and
    manifest row; marked complete."""
    n = len(conv.kept)
    g = open_store(path, "r+")
    g["psf"][:] = np.stack(conv.psf)
    g["received"][:] = np.stack(conv.rec)
    g["psf_power"][:] = np.array(conv.power, np.float32)
    g["rytov"][:] = conv.rytov  # NaN: unknown (no rytov in the manifest)
    g["rytov_measured"][:] = conv.rytov
    g["seed"][:] = np.arange(n, dtype=np.int64)
    fl = g.create_array("flags", shape=(n,), chunks=(max(n, 1),), dtype="uint8", fill_value=0,
                        dimension_names=("sample",))
    flagged_set = set(conv.flagged)
    fl[:] = np.array([rows[j]["sample"] in flagged_set for j in conv.kept], np.uint8)
    nm = g.create_array("manifest_row", shape=(n,), chunks=(max(n, 1),), dtype="int64", fill_value=-1,
                        dimension_names=("sample",))
    nm[:] = np.array(conv.kept, np.int64)  # row of the manifest
    g.attrs.update({"complete": True})


def _import(folder: Path, out: Path, calibration, reference, darks, options: ImportOptions, run: Execution) -> dict:
    t0 = time.perf_counter()
    manifest = folder / "manifest.csv" if folder.is_dir() else folder
    rows = read_manifest(manifest, ("sample", "frame_x", "frame_y", "slm_phase"))
    names = [r["sample"] for r in rows]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValidationError(f"{manifest}: sample {dup!r} is listed twice")
    flats = read_manifest(Path(calibration), ("frame_x", "frame_y"), "calibration list")
    ref = load_device(reference)
    ref_info = open_dataset(reference)
    sensor, a = ref.sensor, ref.crop.size
    shape = (sensor.height_px, sensor.width_px)
    S = ref_info.tensor_size

    # darks and hot pixels
    dark = hot = None
    neg: dict = {}
    if darks:
        dark = _mean_frames([Path(p) for p in darks], shape, "dark frame", neg=neg)
        hot = hot_pixel_map(dark, options.hot_sigma)
    # calibration
    flat = np.stack([_mean_frames([r[f"frame_{p}"] for r in flats], shape, "flat capture", dark, hot, neg)
                     for p in "xy"])
    ref_frames = sensor_frames(ref.pupil, sensor, None)
    c_ref = spot_centroids(ref_frames, sensor, options.threshold)
    al, res, c_meas = calibrate(flat, ref_frames, sensor, options.fit, options.threshold)
    notes = [f"calibration: shift ({al.shift_x_px:+.2f}, {al.shift_y_px:+.2f}) px, rotation {al.rotation_deg:+.3f} deg, "
        f"magnification x{al.scale:.4f}; spot residuals max {res.max():.2f} px"]
    if res.max() > 2.0:
        notes.append(f"warning: a spot is {res.max():.1f} px from the fitted transform (per-polarisation misalignment? "
            "a wrong reference?)")

    split_all = _split_column(rows, manifest, options)
    conv = _convert(rows, manifest, ref, S, _Camera(shape, dark, hot, neg, al), options, run.progress)
    if neg:
        run.log(f"warning: {neg['pixels']} negative counts in {len(neg['frames'])} frame(s) (first: "
                f"{neg['frames'][0]}) clipped at zero: a camera counts photo-electrons (a signed or BZERO-less FITS "
                "file?)")
    for line in notes:  # only once every input is known good (an error is one line)
        run.log(line)

    # pass 2: the store, written aside and renamed
    n = len(conv.kept)
    split = split_all[conv.kept]
    calib = {"alignment": al.to_dict(), "fit": options.fit, "residuals_px": [float(v) for v in res],
             "reference_centres_px": c_ref.tolist(), "measured_centres_px": c_meas.tolist(),
             "flat_captures": len(flats), "dark_frames": len(darks or []),
             "hot_pixels": int(hot.sum()) if hot is not None else None, "window_outside_frame_max": conv.outside_max}
    parts = {"format": DATASET_FORMAT, "source": "captures", "manifest_sha256": file_key(manifest),
             "calibration": calib, "options": options.hashed()}
    attrs = _store_attrs(out.name, parts, conv, split, ref_info, options,
                         {"captures": str(folder), "reference": str(reference)})
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        create_store(tmp, n, S, options.shard_size, a, attrs, split, rytov_fill=-1.0)
        _fill_store(tmp, conv, rows)
        consolidate(tmp)  # before the calibration files beside the arrays (zarr would warn of them)

        atomic_write_text(tmp / "calibration.json", json.dumps(calib, indent=1))
        _plot_calibration(tmp / "calibration.png", flat, c_ref, c_meas, al, res)
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    info = open_dataset(out)
    return {"output": str(out), "samples": n, "listed": len(rows), "saturated": len(conv.flagged),
            "negative_counts_clipped": neg.get("pixels", 0), "negative_count_frames": len(neg.get("frames", [])),
            "saturated_samples": conv.flagged[:20], "saturated_policy": options.saturated, "calibration": calib,
            "seconds": time.perf_counter() - t0, **info.summary()}


def _plot_calibration(path: Path, flat, c_ref, c_meas, al, res) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 2, figsize=(12, 4.6))
    for p, ax in enumerate(axs):
        ax.imshow(np.sqrt(np.clip(flat[p], 0, None)), cmap="gray")
        sl = slice(4 * p, 4 * p + 4)
        ax.plot(*c_ref[sl].T, "c+", ms=12, label="reference (model)")
        ax.plot(*c_meas[sl].T, "rx", ms=10, label="measured")
        fit = al.forward(c_ref[sl], flat.shape[-2:])
        ax.plot(*fit.T, "yo", mfc="none", ms=12, label="fitted transform")
        ax.set_title(f"flat capture, {'xy'[p]} polarisation (sqrt)")
        ax.legend(loc="lower right", fontsize=7)
    fig.suptitle(f"relay: shift ({al.shift_x_px:+.2f}, {al.shift_y_px:+.2f}) px, rotation {al.rotation_deg:+.3f} deg, "
                 f"x{al.scale:.4f}; residual max {res.max():.2f} px")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)

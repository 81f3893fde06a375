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
* ``--mosaic CAMERA.toml``: a polarisation (mosaic) camera's raw captures instead (issue #52): the manifest and
  the calibration list name one raw capture per sample in a ``frame_raw`` column, darks are raw too, and the
  vendor's layout (size, bit depth, packing, the micro-polariser pattern, the demosaic) is the recipe's
  (:mod:`.mosaic_frames`); darks and hot pixels are handled on the raw mosaic, saturation at its bit depth's full
  scale, then each capture is demosaicked into the x and y frames (the reference sensor's size: a raw capture has
  twice its pixels along each side).
* ``--calibration FLAT.csv``: flat-wavefront captures (columns ``frame_x, frame_y``; averaged).
* ``--dark FILE ...``: dark frames (averaged): subtracted from every frame; pixels brighter than the dark
  median by ``--hot-sigma`` robust sigmas are hot and replaced by the median of their non-hot neighbours.
* ``--reference DATASET``: the synthetic dataset of the design the model was trained on: its sensor, tensor
  size, turbulence path and receiver crop are the import's, and its device renders the reference flat
  frames whose spot centroids the calibration is fitted against.
* ``--orientation NAME``: how the camera's frames are turned against the contract's (``flip-ud``, ``rot180``,
  ``swap-pol``, ...: :data:`metadesign.sensing.orientation.ORIENTATIONS`); every frame is put back before
  use.  Default ``identity``.

Orientation (issue #52): the mean flat capture's calibration signature (each spot's ensquared energies: the
defocus ladder) is compared with the reference device's in every orientation
(:func:`metadesign.sensing.orientation.diagnose`); a flat that matches another orientation than the
declared one (a flipped, rotated or mirrored frame, swapped polarisation frames), or none, is refused in
one line naming what is wrong.  The verdict is kept in the store's provenance (``orientation``), and
``evaluate`` refuses captures imported without it.

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

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..execution import fresh_scratch, publish_scratch, remove_scratch, scratch_path
from ..execution import SERIAL, Execution
from ..io import atomic_write_text
from ..plotting import save_figure
from ..tasks import content_key, file_key
from ..outputs import product
from ..sensing.device import Device
from ..validation import ValidationError
from .camera_frames import (aligned_tensor,
                            calibrate, fit_alignment, fix_hot_pixels, hot_pixel_map, read_frame, read_manifest,
                            spot_centroids)
from .dataset_build import normalise_psf
from .dataset_recipe import split_labels
from .dataset_store import DATASET_FORMAT, consolidate, create_store, load_device, open_dataset, open_store
from .frame_orientation import captured_shape, check_flat, put_back, turned_hint
from .mosaic_frames import demosaic_counts, fix_hot_mosaic, load_mosaic_layout, read_raw

__all__ = ["read_frame", "read_manifest", "spot_centroids", "fit_alignment", "aligned_tensor", "hot_pixel_map",
           "fix_hot_pixels", "import_captures", "ImportOptions", "calibrate"]

RYTOV_MAX = 5.0  # the largest Rytov number a dataset recipe takes


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
    orientation: str = "identity"  # how the camera's frames are turned (metadesign.sensing.orientation)

    def hashed(self) -> dict:
        """The options that shape the store's bytes (its recipe hash): all but ``overwrite`` (and the
        orientation when it is the contract's: the hashes of imports made before it existed hold)."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__
                if k != "overwrite" and not (k == "orientation" and self.orientation == "identity")}



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


def _read_counts(path, what, neg: dict | None, mosaic=None):
    """A frame's counts with negative values clipped at zero (a camera counts photo-electrons: a negative
    count is a signed-integer or BZERO artefact of the file); their number goes into ``neg``.  ``mosaic``: a
    raw capture of that layout (:func:`~.mosaic_frames.read_raw`, every count checked)."""
    if mosaic is not None:
        return read_raw(path, mosaic, what)
    f, full = read_frame(path, what)
    bad = f < 0
    if bad.any():
        f = np.where(bad, 0, f)
        if neg is not None:
            neg["pixels"] = neg.get("pixels", 0) + int(bad.sum())
            neg.setdefault("frames", []).append(str(path))
    return f, full


def _fix_hot(frame, hot, mosaic=None):
    """Hot pixels replaced from their neighbours (a raw mosaic's: from those behind the same micro-polariser)."""
    return fix_hot_mosaic(frame, hot) if mosaic is not None else fix_hot_pixels(frame, hot)


def _mean_frames(paths, shape, what, dark=None, hot=None, neg=None, mosaic=None):
    acc = np.zeros(shape)
    for p in paths:
        f, _ = _read_counts(p, what, neg, mosaic)
        if f.shape != shape:
            raise ValidationError(f"{p}: {what}: {f.shape[1]} x {f.shape[0]} pixels, the sensor has "
                                  f"{shape[1]} x {shape[0]}{turned_hint(f.shape, shape)}")
        acc += f
    acc /= len(paths)
    if dark is not None:
        acc = acc - dark
    if hot is not None:
        acc = _fix_hot(acc, hot, mosaic)
    return acc


def import_captures(folder: str | Path, out: str | Path, calibration: str | Path, reference: str | Path,
                    darks: list | None = None, options: ImportOptions = ImportOptions(),
                    run: Execution = SERIAL, mosaic: str | Path | None = None) -> dict:
    """Import a capture folder into a dataset at ``out`` (see the module docstring); returns a report.
    ``run``: its progress (per sample) and log; ``options.overwrite`` replaces an existing ``out``; ``mosaic``:
    the recipe of a polarisation camera's raw captures (:mod:`.mosaic_frames`)."""
    layout = load_mosaic_layout(mosaic) if mosaic is not None else None
    folder, out = Path(folder), Path(out)
    if options.saturated not in ("flag", "drop", "error"):
        raise ValidationError(f"--saturated: expected flag, drop or error, got {options.saturated!r}")
    if out.exists() and not options.overwrite:
        raise ValidationError(f"{out}: exists (use --overwrite to replace it)")
    with product(out, "dataset", {"captures": folder, "--calibration": calibration, "--reference": reference,
                                  **{f"--dark {d}": d for d in (darks or [])},
                                  **({"--mosaic": mosaic} if mosaic is not None else {})},
                 scratch=(scratch_path(out),)):
        return _import(folder, out, calibration, reference, darks, options, run, layout)


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


def _sample_frames(r: dict, shape, options: "ImportOptions", dark, hot, neg=None,
                   mosaic=None) -> tuple[list[np.ndarray], bool]:
    """A sample's two frames, checked, dark-subtracted and hot-pixel-fixed, and whether one saturated (``mosaic``:
    from its one raw capture, demosaicked after the darks and hot pixels)."""
    fr, sat = [], False
    for p in ("raw",) if mosaic is not None else "xy":
        f, full = _read_counts(r[f"frame_{p}"], f"frame_{p} of sample {r['sample']}", neg, mosaic)
        if f.shape != shape:
            raise ValidationError(f"{r[f'frame_{p}']}: frame_{p} of sample {r['sample']}: {f.shape[1]} x "
                                  f"{f.shape[0]} pixels, the sensor has {shape[1]} x {shape[0]}"
                                  f"{turned_hint(f.shape, shape)}")
        level = options.saturation if options.saturation is not None else full
        if level is not None:
            s = f >= level
            if hot is not None:
                s &= ~hot
            sat |= bool(s.any())
        if dark is not None:
            f = f - dark
        if hot is not None:
            f = _fix_hot(f, hot, mosaic)
        fr.append(f)
    if mosaic is not None:
        fr = list(demosaic_counts(fr[0], mosaic))
    return put_back(fr, options.orientation), sat


@dataclass
class _Camera:
    """What every frame of an import goes through: the sensor's (rows, columns), the mean dark frame and
    the hot pixels (None without darks), the negative counts clipped so far, the fitted alignment."""

    shape: tuple[int, int]
    dark: np.ndarray | None
    hot: np.ndarray | None
    neg: dict
    alignment: object
    mosaic: object = None  # a raw mosaic's layout (shape, dark and hot pixels are then the raw mosaic's)


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
        fr, sat = _sample_frames(r, cam.shape, options, cam.dark, cam.hot, cam.neg, cam.mosaic)
        first = r["frame_raw"] if cam.mosaic is not None else r["frame_x"]
        if sat:
            if options.saturated == "error":
                raise ValidationError(f"{first.parent}: sample {r['sample']}: saturated frame "
                                      f"(--saturated error)")
            flagged.append(r["sample"])
            if options.saturated == "drop":
                continue
        phi = _phase(r["slm_phase"], ref.crop, options.phase_per_count, slm_extent[j])
        t, outside = aligned_tensor(np.stack(fr), ref.sensor, cam.alignment, tensor_size)
        outside_max = max(outside_max, outside)
        x, pw = normalise_psf(t)
        if not pw > 0:
            raise ValidationError(f"{first}: sample {r['sample']}: no light after dark subtraction")
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


def _import(folder: Path, out: Path, calibration, reference, darks, options: ImportOptions, run: Execution,
            mosaic=None) -> dict:
    t0 = time.perf_counter()
    manifest = folder / "manifest.csv" if folder.is_dir() else folder
    cols = ("frame_raw",) if mosaic is not None else ("frame_x", "frame_y")
    rows = read_manifest(manifest, ("sample", *cols, "slm_phase"))
    names = [r["sample"] for r in rows]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValidationError(f"{manifest}: sample {dup!r} is listed twice")
    flats = read_manifest(Path(calibration), cols, "calibration list")
    ref = load_device(reference)
    ref_info = open_dataset(reference)
    sensor = ref.sensor
    shape = (sensor.height_px, sensor.width_px)
    raw_shape = captured_shape(shape, options.orientation) if mosaic is None else (2 * shape[0], 2 * shape[1])
    if mosaic is not None and mosaic.width_px and (mosaic.height_px, mosaic.width_px) != raw_shape:
        raise ValidationError(f"--mosaic: a {mosaic.width_px} x {mosaic.height_px} raw mosaic gives "
                              f"{mosaic.width_px // 2} x {mosaic.height_px // 2} frames, the reference's sensor has "
                              f"{shape[1]} x {shape[0]} pixels")
    S = ref_info.tensor_size

    # darks and hot pixels
    dark = hot = None
    neg: dict = {}
    if darks:
        dark = _mean_frames([Path(p) for p in darks], raw_shape, "dark frame", neg=neg, mosaic=mosaic)
        hot = hot_pixel_map(dark, options.hot_sigma)
    # calibration
    if mosaic is not None:
        flat = demosaic_counts(_mean_frames([r["frame_raw"] for r in flats], raw_shape, "flat capture", dark, hot,
                                            neg, mosaic), mosaic)
    else:
        flat = np.stack([_mean_frames([r[f"frame_{p}"] for r in flats], raw_shape, "flat capture", dark, hot, neg)
                         for p in "xy"])
    ref_frames = Device(ref.pupil, sensor).frames()
    flat, verdict = check_flat(flat, ref_frames, options.orientation, calibration)  # issue #52: its orientation
    c_ref = spot_centroids(ref_frames, sensor, options.threshold)
    al, res, c_meas = calibrate(flat, ref_frames, sensor, options.fit, options.threshold)
    notes = [(f"calibration: orientation {verdict.best} (chi2 {verdict.chi2:.2g}, next {verdict.runner_up} "
              f"{verdict.runner_up_chi2:.2g}); shift ({al.shift_x_px:+.2f}, {al.shift_y_px:+.2f}) px, rotation "
              f"{al.rotation_deg:+.3f} deg, magnification x{al.scale:.4f}; spot residuals max {res.max():.2f} px")]
    if verdict.note():
        notes.append(f"warning: {verdict.note()}")
    if res.max() > 2.0:
        notes.append(f"warning: a spot is {res.max():.1f} px from the fitted transform (per-polarisation misalignment? "
            "a wrong reference?)")

    split_all = _split_column(rows, manifest, options)
    conv = _convert(rows, manifest, ref, S, _Camera(raw_shape, dark, hot, neg, al, mosaic), options, run.progress)
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
    if mosaic is not None:  # absent for two frames per sample: those imports keep their hash
        parts["mosaic"] = mosaic.to_dict()
    attrs = _store_attrs(out.name, parts, conv, split, ref_info, options,
                         {"captures": str(folder), "reference": str(reference), "orientation": verdict.to_dict()})
    tmp = fresh_scratch(out, "store")  # OUT.partial/store: zarr empties its own folder, so the marker stays outside
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        create_store(tmp, attrs, split, rytov_fill=-1.0)
        _fill_store(tmp, conv, rows)
        consolidate(tmp)  # before the calibration files beside the arrays (zarr would warn of them)

        atomic_write_text(tmp / "calibration.json", json.dumps({**calib, "orientation": verdict.to_dict()}, indent=1))
        _plot_calibration(tmp / "calibration.png", flat, c_ref, c_meas, al, res)
        if out.exists():
            shutil.rmtree(out)
        publish_scratch(tmp, out)
    except BaseException:
        remove_scratch(tmp.parent)
        raise
    info = open_dataset(out)
    return {"output": str(out), "samples": n, "listed": len(rows), "saturated": len(conv.flagged),
            "negative_counts_clipped": neg.get("pixels", 0), "negative_count_frames": len(neg.get("frames", [])),
            "saturated_samples": conv.flagged[:20], "saturated_policy": options.saturated, "calibration": calib,
            "orientation": verdict.to_dict(), "seconds": time.perf_counter() - t0, **info.summary()}


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

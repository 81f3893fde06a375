"""Stage 6a, the dataset store: the zarr v3 store of a dataset of 8-PSF frames (created here, filled by
:mod:`.dataset_build` or :mod:`.captures`), opened, verified and asked for its device here (reading
samples for training and evaluation: :mod:`.data`).

Store layout (``OUT/``, a zarr v3 group; readable with plain ``zarr`` + numpy):

* ``psf``       (N, 8, S, S) float32: the PSF tensor (x-pol QI..QIV, y-pol QI..QIV), area-resampled,
  **normalised so that its 8 channels sum to 8** (each channel ~1): scintillation swings the received
  power by ~10x, the network should not see it.  Noise-free: noise is applied when samples are read.
* ``psf_power`` (N,) float32: the tensor's total power before normalisation (unit incident intensity).
* ``received``  (N, A, A) complex64: the collimated received field (vacuum wavefront and amplitude divided
  out) on the A x A crop of the turbulence grid that holds the receiver aperture, 0 outside it.
  Crop start and grid in the attributes (``received_crop``).
* ``rytov``     (N,) float32 nominal Rytov number; ``rytov_measured`` (N,) the sample's own log-amplitude
  variance over the aperture (the x-axis of Fig. 3b).
* ``seed``      (N,) int64: the screens' seed: ``Turbulence.at_rytov(rytov).screens(seed)`` regenerates the
  13 screens bit for bit (the end-to-end loss back-propagates through them).
* ``split``     (N,) uint8: 0 train, 1 validation, 2 test (a seeded permutation; fractions from the recipe).

A shard is finished when its marker ``OUT/.shards/NNNNNN`` exists (written atomically after its arrays);
``complete`` is set in the attributes at the end of a build.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..io import read_npz
from ..sensing.device import Device, ReceiverCrop, load_pupil
from ..sensing.forward import CoarsePupil
from ..sensing.sensor import CHANNELS, SensorSpec
from ..turbulence.scenario import scenario_from_dict
from ..validation import ValidationError

__all__ = ["DATASET_FORMAT", "OPERATOR_ARRAY", "JSON_ATTRS", "store_attrs", "decoded_attrs", "mark_complete",
           "operator_info", "has_operators", "open_store", "consolidate",
           "open_xarray", "create_store", "DatasetInfo", "open_dataset", "damaged", "check_psf", "verify_dataset",
           "PUPIL_GROUP", "write_store_pupil", "read_store_pupil", "load_device"]

DATASET_FORMAT = "metadesign.dataset/1"

#: the root attribute that names the attributes stored as JSON text (space-separated)
JSON_ATTRS = "json_attributes"


def _netcdf_value(v) -> bool:
    """Whether a netCDF file holds ``v`` as an attribute as it is: a string, a number (not a bool) or a
    non-empty flat list of numbers."""
    def number(x):
        return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))

    if isinstance(v, str) or number(v):
        return True
    return isinstance(v, (list, tuple)) and len(v) > 0 and all(number(x) for x in v)


def store_attrs(attrs: dict) -> dict:
    """A dataset's root attributes as the store keeps them, in the forms a netCDF file can hold, so that
    ``xarray.open_zarr(DATASET).to_netcdf(FILE)`` writes: strings, numbers and flat lists of numbers as
    they are, booleans as 0/1, everything else (the nested provenance, ``rytov``, ``received_crop``,
    None, lists of strings) as JSON text, named in :data:`JSON_ATTRS`.  Its inverse: :func:`decoded_attrs`
    (idempotent on both sides)."""
    plain = decoded_attrs(attrs)
    out, coded = {}, []
    for k, v in plain.items():
        if isinstance(v, (bool, np.bool_)):
            out[k] = int(v)
        elif _netcdf_value(v):
            out[k] = list(v) if isinstance(v, tuple) else v
        else:
            out[k] = json.dumps(v, sort_keys=True)
            coded.append(k)
    if coded:
        out[JSON_ATTRS] = " ".join(coded)
    return out


def decoded_attrs(attrs) -> dict:
    """The root attributes of a dataset as the project reads them: the ones :data:`JSON_ATTRS` names parsed
    back from JSON; stores written before the attributes were netCDF-safe (nested dicts as they are) pass
    through unchanged.  Every reader of a dataset's attributes goes through here (:func:`read_attrs`,
    :func:`open_dataset`)."""
    attrs = dict(attrs)
    names = attrs.pop(JSON_ATTRS, "")
    for k in str(names).split():
        if isinstance(attrs.get(k), str):
            try:
                attrs[k] = json.loads(attrs[k])
            except ValueError:
                pass  # a damaged attribute: left as text for the reader's own one-line error
    return attrs


#: the stored bucket operators' array (``metadesign dataset operators``, :mod:`.operators`)
OPERATOR_ARRAY = "pib_operator"


def operator_info(attrs: dict) -> dict | None:
    """The store's ``pib_operator`` attribute block, or None."""
    return attrs.get(OPERATOR_ARRAY)


def has_operators(attrs: dict, split: str) -> bool:
    """Whether every sample of ``split`` has a stored operator (a finished ``dataset operators`` run)."""
    info = operator_info(attrs)
    return bool(info and info.get("complete") and split in info.get("splits", ()))


#: the zarr group of a dataset that holds its device's coarse pupil (older datasets: device-pupil.npz)
PUPIL_GROUP = "device"


def write_store_pupil(store: Path, cp, key: dict) -> None:
    """The coarse pupil as arrays ``device/G`` (2, m*m, N, N) complex64 and ``device/X`` (N,) metres, with
    its scalars and cache key as the group's attributes."""
    import zarr

    g = open_store(store, "r+")
    d = g.require_group(PUPIL_GROUP)
    d.attrs.update({"complete": False})
    G = d.create_array("G", shape=cp.G.shape, chunks=cp.G.shape, dtype="complex64", overwrite=True,
                       dimension_names=("pol", "channel", "y", "x"))
    G[:] = cp.G
    X = d.create_array("X", shape=cp.X.shape, chunks=cp.X.shape, dtype="float64", overwrite=True,
                       dimension_names=("x",))
    X[:] = cp.X
    d.attrs.update({"block": int(cp.block), "period_m": float(cp.period), "wavelength_m": float(cp.wavelength),
                    "z_m": float(cp.z), "n_clamped": int(cp.n_clamped), "key": key, "complete": True,
                    "meaning": "coarse pupil of the as-fabricated device (metadesign.sensing.forward.CoarsePupil)"})


def read_store_pupil(store: Path):
    """(coarse pupil, its cache key) from a dataset's ``device`` group, or from the ``device-pupil.npz``
    beside the store of datasets built before the group existed."""
    import zarr

    legacy = Path(store) / "device-pupil.npz"
    try:
        d = open_store(store)[PUPIL_GROUP]
    except (KeyError, FileNotFoundError, ValueError, OSError):
        d = None
    if d is None or not d.attrs.get("complete"):
        if legacy.is_file():
            z = read_npz(legacy, "device pupil")
            return load_pupil(legacy, z), (json.loads(str(z["key"])) if "key" in z else None)
        raise ValidationError(f"{store}: no device pupil (written by `metadesign dataset build`)")
    try:
        G, X = np.asarray(d["G"][:]), np.asarray(d["X"][:])
        a = d.attrs
        cp = CoarsePupil(G, X, int(a["block"]), float(a["period_m"]), float(a["wavelength_m"]), float(a["z_m"]),
                         int(a["n_clamped"]))
    except Exception as exc:  # a damaged group: zarr raises many kinds
        raise ValidationError(f"{store}: damaged device pupil ({exc.__class__.__name__})") from None
    if G.ndim != 4 or G.shape[0] != 2 or not np.isfinite(G).all():
        raise ValidationError(f"{store}: device pupil: expected finite G of shape (2, m*m, N, N), got {G.shape}")
    return cp, dict(a["key"])


def load_device(dataset: str | Path) -> Device:
    """The device a dataset was made with (:class:`~metadesign.sensing.device.Device`): its coarse pupil
    (the store's ``device`` group, written by ``dataset build``), sensor and received-field crop; the dataset's
    turbulence scenario must be at the device's wavelength."""
    info = open_dataset(dataset)
    if info.attrs.get("propagation") == "slm":
        raise ValidationError(f"{dataset}: imported captures carry no device model (the forward model of "
                              "compare / retrieve / synth-captures needs a synthetic dataset)")
    cp, _ = read_store_pupil(Path(dataset))
    dev = Device(cp, info.sensor(), info.receiver_crop())
    dev.check_wavelength(info.scenario().wavelength, f"{dataset}: turbulence scenario")
    return dev


def open_store(path: str | Path, mode: str = "r"):
    """The dataset's zarr group, read from the store itself (never from consolidated metadata, which a
    build or an operators run in progress has not refreshed yet)."""
    import zarr

    return zarr.open_group(str(path), mode=mode, use_consolidated=False)


def consolidate(path: str | Path) -> None:
    """Consolidate the store's metadata (what ``xarray.open_zarr`` reads in one request, without a
    warning); done when a build, an import or an operators run completes.  The root attributes are first
    brought to their netCDF-safe form (:func:`store_attrs`), whoever wrote them."""
    import warnings

    import zarr

    g = open_store(path, "r+")
    safe = store_attrs(g.attrs.asdict())  # whatever a writer set since (``complete: True``, a nested block)
    if safe != g.attrs.asdict():
        g.attrs.put(safe)
    with warnings.catch_warnings():  # "not part of the Zarr format 3 specification": xarray reads it all the same
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        zarr.consolidate_metadata(str(path))


def mark_complete(path: str | Path) -> None:
    """Set the store's ``complete`` attribute (1: netCDF has no boolean) at the end of a build or an import."""
    open_store(path, "r+").attrs.update({"complete": 1})


def open_xarray(path: str | Path):
    """The dataset as a strict netCDF-4 ``xarray.Dataset``: each complex variable as ``NAME_real`` and
    ``NAME_imag`` (netCDF has no complex type; h5netcdf writes HDF5's), the channel names as plain strings,
    structured attributes as JSON strings (stores written before their attributes were netCDF-safe
    included).  The store itself opens with plain ``xarray.open_zarr(DATASET)`` (consolidated, every axis
    labelled, CF units and long names, complex ``received``) and writes with plain ``.to_netcdf(FILE)``."""
    import xarray as xr

    open_dataset(path)  # a missing, damaged or unfinished store: one line

    def safe(attrs: dict) -> dict:
        return {k: (v if isinstance(v, (str, int, float)) and not isinstance(v, bool) else
                    json.dumps(v, sort_keys=True, default=str)) for k, v in attrs.items()}

    ds = xr.open_zarr(str(path), consolidated=True)
    for name in [k for k, v in ds.data_vars.items() if np.iscomplexobj(v.dtype.type(0))]:
        v = ds[name]
        ds = ds.drop_vars(name).assign({
            f"{name}_real": v.real.assign_attrs({**v.attrs, "long_name": f"real part of {name}: "
                                                 + v.attrs.get("long_name", name)}),
            f"{name}_imag": v.imag.assign_attrs({**v.attrs, "long_name": f"imaginary part of {name}: "
                                                 + v.attrs.get("long_name", name)})})
    ds = ds.assign_coords(channel=np.asarray(ds["channel"].values, dtype=object))
    ds.attrs = store_attrs(ds.attrs)
    for v in ds.variables.values():
        v.attrs = safe(v.attrs)
    return ds


#: CF attributes of the store's variables (xarray shows them; units "1": dimensionless)
CF_ATTRS = {
    "psf": {"long_name": "PSF tensor: the 8 sensor quadrants, each area-resampled to S x S pixels; each sample's "
                         "8 channels sum to 8", "units": "1"},
    "received": {"long_name": "received complex field on the receiver-aperture crop (vacuum removed)", "units": "1"},
    "psf_power": {"long_name": "power on the 8 quadrants before normalisation, for a 1 W m-2 incident irradiance",
                  "units": "W"},
    "rytov": {"long_name": "nominal Rytov number of the sample's path", "units": "1"},
    "rytov_measured": {"long_name": "log-amplitude variance of the sample's received field", "units": "1"},
    "seed": {"long_name": "seed of the sample's phase screens"},
    "split": {"long_name": "split of the sample", "flag_values": [0, 1, 2], "flag_meanings": "train val test"},
    "sample": {"long_name": "sample index"},
    "channel": {"long_name": "sensor channel: polarisation and quadrant"},
}


def create_store(out: Path, attrs: dict, split: np.ndarray, rytov_fill: float = float("nan")):
    """The store's arrays and attributes; the arrays' sizes are the attributes' (``samples``, ``tensor_size``,
    ``shard_size``, ``received_crop.size``), so the two cannot disagree.  ``rytov_fill``: imported captures
    store an unknown Rytov number as NaN, so their fill value is another (-1) and NaN chunks are written."""
    import zarr
    from zarr.codecs import Crc32cCodec, ZstdCodec

    n, s, shard = int(attrs["samples"]), int(attrs["tensor_size"]), int(attrs["shard_size"])
    a = int(attrs["received_crop"]["size"])

    g = zarr.open_group(str(out), mode="w")
    # every sample's chunk carries a CRC-32C (zarr checks it on each read: a flipped bit is an error, not a
    # wrong number; zstd itself has no checksum here), as every shard index does
    checked = [ZstdCodec(level=0, checksum=False), Crc32cCodec()]
    # fill values no sample can hold: zarr does not store chunks equal to the fill value
    g.create_array("psf", shape=(n, 8, s, s), chunks=(1, 8, s, s), shards=(shard, 8, s, s), dtype="float32",
                   fill_value=float("nan"), dimension_names=("sample", "channel", "row", "col"), compressors=checked)
    g.create_array("received", shape=(n, a, a), chunks=(1, a, a), shards=(shard, a, a), dtype="complex64",
                   fill_value=0j, dimension_names=("sample", "y", "x"), compressors=checked)
    for k, dt, fv in (("psf_power", "float32", float("nan")), ("rytov", "float32", rytov_fill),
                      ("rytov_measured", "float32", rytov_fill), ("seed", "int64", -1)):
        g.create_array(k, shape=(n,), chunks=(shard,), dtype=dt, fill_value=fv, dimension_names=("sample",))
    if attrs.get("closed_loop"):  # each training sample's closed-loop gain (0: an open-loop beacon)
        g.create_array("loop_gain", shape=(n,), chunks=(shard,), dtype="float32", fill_value=float("nan"),
                       dimension_names=("sample",))
        g.create_array("mirror_phase", shape=(n, a, a), chunks=(1, a, a), shards=(shard, a, a), dtype="float32",
                       fill_value=float("nan"), dimension_names=("sample", "y", "x"), compressors=checked)
    sp = g.create_array("split", shape=(n,), chunks=(max(n, 1),), dtype="uint8", fill_value=255,
                        dimension_names=("sample",))
    sp[:] = split
    _write_coordinates(g, n, s, a, attrs)
    for k, v in CF_ATTRS.items():
        if k in g:
            g[k].attrs.update(v)
    g.attrs.update(store_attrs(attrs))
    return g


#: the per-sample arrays xarray shows as coordinates of the data arrays (CF "coordinates" attribute)
SAMPLE_COORDINATES = "rytov rytov_measured seed split"


def _write_coordinates(g, n: int, s: int, a: int, attrs: dict) -> None:
    """Dimension coordinates, so that ``xarray.open_zarr(DATASET)`` labels every axis: ``sample`` (index),
    ``channel`` (0..7 with their names), ``row``/``col`` (tensor pixel index in a quadrant), ``y``/``x``
    (metres on the turbulence grid, the received crop's samples); and the per-sample Rytov numbers,
    seeds and split as coordinates of ``psf``, ``received`` and ``psf_power``."""
    crop = attrs.get("received_crop") or {}
    c = g.create_array("sample", shape=(n,), chunks=(max(n, 1),), dtype="int64", dimension_names=("sample",))
    c[:] = np.arange(n)
    labels = list(CHANNELS)
    ch = g.create_array("channel", shape=(8,), chunks=(8,), dtype=str, dimension_names=("channel",))
    ch[:] = np.array(labels)  # a string coordinate: ds.sel(channel="x-pol QI")
    ch.attrs.update({"labels": labels})
    for k in ("row", "col"):
        r = g.create_array(k, shape=(s,), chunks=(s,), dtype="int32", dimension_names=(k,))
        r[:] = np.arange(s)
        r.attrs.update({"long_name": f"tensor pixel {k} in its quadrant (each quadrant area-resampled to S x S)"})
    if crop.get("dx_m") is not None:
        x = (crop["start"] + np.arange(a) - crop["n_grid"] // 2) * float(crop["dx_m"])
        for k in ("y", "x"):
            r = g.create_array(k, shape=(a,), chunks=(a,), dtype="float64", dimension_names=(k,))
            r[:] = x
            r.attrs.update({"units": "m", "long_name": f"{k} on the turbulence grid (FFT-centred)"})
    for k in ("psf", "received", "psf_power"):
        g[k].attrs.update({"coordinates": SAMPLE_COORDINATES})


# ------------------------------------------------------------------ reading


def read_attrs(out: Path) -> dict | None:
    """The dataset's root attributes, decoded (:func:`decoded_attrs`); None for a folder that is not a
    metadesign dataset."""
    try:
        meta = json.loads((Path(out) / "zarr.json").read_text())
    except (OSError, ValueError):
        return None
    attrs = meta.get("attributes", {}) if isinstance(meta, dict) else {}
    if not isinstance(attrs, dict) or attrs.get("format") != DATASET_FORMAT:
        return None
    return decoded_attrs(attrs)


_ARRAYS = ("psf", "psf_power", "received", "rytov", "rytov_measured", "seed", "split")


@dataclass
class DatasetInfo:
    path: Path
    attrs: dict
    n: int
    tensor_size: int
    split: np.ndarray
    rytov: np.ndarray
    rytov_measured: np.ndarray
    seed: np.ndarray
    bytes_on_disk: int

    def attr(self, key: str):
        """A store attribute the reader needs; a store without it is damaged (one line)."""
        if key not in self.attrs:
            raise ValidationError(f"{self.path}: damaged dataset: the store lacks its {key!r} attribute")
        return self.attrs[key]

    def scenario(self):
        """The turbulence scenario the dataset was made with (from its provenance)."""
        prov = self.attr("provenance")
        if "scenario" not in prov:
            raise ValidationError(f"{self.path}: damaged dataset: its provenance lacks the turbulence scenario")
        return scenario_from_dict(prov["scenario"], f"{self.path} (provenance)")

    def sensor(self) -> SensorSpec:
        """The sensor the dataset's tensors were rendered on (tensor size: the dataset's)."""
        s = self.attr("provenance").get("sensor")
        try:
            return SensorSpec(int(s["width_px"]), int(s["height_px"]), float(s["pixel_um"]) * 1e-6,
                              float(s["magnification"]), float(s["distance_mm"]) * 1e-3, int(self.tensor_size))
        except (TypeError, KeyError, ValueError) as exc:
            raise ValidationError(f"{self.path}: damaged dataset: its provenance has no valid sensor ({exc})") \
                from None

    def crop(self) -> tuple[int, int]:
        """(start, size) of the received-field crop on the turbulence grid."""
        c = self.attr("received_crop")
        try:
            return int(c["start"]), int(c["size"])
        except (TypeError, KeyError, ValueError):
            raise ValidationError(f"{self.path}: damaged dataset: bad received_crop attribute {c!r}") from None

    def receiver_crop(self) -> ReceiverCrop:
        c0, a = self.crop()
        return ReceiverCrop.of_scenario(self.scenario(), c0, a)

    def indices(self, split: str) -> np.ndarray:
        lab = {"train": 0, "val": 1, "test": 2}
        if split == "all":
            return np.arange(self.n)
        return np.nonzero(self.split == lab[split])[0]

    def summary(self) -> dict:
        counts = {k: int(np.sum(self.split == v)) for k, v in (("train", 0), ("val", 1), ("test", 2))}
        def span(x):  # NaN: unknown (captures imported without a Rytov number)
            ok = x[np.isfinite(x)]
            return [float(ok.min()), float(ok.max())] if ok.size else None

        known = self.rytov_measured[np.isfinite(self.rytov_measured)]
        return {"path": str(self.path), "samples": self.n, "tensor": [8, self.tensor_size, self.tensor_size],
                "split_counts": counts, "rytov_nominal": span(self.rytov), "rytov_measured": span(self.rytov_measured),
                "rytov_measured_mean": float(known.mean()) if known.size else None,
                "rytov_unknown": int(self.n - known.size),
                "bytes_on_disk": self.bytes_on_disk, "bytes_per_sample": self.bytes_on_disk / max(self.n, 1),
                "root_seed": self.attrs.get("root_seed"), "version": self.attrs.get("version"),
                "layout_sha256": self.attrs.get("provenance", {}).get("layout_sha256"),
                "library_sha256": self.attrs.get("provenance", {}).get("library_sha256"),
                "complete": bool(self.attrs.get("complete"))}


def open_dataset(path: str | Path) -> DatasetInfo:
    """Open and check a dataset store: format tag, completeness, every array and every shard file present.
    Problems raise one-line :class:`ValidationError`."""
    import zarr

    path = Path(path)
    if not path.is_dir():
        raise ValidationError(f"{path}: a file, not a dataset folder" if path.exists() else
                              f"{path}: no such dataset folder")
    attrs = read_attrs(path)
    if attrs is None:
        raise ValidationError(f"{path}: not a metadesign dataset (no zarr.json with format {DATASET_FORMAT})")
    if not attrs.get("complete"):
        raise ValidationError(f"{path}: incomplete dataset (the build was interrupted): rerun the same "
                              "`metadesign dataset build` to finish it")
    for key in ("samples", "tensor_size", "shard_size", "provenance", "received_crop"):
        if key not in attrs:
            raise ValidationError(f"{path}: damaged dataset: the store lacks its {key!r} attribute")
    n = int(attrs["samples"])
    try:
        g = open_store(path)
        arrays = {k: g[k] for k in _ARRAYS}
    except (KeyError, ValueError, OSError, FileNotFoundError) as exc:
        raise ValidationError(f"{path}: truncated or damaged dataset ({exc.__class__.__name__}: {exc})") from None
    for k, a in arrays.items():
        if a.shape[0] != n:
            raise ValidationError(f"{path}: array {k} has {a.shape[0]} samples, expected {n}")
        n_files = sum(1 for p in (path / k / "c").rglob("*") if p.is_file() and p.stat().st_size > 0) \
            if (path / k / "c").exists() else 0
        grid = int(np.ceil(n / (a.shards or a.chunks)[0]))
        if n_files < grid:
            raise ValidationError(f"{path}: truncated dataset: array {k} has {n_files} of {grid} chunk files")
    try:
        small = {k: np.asarray(arrays[k][:]) for k in ("split", "rytov", "rytov_measured", "seed")}
    except Exception as exc:  # a damaged chunk: zarr/numcodecs raise many kinds
        raise ValidationError(f"{path}: damaged dataset ({exc.__class__.__name__}: {str(exc)[:100]})") from None
    size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return DatasetInfo(path, attrs, n, int(attrs["tensor_size"]), small["split"], small["rytov"],
                       small["rytov_measured"], small["seed"], size)


#: |sum of a sample's 8 normalised channels - 8| above which a PSF tensor is damaged (float32 sums: ~1e-5)
PSF_SUM_TOL = 1e-3


def damaged(path: str | Path, i: int, shard_size: int, exc: BaseException | str) -> ValidationError:
    """The one-line error of an unreadable or corrupt sample: names the sample, its shard and the remedy."""
    why = exc if isinstance(exc, str) else f"{exc.__class__.__name__}: {str(exc).strip().splitlines()[0][:80]}" \
        if str(exc).strip() else exc.__class__.__name__
    return ValidationError(f"{path}: damaged dataset: sample {i} (shard {i // max(int(shard_size), 1)}) is unreadable "
                           f"or corrupt ({why}); `metadesign dataset verify {path}` lists every damaged shard")


def check_psf(psf: np.ndarray) -> str | None:
    """Why a stored (noise-free, normalised) PSF tensor is corrupt, or None: every value finite, the 8
    channels summing to 8 (the normalisation every writer applies; imported, dark-subtracted captures may
    hold small negative values)."""
    if not np.isfinite(psf).all():
        return "non-finite PSF values"
    s = float(psf.sum(dtype=np.float64))
    if abs(s - 8.0) > PSF_SUM_TOL * 8 and s != 0.0:  # 0: a sample without light is stored unnormalised
        return f"PSF channels sum to {s:.6g}, not 8"
    return None


def verify_dataset(path: str | Path, progress: Callable[[int, int], None] | None = None) -> dict:
    """Read every sample of every array of a dataset and check it (decodes, checksums of the shard
    indexes, finite values, the PSF normalisation); returns the damaged shards, never raises on damage."""
    import zarr

    info = open_dataset(path)
    g = open_store(path)
    shard = int(info.attrs["shard_size"])
    names = [k for k in ("psf", "received", "psf_power", OPERATOR_ARRAY) if k in g]
    bad: dict[int, str] = {}
    n = info.n
    for j0 in range(0, n, shard):
        j1 = min(n, j0 + shard)
        k = j0 // shard
        for name in names:
            if k in bad:
                break
            try:
                arr = np.asarray(g[name][j0:j1])
            except Exception as exc:  # zarr/numcodecs raise many kinds on damaged chunks
                bad[k] = f"{name}: {exc.__class__.__name__}"
                continue
            if name == "psf":
                for r, x in enumerate(arr):
                    why = check_psf(x)
                    if why:
                        bad[k] = f"psf of sample {j0 + r}: {why}"
                        break
            elif np.iscomplexobj(arr) or np.issubdtype(arr.dtype, np.floating):
                if not np.isfinite(arr).all():
                    bad[k] = f"{name}: non-finite values"
        if progress:
            progress(j1, n)
    return {"path": str(path), "samples": n, "shards": -(-n // shard), "arrays": names,
            "damaged_shards": [{"shard": k, "samples": [k * shard, min(n, (k + 1) * shard) - 1], "problem": v}
                               for k, v in sorted(bad.items())], "ok": not bad}


"""Stage 6a, the dataset store: seeded, sharded datasets of 8-PSF frames from scintillated beacons
through the as-fabricated metasurface (zarr v3), built on a local process pool
or a Dask cluster, resumable after SIGKILL; opened, verified and asked for its device here (reading
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

Sample ``i`` depends only on (root seed, i, recipe): the screens' seed is
``SeedSequence(root, spawn_key=(0, i))``, its Rytov number is drawn from
``SeedSequence(root, spawn_key=(1, i))``; so any worker count or scheduler writes the same arrays.
Big arrays are sharded (one shard file per block of ``shard_size`` samples, one inner chunk per
sample, so a reader decodes only the sample it needs).  A shard is finished when its marker
``OUT/.shards/NNNNNN`` exists (written atomically after its arrays); a re-run continues from the
unfinished shards; ``complete`` is set in the attributes at the end.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..config import ConfigError, Param, Section, load_toml, parse
from ..design.recipe import load_design_recipe
from ..design.store import load_design, run_design
from ..io import read_npz
from ..outputs import Need, product
from ..layouts.make import make_layout
from ..library.locate import file_sha256
from ..tasks import TaskFolder, content_key, run_resumable
from ..parallel import dask_client
from ..paths import resolve_against
from ..sensing.device import Device, ReceiverCrop, load_pupil
from ..sensing.forward import CoarsePupil
from ..sensing.sensor import CHANNELS, SensorSpec
from ..turbulence.system import build_system
from ..turbulence.chain import BeaconChain
from ..turbulence.path import check_sampling, solve_path
from ..turbulence.scenario import load_scenario, scenario_from_dict
from ..validation import ValidationError

__all__ = ["open_xarray", "open_store", "DatasetRecipe", "load_dataset_recipe", "dataset_recipe_from_dict", "build_dataset", "open_dataset",
           "DatasetInfo", "DATASET_FORMAT", "sample_seed", "sample_rytov", "make_sample", "ShardContext",
           "received_crop", "measured_rytov", "normalise_psf", "load_device", "expected_sizes", "verify_dataset", "check_psf", "damaged"]

DATASET_FORMAT = "metadesign.dataset/1"
_MAX_SEED = 2**63 - 1

#: the network input's side S (8 x S x S), one definition for every recipe that sets it
TENSOR_SIZE = Param("tensor_size", int, 256, lo=8, hi=1024, help="network input: 8 x S x S PSF tensors")

SECTIONS = (
    Section("dataset", (
        Param("layout", str, None, help="OASIS/GDS layout (relative to the recipe)"),
        Param("design", str, None, help="design recipe that builds the layout when it is missing"),
        Param("sensor", str, "paper.toml"),
        Param("turbulence", str, "turbulence.toml"),
        Param("samples", int, lo=1, hi=10_000_000),
        Param("rytov_min", float, 0.25, lo=0, open_lo=True, hi=5),
        Param("rytov_max", float, 0.6, lo=0, open_lo=True, hi=5),
        Param("rytov_values", list, None, lo=0, open_lo=True, hi=5),
        Param("split", list, [0.9, 0.05, 0.05], lo=0, hi=1),
        Param("seed", int, 0, lo=0, hi=_MAX_SEED),
        TENSOR_SIZE,
        Param("shard_size", int, 64, lo=1, hi=4096),
    )),
    Section("fabrication", (
        Param("bias_x_nm", float, 0.0, lo=-200, hi=200),
        Param("bias_y_nm", float, 0.0, lo=-200, hi=200),
        Param("jitter_nm", float, 0.0, lo=0, hi=100),
        Param("corner_nm", float, 0.0, lo=0, hi=500),
        Param("seed", int, 0, lo=0, hi=_MAX_SEED),
        Param("height_nm", float, 0.0, lo=-500, hi=500, help="etch depth error (needs fab_library)"),
        Param("sidewall_deg", float, 90.0, lo=60, hi=90, help="sidewall angle (needs fab_library)"),
        Param("height_gradient_nm", float, 0.0, lo=-500, hi=500),
        Param("sidewall_gradient_deg", float, 0.0, lo=-30, hi=30),
        Param("fab_library", str, None, help="library with height / sidewall axes (relative to the recipe)"),
        Param("coupling", str, None, choices=("lpa", "supercell"),
              help="supercell coupling of the pillars (default: the sensing recipe's pupil.coupling)"),
        Param("coupling_model", str, None, help="the coupling model (relative to the recipe; default: the one "
                                                "fitted against the layout's library)"),
    ), optional=True),
)


@dataclass(frozen=True)
class DatasetRecipe:
    name: str
    source: Path | None
    layout: Path | None
    design: Path | None
    sensor: Path
    turbulence: Path
    samples: int
    rytov_range: tuple[float, float]
    rytov_values: tuple[float, ...] | None
    split: tuple[float, float, float]
    seed: int
    tensor_size: int
    shard_size: int
    fabrication: dict
    raw: dict = field(repr=False, default_factory=dict)

    def default_output(self) -> Path:
        return (self.source.parent if self.source else Path.cwd()) / self.name

    def with_fabrication(self, name: str, **kinds) -> "DatasetRecipe":
        """The same dataset through a device made with another process: ``kinds`` are the recipe's
        [fabrication] keys (:attr:`metadesign.sensing.transmission.Perturbation.KINDS`, ``fab_library``),
        checked as a recipe is."""
        raw = json.loads(json.dumps(self.raw))
        raw["fabrication"] = dict(kinds)
        return dataset_recipe_from_dict(raw, name, self.source)

    def declared_key(self) -> str:
        """The recipe as declared, by content: its tables and the recipes and library it names (parsed TOML,
        so a comment edit keeps the key; a built layout is a product of the design recipe and is left out).
        A committed result records it (``made_with``) and a test checks it against the committed recipe;
        :attr:`recipe_hash` (what shapes the bytes) also needs the built layout."""
        def toml(p):
            return load_toml(p) if p is not None and Path(p).is_file() else None

        parts = {"recipe": json.loads(json.dumps(self.raw, default=str)), "sensor": toml(self.sensor),
                 "turbulence": toml(self.turbulence), "design": toml(self.design)}
        if self.design is not None and Path(self.design).is_file():
            lib = load_design_recipe(self.design).library_path
            parts["library_sha256"] = file_sha256(lib) if Path(lib).is_file() else None
        return content_key(parts)

    def with_samples(self, n: int) -> "DatasetRecipe":
        raw = json.loads(json.dumps(self.raw))
        raw.setdefault("dataset", {})["samples"] = n
        return replace(self, samples=n, raw=raw)


def dataset_recipe_from_dict(data: dict, name: str = "dataset", source: Path | None = None) -> DatasetRecipe:
    v = parse(data, SECTIONS, str(source) if source else "recipe")
    d, fab = v["dataset"], v["fabrication"]
    base = source.parent if source else Path.cwd()

    def rel(p):
        if p is None:
            return None
        p = Path(p)
        return p if p.is_absolute() else base / p

    if d["layout"] is None and d["design"] is None:
        raise ConfigError("dataset.layout", "missing; give the layout (OASIS) or a design recipe to build one")
    if d["rytov_min"] >= d["rytov_max"] and d["rytov_values"] is None:
        raise ConfigError("dataset.rytov_min", f"must be < dataset.rytov_max ({d['rytov_max']:g})")
    vals = d["rytov_values"]
    if vals is not None and not vals:
        raise ConfigError("dataset.rytov_values", "expected at least one Rytov number")
    split = d["split"]
    if len(split) != 3 or abs(sum(split) - 1) > 1e-6:
        raise ConfigError("dataset.split", f"expected three fractions [train, val, test] summing to 1, got {list(split)}")
    return DatasetRecipe(
        name=name, source=source, layout=rel(d["layout"]), design=rel(d["design"]), sensor=rel(d["sensor"]),
        turbulence=rel(d["turbulence"]), samples=d["samples"], rytov_range=(d["rytov_min"], d["rytov_max"]),
        rytov_values=tuple(vals) if vals is not None else None, split=tuple(split), seed=d["seed"],
        tensor_size=d["tensor_size"], shard_size=d["shard_size"], fabrication=fab, raw=data)


def load_dataset_recipe(path: str | Path) -> DatasetRecipe:
    path = Path(path)
    return dataset_recipe_from_dict(load_toml(path), name=path.stem, source=path)


# ----------------------------------------------------------------- samples


def sample_seed(root: int, i: int) -> int:
    """The screens' seed of sample ``i`` (63-bit, storable as int64)."""
    return int(np.random.SeedSequence(root, spawn_key=(0, i)).generate_state(1, np.uint64)[0] & np.uint64(_MAX_SEED))


def sample_rytov(root: int, i: int, rytov_range, rytov_values) -> float:
    rng = np.random.default_rng(np.random.SeedSequence(root, spawn_key=(1, i)))
    if rytov_values:
        return float(rytov_values[int(rng.integers(len(rytov_values)))])
    return float(rng.uniform(*rytov_range))


def split_labels(root: int, n: int, fractions) -> np.ndarray:
    perm = np.random.default_rng(np.random.SeedSequence(root, spawn_key=(2,))).permutation(n)
    n_train = int(round(fractions[0] * n))
    n_val = int(round(fractions[1] * n))
    lab = np.full(n, 2, np.uint8)
    lab[perm[:n_train]] = 0
    lab[perm[n_train:n_train + n_val]] = 1
    return lab


#: the stored bucket operators' array (``metadesign dataset operators``, :mod:`.operators`)
OPERATOR_ARRAY = "pib_operator"


def operator_info(attrs: dict) -> dict | None:
    """The store's ``pib_operator`` attribute block, or None."""
    return attrs.get(OPERATOR_ARRAY)


def has_operators(attrs: dict, split: str) -> bool:
    """Whether every sample of ``split`` has a stored operator (a finished ``dataset operators`` run)."""
    info = operator_info(attrs)
    return bool(info and info.get("complete") and split in info.get("splits", ()))


def received_crop(sc) -> tuple[int, int]:
    """(start index, size) of the square crop of the turbulence grid holding the receiver aperture
    (FFT-centred grid: the centre is sample n/2)."""
    half = int(np.floor(sc.receiver_aperture / 2 / sc.dx + 1e-9))
    return sc.n_grid // 2 - half, 2 * half + 1


@dataclass
class ShardContext:
    """Everything a worker needs to make a shard (no layout: the device is its coarse pupil)."""

    pupil: object  # CoarsePupil
    sensing: object  # SensingRecipe (tensor_size of the recipe)
    scenario: object  # Scenario
    aperture: float  # metasurface aperture (m)
    out: str
    root_seed: int
    n: int
    shard_size: int
    rytov_range: tuple
    rytov_values: tuple | None
    _chain: object = None
    kind = "shard"

    def make(self, shard: int) -> dict:
        return make_shard(self, shard)

    def chain(self):
        if self._chain is None:
            self._chain = BeaconChain(self.pupil, self.sensing, self.scenario, self.aperture)
        return self._chain


def make_sample(ctx: ShardContext, i: int) -> dict:
    """Sample ``i`` of the dataset: arrays as stored, and the time spent per step."""
    t0 = time.perf_counter()
    chain = ctx.chain()
    seed = sample_seed(ctx.root_seed, i)
    rytov = sample_rytov(ctx.root_seed, i, ctx.rytov_range, ctx.rytov_values)
    s = chain.sample(seed, rytov)
    t1 = time.perf_counter()
    c0, a = received_crop(chain.turbulence.sc)
    rec = s.received[c0:c0 + a, c0:c0 + a]
    psf, power = normalise_psf(s.tensor)
    t2 = time.perf_counter()
    return {"psf": psf, "psf_power": power, "received": rec.astype(np.complex64), "rytov": rytov,
            "rytov_measured": measured_rytov(rec, chain.turbulence.aperture[c0:c0 + a, c0:c0 + a]), "seed": seed,
            "timings": {**s.timings, "other": (t2 - t1) + (t1 - t0) - sum(s.timings.values())}}


def measured_rytov(received: np.ndarray, aperture: np.ndarray) -> float:
    """A sample's own Rytov number: the variance of the log-amplitude of its received field over the
    receiver aperture (its crop)."""
    return float(np.var(np.log(np.maximum(np.abs(received[aperture]), 1e-30))))


def normalise_psf(tensor: np.ndarray) -> tuple[np.ndarray, float]:
    """The network's input normalisation: the 8 channels sum to 8 (each ~1); returns (psf, raw total)."""
    power = float(tensor.sum())
    return ((tensor * (8.0 / power)).astype(np.float32) if power > 0 else tensor.astype(np.float32)), power


def shard_folder(out: Path, kind: str = "shards") -> TaskFolder:
    """The task folder of a store's shards (``OUT/.shards/NNNNNN.json``: a shard's marker, written once its
    arrays are in the store)."""
    return TaskFolder(Path(out) / f".{kind}")


def shard_name(shard: int) -> str:
    return f"{shard:06d}"


def make_shard(ctx: ShardContext, shard: int) -> dict:
    """Compute shard ``shard`` and write it into the store (its marker follows: :func:`run_shards`).

    BLAS runs on one thread here whatever the process was started with: a multi-threaded complex matrix
    product sums in another order (~1e-6 relative), and the same seed must give the same bytes."""
    import zarr
    from threadpoolctl import threadpool_limits

    i0 = shard * ctx.shard_size
    i1 = min(ctx.n, i0 + ctx.shard_size)
    with threadpool_limits(limits=1):
        rows = [make_sample(ctx, i) for i in range(i0, i1)]
    t0 = time.perf_counter()
    g = open_store(ctx.out, "r+")
    g["psf"][i0:i1] = np.stack([r["psf"] for r in rows])
    g["received"][i0:i1] = np.stack([r["received"] for r in rows])
    for k, dt in (("psf_power", np.float32), ("rytov", np.float32), ("rytov_measured", np.float32),
                  ("seed", np.int64)):
        g[k][i0:i1] = np.array([r[k] for r in rows], dt)
    t_store = time.perf_counter() - t0
    tim = {k: float(sum(r["timings"][k] for r in rows)) for k in rows[0]["timings"]}
    tim["storage"] = t_store
    return {"shard": shard, "samples": i1 - i0, "timings": tim}


# ------------------------------------------------------------ the builder


def ensure_layout(recipe: DatasetRecipe, log: Callable[[str], None]) -> Path:
    """The recipe's layout; built from its design recipe (design + OASIS + exact verify) if missing."""
    if recipe.layout is not None and recipe.layout.exists():
        return recipe.layout
    if recipe.design is None:
        raise ValidationError(f"dataset.layout: {recipe.layout}: no such layout (give dataset.design to build it)")

    dr = load_design_recipe(recipe.design)
    out = recipe.layout.parent if recipe.layout is not None else dr.default_output()
    target = recipe.layout or out / "layout.oas"
    log(f"building the layout {target} from {recipe.design} (design, OASIS, exact read-back)")
    with product(out, "design", {"dataset.design": recipe.design, "design.library": dr.library_path},
                 also=(target, target.with_name(target.name + ".json"))):
        _, folder = run_design(dr, out)
        made = make_layout(load_design(folder), target, drc=False)
    if not made.exact:
        raise ValidationError(f"{target}: the layout read back differs from the design: {made.verify['problems'][:2]}")
    return target


def _device_pupil(fab, sensing, pert, store: Path, layout_sha: str, progress=None):
    """The device's coarse pupil, kept in the dataset's store as the zarr group ``device`` (keyed by
    layout, library, perturbation, sensor: a resumed build reuses it)."""
    key = {"layout_sha256": layout_sha, "library_sha256": fab.lib.identity, "perturbation": pert.to_dict(),
           "distance_m": sensing.sensor.distance, "pupil_grid": sensing.pupil_grid}
    if fab.fab_lib is not None:
        key["fab_library_sha256"] = fab.fab_lib.identity
    try:
        cp, stored = read_store_pupil(store)
        if stored == key:
            return cp
    except ValidationError:
        pass
    cp = fab.pupil(sensing.sensor.distance, sensing.pupil_grid, pert, progress)
    write_store_pupil(store, cp, key)
    return cp


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


def expected_sizes(recipe: DatasetRecipe) -> tuple[int, int]:
    """(tensor size, received-crop size) of the dataset a recipe would build (no build): what a model
    must take and give to be trained or evaluated on it."""
    return recipe.tensor_size, received_crop(load_scenario(recipe.turbulence))[1]


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


def _recipe_hash(parts: dict) -> str:
    """The dataset's content key (what shapes its bytes): :func:`metadesign.tasks.content_key`."""
    return content_key(parts)  # = sha256 of json.dumps(parts, sort_keys=True): the same value as before


def open_store(path: str | Path, mode: str = "r"):
    """The dataset's zarr group, read from the store itself (never from consolidated metadata, which a
    build or an operators run in progress has not refreshed yet)."""
    import zarr

    return zarr.open_group(str(path), mode=mode, use_consolidated=False)


def consolidate(path: str | Path) -> None:
    """Consolidate the store's metadata (what ``xarray.open_zarr`` reads in one request, without a
    warning); done when a build, an import or an operators run completes."""
    import warnings

    import zarr

    with warnings.catch_warnings():  # "not part of the Zarr format 3 specification": xarray reads it all the same
        warnings.filterwarnings("ignore", message="Consolidated metadata")
        zarr.consolidate_metadata(str(path))


def open_xarray(path: str | Path):
    """The dataset as a netCDF-ready ``xarray.Dataset``: structured attributes (the provenance, ...) as
    JSON strings, each complex variable as ``NAME_real`` and ``NAME_imag`` (netCDF has no complex type),
    the channel names as plain strings; so ``open_xarray(DATASET).to_netcdf(FILE)`` writes a netCDF-4 file
    (h5netcdf).  The store itself opens with plain ``xarray.open_zarr(DATASET)`` (consolidated, every axis
    labelled, CF units and long names, complex ``received``)."""
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
    ds.attrs = safe(ds.attrs)
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


def _create_store(out: Path, n: int, s: int, shard: int, a: int, attrs: dict, split: np.ndarray,
                  rytov_fill: float = float("nan")):
    """The store's arrays and attributes.  ``rytov_fill``: imported captures store an unknown Rytov number as
    NaN, so their fill value is another (-1) and NaN chunks are written."""
    import zarr
    from zarr.codecs import Crc32cCodec, ZstdCodec

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
    sp = g.create_array("split", shape=(n,), chunks=(max(n, 1),), dtype="uint8", fill_value=255,
                        dimension_names=("sample",))
    sp[:] = split
    _write_coordinates(g, n, s, a, attrs)
    for k, v in CF_ATTRS.items():
        if k in g:
            g[k].attrs.update(v)
    g.attrs.update(attrs)
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


def _make_shard(ctx, i: int) -> tuple[str, dict]:
    return shard_name(i), ctx.make(i)


def run_shards(ctx, shards: dict[str, int], folder: TaskFolder, workers: int, scheduler: str | None = None,
               client=None, weight=lambda name: 1, progress=None, log=lambda s: None):
    """``ctx.make(i)`` for every shard not yet marked done in ``folder`` (a :class:`ShardContext` or the
    operators' context), on the resumable engine (:func:`metadesign.tasks.run_resumable`): the context goes
    to each worker once; returns ``(results by name, names computed now)``."""
    return run_resumable(_make_shard, shards, folder, store="marker", workers=workers, shared=ctx, client=client,
                         scheduler=scheduler, dask_key=f"metadesign-{ctx.kind}-{ctx.out}", weight=weight,
                         progress=progress, log=log, unit="sample")


def build_dataset(recipe: DatasetRecipe, out: Path | None = None, workers: int = 1, scheduler: str | None = None,
                  overwrite: bool = False, progress: Callable[[int, int], None] | None = None,
                  log: Callable[[str], None] = lambda s: None, client=None) -> dict:
    """Build (or resume) the dataset of ``recipe`` into ``out``; returns a report.

    ``scheduler``: address of a running Dask scheduler (or ``client``, a ``dask.distributed.Client``);
    default: a local pool of ``workers`` spawned processes."""
    out = Path(out or recipe.default_output())
    if out.exists() and not out.is_dir():
        raise ValidationError(f"-o/--output {out}: exists and is not a folder")
    f = recipe.fabrication
    base = recipe.source.parent if recipe.source else Path.cwd()  # what the recipe's paths are relative to
    need = None
    if overwrite or not (out / "zarr.json").exists():  # a new store (a resumed one holds its arrays already)
        s, a = expected_sizes(recipe)  # the arrays uncompressed: an upper bound
        need = Need(disk=recipe.samples * (8 * s * s * 4 + a * a * 8 + 64),
                    what="fewer dataset.samples, a smaller tensor_size or another output")
    with product(out, "dataset", {"dataset.layout": recipe.layout, "dataset.design": recipe.design,
                                  "dataset.sensor": recipe.sensor, "dataset.turbulence": recipe.turbulence,
                                  "the recipe": recipe.source,
                                  "fabrication.coupling_model": resolve_against(base, f["coupling_model"]),
                                  "fabrication.fab_library": resolve_against(base, f["fab_library"])}, need=need):
        own = None
        if scheduler is not None and client is None:  # an unreachable scheduler fails before anything is written
            client = own = dask_client(scheduler)
        try:
            return _build_dataset(recipe, out, workers, client is not None, overwrite, progress, log, client)
        finally:
            if own is not None:
                own.close()


def _build_dataset(recipe: DatasetRecipe, out: Path, workers: int, dask: bool, overwrite: bool, progress, log,
                   client) -> dict:
    existing = _read_attrs(out) if (out / "zarr.json").exists() else None  # (a foreign folder: refused already)
    scenario = load_scenario(recipe.turbulence)
    for r in ([*recipe.rytov_values] if recipe.rytov_values else list(recipe.rytov_range)):
        sc = replace(scenario, rytov=r)
        rep = check_sampling(sc, solve_path(sc))
        if not rep.ok:
            raise ValidationError(f"dataset: Rytov {r:g}: infeasible turbulence sampling: {rep.failures[0]}")
    layout = ensure_layout(recipe, log)
    layout_sha = file_sha256(layout)
    system = build_system(layout, recipe.sensor, scenario, recipe.fabrication,
                          recipe.source.parent if recipe.source else Path.cwd(), recipe.tensor_size)
    fab, sensing, pert = system.device, system.sensing, system.perturbation
    parts = {"format": DATASET_FORMAT, "recipe": recipe.raw, "sensor": sensing.sensor.to_dict(),
             "pupil_grid": sensing.pupil_grid, "scenario": scenario.to_dict(), "layout_sha256": layout_sha,
             "library_sha256": fab.lib.identity, "perturbation": pert.to_dict()}
    if fab.fab_lib is not None:
        parts["fab_library_sha256"] = fab.fab_lib.identity
    if fab.coupling_card is not None:  # absent for the LPA: those datasets keep their hash
        parts["coupling_model_sha256"] = fab.coupling_card["weights_sha256"]
    rhash = _recipe_hash(parts)
    if existing is not None and existing.get("recipe_hash") != rhash:
        if not overwrite:
            raise ValidationError(f"{out}: holds a dataset built from a different recipe (or device); "
                                  "use --overwrite to replace it, or -o for another folder")
        log(f"--overwrite: removing the dataset in {out}")
        shutil.rmtree(out)
        existing = None
    n, shard = recipe.samples, recipe.shard_size
    n_shards = (n + shard - 1) // shard
    t_start = time.perf_counter()
    c0, a = received_crop(scenario)
    out.mkdir(exist_ok=True)
    if existing is None:
        attrs = {
            "format": DATASET_FORMAT, "version": __version__, "complete": False, "recipe_hash": rhash,
            "recipe_key": recipe.declared_key(), "name": recipe.name, "samples": n, "shard_size": shard, "n_shards": n_shards,
            "tensor_size": recipe.tensor_size, "root_seed": recipe.seed, "split_fractions": list(recipe.split),
            "rytov": {"range": list(recipe.rytov_range), "values": list(recipe.rytov_values or []) or None},
            "provenance": {**parts, "layout": str(layout), "design": fab.layout.provenance.get("design"),
                           "channels": fab.layout.provenance.get("channels")},
            "received_crop": {"start": c0, "size": a, "n_grid": scenario.n_grid, "dx_m": scenario.dx,
                              "centring": "FFT-centred grid: x = (i - n/2) dx; crop rows/cols start..start+size"},
            "normalisation": "psf: each sample's 8 channels sum to 8 (psf_power holds the raw total)",
            "seeds": "screens: Turbulence.at_rytov(rytov).screens(seed); seed_i = SeedSequence(root, "
                     "spawn_key=(0, i)) & (2^63-1); Rytov from SeedSequence(root, spawn_key=(1, i))",
            "split_labels": {"0": "train", "1": "val", "2": "test"},
        }
        _create_store(out, n, recipe.tensor_size, shard, a, attrs, split_labels(recipe.seed, n, recipe.split))
    cp = _device_pupil(fab, sensing, pert, out, layout_sha)  # after the store (mode "w")
    folder = shard_folder(out)
    shards = {shard_name(i): i for i in range(n_shards)}
    size = {shard_name(i): min(n, (i + 1) * shard) - i * shard for i in range(n_shards)}
    done = {nm for nm in shards if folder.marked(nm) is not None}
    ctx = ShardContext(cp, sensing, scenario, fab.n_cells * fab.period, str(out), recipe.seed, n, shard,
                       recipe.rytov_range, recipe.rytov_values)
    log(f"dataset {recipe.name}: {n} samples in {n_shards} shards ({len(done)} done), "
        f"tensor 8x{recipe.tensor_size}^2 -> {out}")
    timings: dict = {}
    t_sweep = time.perf_counter()
    results, computed_now = run_shards(ctx, shards, folder, workers, client=client, weight=size.__getitem__,
                                       progress=progress)
    for nm in computed_now:
        for k, v in results[nm]["timings"].items():
            timings[k] = timings.get(k, 0.0) + v
    sweep = time.perf_counter() - t_sweep
    open_store(out, "r+").attrs.update({"complete": True})
    folder.remove()
    consolidate(out)
    info = open_dataset(out)
    computed = sum(size[nm] for nm in computed_now)
    return {"output": str(out), "samples": n, "shards": n_shards, "resumed_shards": len(done),
            "computed_samples": computed, "seconds": time.perf_counter() - t_start, "sweep_seconds": sweep,
            "per_sample_seconds": {k: v / max(computed, 1) for k, v in timings.items()},
            "workers": "dask" if dask else workers, **info.summary()}


# ------------------------------------------------------------------ reading


def _read_attrs(out: Path) -> dict | None:
    try:
        meta = json.loads((Path(out) / "zarr.json").read_text())
    except (OSError, ValueError):
        return None
    attrs = meta.get("attributes", {}) if isinstance(meta, dict) else {}
    return attrs if attrs.get("format") == DATASET_FORMAT else None


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
        raise ValidationError(f"{path}: no such dataset folder")
    attrs = _read_attrs(path)
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


"""Stage 6a, the dataset recipe: its TOML tables parsed and checked (:class:`DatasetRecipe`), and what the
recipe alone decides of every sample, before anything is computed: the screens' seed and Rytov number of
sample ``i`` (:func:`sample_seed`, :func:`sample_rytov`), the train / val / test split
(:func:`split_labels`) and the sizes of the arrays (:func:`expected_sizes`).

Sample ``i`` depends only on (root seed, i, recipe): the screens' seed is
``SeedSequence(root, spawn_key=(0, i))``, its Rytov number is drawn from
``SeedSequence(root, spawn_key=(1, i))``; so any worker count or scheduler writes the same arrays
(the build: :mod:`.dataset_build`; the store: :mod:`.dataset_store`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..config import ConfigError, Param, Section, load_toml, parse
from ..design.recipe import load_design_recipe
from ..tasks import content_key, file_key
from ..turbulence.scenario import load_scenario

__all__ = ["DatasetRecipe", "load_dataset_recipe", "dataset_recipe_from_dict", "TENSOR_SIZE", "SECTIONS",
           "sample_seed", "sample_rytov", "sample_loop_gain", "split_labels", "received_crop", "expected_sizes"]

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
        Param("coupling", str, None, choices=("lpa", "supercell", "coupling", "peds"),
              help="supercell coupling of the pillars (default: the sensing recipe's pupil.coupling)"),
        Param("coupling_model", str, None, help="the coupling model (relative to the recipe; default: the one "
                                                "fitted against the layout's library)"),
    ), optional=True),
    Section("closed_loop", (
        Param("fraction", float, 0.0, lo=0, hi=1, help="of the training and validation splits' beacons"),
        Param("gain", float, [0.0, 1.0], lo=0, hi=1, span=True),
        Param("actuators", int, 12, lo=2, hi=128),
        Param("coupling", float, 0.15, lo=0, hi=1, open_lo=True, open_hi=True),
        Param("regularisation", float, 1e-3, lo=0, hi=1),
    ), optional=True, help="beacons as a closed loop's sensor sees them: a fraction of the training and "
                           "validation splits' received fields times the conjugate of the mirror's phase, gain "
                           "x its fit of the beacon's unwrapped phase (dataset_build.converged_mirror; gain drawn "
                           "per sample from [lo, "
                           "hi]), rendered through the loop's path (Device.pupil_field); the mirror's phase is "
                           "stored (mirror_phase), so NPiB counts it; the test split stays open loop"),
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
    closed_loop: dict = field(default_factory=dict)  # [closed_loop] ({} or fraction 0: every beacon open loop)

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
            parts["library_sha256"] = file_key(lib) if Path(lib).is_file() else None
        return content_key(parts)

    def with_samples(self, n: int) -> "DatasetRecipe":
        raw = json.loads(json.dumps(self.raw))
        raw.setdefault("dataset", {})["samples"] = n
        return replace(self, samples=n, raw=raw)


def dataset_recipe_from_dict(data: dict, name: str = "dataset", source: Path | None = None) -> DatasetRecipe:
    v = parse(data, SECTIONS, str(source) if source else "recipe")
    d, fab = v["dataset"], v["fabrication"]
    cl = dict(v["closed_loop"]) if "closed_loop" in data else {}
    if cl and cl["fraction"] > 0 and d["split"][0] <= 0:
        raise ConfigError("closed_loop.fraction", "draws training beacons; dataset.split has no training split")
    if cl and cl["gain"][1] <= 0 and cl["fraction"] > 0:
        raise ConfigError("closed_loop.gain", "must reach above 0 (a gain of 0 is an open-loop beacon)")
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
        tensor_size=d["tensor_size"], shard_size=d["shard_size"], fabrication=fab, raw=data,
        closed_loop=cl if cl.get("fraction", 0) > 0 else {})


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


def sample_loop_gain(root: int, i: int, split_label: int, closed_loop: dict) -> float:
    """The closed-loop gain of sample ``i`` (0: an open-loop beacon): a training or validation sample
    (``split_label`` 0 or 1) is a residual with probability ``closed_loop["fraction"]``, its gain uniform in
    ``closed_loop["gain"]`` (its own stream, spawn key (3, i): the screens, Rytov numbers and split are the
    same as without it); a test sample never is."""
    if not closed_loop or closed_loop.get("fraction", 0) <= 0 or split_label not in (0, 1):
        return 0.0
    rng = np.random.default_rng(np.random.SeedSequence(root, spawn_key=(3, i)))
    u, g = rng.random(2)
    lo, hi = closed_loop["gain"]
    return float(lo + (hi - lo) * g) if u < closed_loop["fraction"] else 0.0


def split_labels(root: int, n: int, fractions) -> np.ndarray:
    perm = np.random.default_rng(np.random.SeedSequence(root, spawn_key=(2,))).permutation(n)
    n_train = int(round(fractions[0] * n))
    n_val = int(round(fractions[1] * n))
    lab = np.full(n, 2, np.uint8)
    lab[perm[:n_train]] = 0
    lab[perm[n_train:n_train + n_val]] = 1
    return lab


def received_crop(sc) -> tuple[int, int]:
    """(start index, size) of the square crop of the turbulence grid holding the receiver aperture
    (FFT-centred grid: the centre is sample n/2)."""
    half = int(np.floor(sc.receiver_aperture / 2 / sc.dx + 1e-9))
    return sc.n_grid // 2 - half, 2 * half + 1



def expected_sizes(recipe: DatasetRecipe) -> tuple[int, int]:
    """(tensor size, received-crop size) of the dataset a recipe would build (no build): what a model
    must take and give to be trained or evaluated on it."""
    return recipe.tensor_size, received_crop(load_scenario(recipe.turbulence))[1]



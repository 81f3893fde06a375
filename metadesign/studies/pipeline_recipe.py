"""The pipeline recipe (``metadesign run RECIPE``): its schema and one typed, frozen dataclass per section.

The TOML format is the schema :data:`SECTIONS` (validated by :func:`metadesign.config.parse`: one line
naming the field and what is allowed; NaN and infinities are bad values); :func:`load_pipeline_recipe`
turns it into a :class:`PipelineRecipe` once: paths relative to the recipe, etch biases and jitters in
nm, the library's re-check cells as integer pairs.  The stages read its fields (and the derived
``*_content`` properties, what shapes a stage's result) and never a string key."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..config import Param, Section, load_toml, parse
from ..reconstruction.dataset import TENSOR_SIZE
from ..validation import ValidationError

__all__ = ["SECTIONS", "DATASET_SECTIONS", "PipelineRecipe", "PipelineSection", "DatasetSection", "TrainSection",
           "EvaluateSection", "BeaconsSection", "load_pipeline_recipe"]

SECTIONS = (
    Section("pipeline", (
        Param("library", str, "../library/paper.npz"),
        Param("library_recipe", str, None),
        Param("design", str),
        Param("sensor", str),
        Param("turbulence", str, "turbulence.toml"),
        Param("turbulence_samples", int, 10, lo=2, hi=10000),
        Param("library_recheck", list, [], lo=0, hi=100_000, pairs=True,
              help="[i, j] indices of library cells re-solved with RCWA against the table"),
        Param("klayout", bool, False, help="also read the layout back through KLayout"),
        Param("fab_bias_nm", list, [-10.0, 0.0, 10.0], lo=-100, hi=100),
        Param("fab_jitter_nm", list, [], lo=0, hi=100),
    )),
    Section("dataset", (
        Param("samples", int, lo=1, hi=10_000_000),
        Param("rytov_min", float, 0.25, lo=0, open_lo=True, hi=5),
        Param("rytov_max", float, 0.6, lo=0, open_lo=True, hi=5),
        Param("split", list, [0.9, 0.05, 0.05], lo=0, hi=1),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
        TENSOR_SIZE,
        Param("shard_size", int, 64, lo=1, hi=4096),
        Param("workers", int, 2, lo=1, hi=256),
    )),
    Section("train", (
        Param("model", str, None),
        Param("recipe", str, None),
    )),
    Section("evaluate", (
        Param("noise_percent", list, [0.0, 5.0], lo=0, hi=100),
        Param("split", str, "test", choices=["test", "val", "train", "all"]),
    ), optional=True),
    Section("beacons", (
        Param("design", str),
        Param("sensor", str),
        Param("model", str),
        Param("samples", int, 32, lo=1, hi=100_000),
        Param("seed", int, 2026, lo=0, hi=2**63 - 1),
        Param("noise_percent", list, [0.0, 5.0], lo=0, hi=100),
        Param("rytov_min", float, 0.25, lo=0, open_lo=True, hi=5),
        Param("rytov_max", float, 0.6, lo=0, open_lo=True, hi=5),
    ), optional=True),
)
#: sections that only a recipe with a dataset (and its model) has: [dataset] and [train] come together
DATASET_SECTIONS = ("dataset", "train")


@dataclass(frozen=True)
class PipelineSection:
    """``[pipeline]``: stages 1-5 (paths resolved against the recipe; biases and jitters in nm)."""

    library: Path
    library_recipe: Path | None
    design: Path
    sensor: Path
    turbulence: Path
    turbulence_samples: int
    library_recheck: tuple[tuple[int, int], ...]
    klayout: bool
    fab_bias_nm: tuple[float, ...]
    fab_jitter_nm: tuple[float, ...]

    @property
    def library_source(self) -> Path:
        """What the library is made from: its recipe when it is built, else the table itself."""
        return self.library if self.library_recipe is None else self.library_recipe

    @property
    def recheck_cells(self) -> list[list[int]]:
        return [list(c) for c in self.library_recheck]

    @property
    def fab_cases(self) -> list[tuple[str, float, float, int]]:
        """The fab study's devices: (label, etch bias nm, width jitter nm, jitter seed)."""
        return ([("nominal" if b == 0 else f"bias {b:+g} nm", b, 0.0, 0) for b in self.fab_bias_nm]
                + [(f"jitter {j:g} nm", 0.0, j, 1) for j in self.fab_jitter_nm])

    @property
    def fab_content(self) -> list[list]:
        return [list(c) for c in self.fab_cases]


@dataclass(frozen=True)
class DatasetSection:
    """``[dataset]``: the test (or training) set built on the pipeline's device."""

    samples: int
    rytov_min: float
    rytov_max: float
    split: tuple[float, ...]
    seed: int
    tensor_size: int
    shard_size: int
    workers: int

    @property
    def content(self) -> dict:
        """The dataset recipe's own keys (not where its device lies, not how many workers build it)."""
        return {"samples": self.samples, "rytov_min": self.rytov_min, "rytov_max": self.rytov_max,
                "split": list(self.split), "seed": self.seed, "tensor_size": self.tensor_size,
                "shard_size": self.shard_size}

    def document(self, layout: Path, sensor: Path, turbulence: Path) -> dict:
        """The dataset recipe (as :func:`~metadesign.reconstruction.dataset.dataset_recipe_from_dict` reads
        it) of this section on ``layout``, ``sensor`` and ``turbulence``."""
        return {"dataset": {"layout": str(Path(layout).resolve()), "sensor": str(Path(sensor).resolve()),
                            "turbulence": str(Path(turbulence).resolve()), **self.content}}


@dataclass(frozen=True)
class TrainSection:
    """``[train]``: exactly one of a given model (weights) or a training recipe."""

    model: Path | None
    recipe: Path | None


@dataclass(frozen=True)
class EvaluateSection:
    noise_percent: tuple[float, ...]
    split: str

    @property
    def content(self) -> dict:
        return {"noise_percent": self.noise_percent, "split": self.split}


@dataclass(frozen=True)
class BeaconsSection:
    """``[beacons]``: fresh beacons through a second device, estimated by a given model."""

    design: Path
    sensor: Path
    model: Path
    samples: int
    seed: int
    noise_percent: tuple[float, ...]
    rytov_min: float
    rytov_max: float

    @property
    def content(self) -> dict:
        """What shapes the result besides the three files."""
        return {"samples": self.samples, "seed": self.seed, "noise_percent": self.noise_percent,
                "rytov_min": self.rytov_min, "rytov_max": self.rytov_max}


@dataclass(frozen=True)
class PipelineRecipe:
    name: str
    source: Path
    pipeline: PipelineSection
    evaluate: EvaluateSection
    dataset: DatasetSection | None = None
    train: TrainSection | None = None
    beacons: BeaconsSection | None = None


def _resolver(base: Path):
    def rel(p):
        return None if p is None else (Path(p) if Path(p).is_absolute() else base / p)
    return rel


def _pipeline_section(v: dict, rel, path: Path) -> PipelineSection:
    p = dict(v)
    for k in ("library", "library_recipe", "design", "sensor", "turbulence"):
        p[k] = rel(p[k])
    p["library_recheck"] = tuple((int(i), int(j)) for i, j in p["library_recheck"])
    p["fab_bias_nm"] = tuple(round(x * 1e9, 6) for x in p["fab_bias_nm"])  # fab_study takes nm
    p["fab_jitter_nm"] = tuple(round(x * 1e9, 6) for x in p["fab_jitter_nm"])
    if 0.0 not in p["fab_bias_nm"]:
        raise ValidationError(f"{path}: pipeline.fab_bias_nm: expected the nominal device (0) among the etch biases, "
                              f"got {list(p['fab_bias_nm'])}")
    return PipelineSection(**p)


def _train_section(v: dict, rel, path: Path) -> TrainSection:
    t = TrainSection(model=rel(v["model"]), recipe=rel(v["recipe"]))
    if (t.model is None) == (t.recipe is None):
        raise ValidationError(f"{path}: [train] needs exactly one of model (weights to evaluate) or recipe "
                              "(a training recipe)")
    return t


def _beacons_section(v: dict, rel, path: Path) -> BeaconsSection:
    b = dict(v)
    for k in ("design", "sensor", "model"):
        b[k] = rel(b[k])
        if not b[k].exists():
            raise ValidationError(f"{path}: beacons.{k}: {b[k]}: no such file")
    if b["rytov_min"] > b["rytov_max"]:
        raise ValidationError(f"{path}: beacons.rytov_min {b['rytov_min']:g} is above beacons.rytov_max "
                              f"{b['rytov_max']:g}")
    if not b["noise_percent"]:
        raise ValidationError(f"{path}: beacons.noise_percent: expected at least one level (0: a clean camera)")
    return BeaconsSection(**b)


def load_pipeline_recipe(path: str | Path) -> PipelineRecipe:
    """The pipeline recipe at ``path``, validated (one line on the first problem)."""
    path = Path(path)
    raw = load_toml(path)
    has = [k for k in DATASET_SECTIONS if k in raw]
    if len(has) == 1:
        missing = next(k for k in DATASET_SECTIONS if k not in has)
        raise ValidationError(f"{path}: [{has[0]}] needs [{missing}] (a dataset and the model it evaluates)")
    v = parse(raw, [s for s in SECTIONS if (s.name not in DATASET_SECTIONS or has)
                    and (s.name != "beacons" or "beacons" in raw)], str(path))
    if not has and "beacons" not in raw:
        raise ValidationError(f"{path}: nothing to reconstruct: give [dataset] with [train], or [beacons]")
    rel = _resolver(path.parent)
    p = _pipeline_section(v["pipeline"], rel, path)
    train = _train_section(v["train"], rel, path) if has else None
    for k in ("design", "sensor", "turbulence"):
        if not getattr(p, k).exists():
            raise ValidationError(f"{path}: pipeline.{k}: {getattr(p, k)}: no such file")
    beacons = _beacons_section(v["beacons"], rel, path) if "beacons" in v else None
    if has and not v["evaluate"]["noise_percent"]:
        raise ValidationError(f"{path}: evaluate.noise_percent: expected at least one level (0: a clean camera)")
    return PipelineRecipe(name=path.stem, source=path, pipeline=p, evaluate=EvaluateSection(**v["evaluate"]),
                          dataset=DatasetSection(**v["dataset"]) if has else None, train=train, beacons=beacons)

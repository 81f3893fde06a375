"""``metadesign run RECIPE``: every stage from a pipeline recipe, skipping stages whose inputs did not
change, and one self-contained HTML report (figures embedded, readable offline).

Stages (:data:`STAGES`): library (the committed one, or built from a library recipe), design, layout
(OASIS, exact read-back, design rules), as-fabricated PSFs and fab study (Fig. 2c), turbulence validation
(Figs. S5, S6), dataset, training (or a given model), evaluation (Figs. 3b-d), fresh beacons; then the
report.  Each stage declares what it reads, and its key follows: a stage makes a product
(:data:`PRODUCTS`) whose key is the content key (:func:`metadesign.tasks.content_key`) of the upstream
products' keys and the recipe fields it is made from (files by their bytes, never by where they lie: a
copied run folder is up to date); what the stage reads beside its product (the library's re-check cells,
KLayout, the fab study's cases, the number of validation beacons) extends the product's key into the
stage's.  Before any stage runs, :func:`~.pipeline_check.check_inputs` refuses what a stage would refuse
(the recipes named, the models' cards and safetensors headers), so a bad input writes nothing.

The recipe: :mod:`.pipeline_recipe`; the stages' work: :mod:`.pipeline_stages`; the HTML report:
:mod:`.pipeline_report`."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..io import atomic_write_text
from ..tasks import TaskFolder, content_key, path_key
from . import pipeline_stages as stages
from .pipeline_check import check_inputs
from .pipeline_recipe import DATASET_SECTIONS, SECTIONS, PipelineRecipe, load_pipeline_recipe
from .pipeline_report import provenance, report_html

__all__ = ["run_pipeline", "load_pipeline_recipe", "SECTIONS", "DATASET_SECTIONS", "STAGES", "PRODUCTS",
           "Stage", "Product", "stage_keys"]


def _always(rec: PipelineRecipe) -> bool:
    return True


def _has_dataset(rec: PipelineRecipe) -> bool:
    return rec.dataset is not None


def _given_model(rec: PipelineRecipe) -> bool:
    return rec.train is not None and rec.train.model is not None


def _trains(rec: PipelineRecipe) -> bool:
    return rec.train is not None and rec.train.recipe is not None


def _has_beacons(rec: PipelineRecipe) -> bool:
    return rec.beacons is not None


@dataclass(frozen=True)
class Product:
    """What a stage makes and later stages read.  ``inputs``: ``"@name"`` an upstream product (its key),
    ``"file:name"`` a file of the run (:class:`Run` attribute ``name``, by its bytes), else a field of the
    recipe (``"section.field"``; a path by its file's bytes).  ``when``: whether the recipe has it."""

    name: str
    inputs: tuple[str, ...]
    when: Callable[[PipelineRecipe], bool] = _always


@dataclass(frozen=True)
class Stage:
    """A stage: the product it makes, what else it reads (fields that shape its result but not the
    product), and its work (``run(run, key)``, :mod:`.pipeline_stages`)."""

    name: str
    makes: str
    reads: tuple[str, ...]
    run: Callable[["Run", str], None]
    when: Callable[[PipelineRecipe], bool] = _always


PRODUCTS = (
    Product("library", ("pipeline.library_source",)),  # its recipe when built, else the table
    Product("design", ("@library", "pipeline.design")),
    Product("layout", ("@design",)),
    Product("psf", ("@layout", "pipeline.sensor")),
    Product("scenario", ("pipeline.turbulence",)),  # what the dataset reads: the scenario, not its validation
    Product("dataset", ("@psf", "@scenario", "dataset.content"), _has_dataset),
    Product("model", ("train.model",), _given_model),
    Product("model", ("@dataset", "train.recipe"), _trains),
    Product("evaluation", ("@dataset", "file:model", "evaluate.content"), _has_dataset),
    Product("beacons", ("@library", "@scenario", "beacons.design", "beacons.sensor", "beacons.model",
                        "beacons.content"), _has_beacons),
)

STAGES = (
    Stage("library", "library", ("pipeline.recheck_cells",), stages.library),
    Stage("design", "design", (), stages.design),
    Stage("layout", "layout", ("pipeline.klayout",), stages.layout),
    Stage("sensing", "psf", ("pipeline.turbulence", "pipeline.fab_content"), stages.sensing),
    Stage("turbulence", "scenario", ("pipeline.turbulence_samples",), stages.turbulence),
    Stage("dataset", "dataset", (), stages.dataset, _has_dataset),
    Stage("train", "model", (), stages.train, _has_dataset),
    Stage("evaluate", "evaluation", (), stages.evaluate, _has_dataset),
    Stage("beacons", "beacons", (), stages.beacons, _has_beacons),
)


def _h(*parts) -> str:
    """The content key of ``parts``: paths by their files' bytes (:func:`metadesign.tasks.path_key`)."""
    def content(x):
        if isinstance(x, Path):
            return path_key(x)
        if isinstance(x, dict):
            return {k: content(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [content(v) for v in x]
        return x

    return content_key(*(content(x) for x in parts))


class _Keys:
    """The products' and stages' keys of one run, each computed when first asked (a product read by
    file, the trained model, only once its stage has made it)."""

    def __init__(self, run: "Run", strict: bool = False):
        self.run, self.products, self.strict = run, {}, strict  # strict: a run's file not made yet is an error

    def value(self, ref: str):
        if ref.startswith("@"):
            return self.product(ref[1:])
        if ref.startswith("file:"):
            f = Path(getattr(self.run, ref[len("file:"):]))
            if self.strict and not f.is_file():
                raise FileNotFoundError(f)
            return f
        obj = self.run.rec
        for part in ref.split("."):
            obj = getattr(obj, part)
        return obj

    def product(self, name: str) -> str:
        if name not in self.products:
            (prod,) = [p for p in PRODUCTS if p.name == name and p.when(self.run.rec)]
            self.products[name] = _h(*(self.value(r) for r in prod.inputs))
        return self.products[name]

    def stage(self, st: Stage) -> str:
        """A stage's key: its product's, extended by what the stage reads beside it."""
        k = self.product(st.makes)
        return _h(k, *(self.value(r) for r in st.reads)) if st.reads else k


def run_pipeline(recipe_path: str | Path, out: Path, log: Callable[[str], None] = print) -> dict:
    """Every stage of a pipeline recipe into ``out`` (stages whose inputs did not change are skipped), and
    ``report.html``; returns the report (stages, tables, figures)."""
    t_start = time.perf_counter()
    rec = load_pipeline_recipe(recipe_path)
    check_inputs(rec)  # everything a stage would refuse, before anything is written
    out = Path(out)
    out.mkdir(exist_ok=True)
    run = Run(rec, out, log)
    for st in STAGES:
        if st.when(rec):
            st.run(run, run.keys.stage(st))
    run.report["provenance"] = provenance(
        rec, run.lib_path, run.model, time.perf_counter() - t_start, out=out,
        layout=run.lay if rec.dataset is not None else None,
        beacon_device=out / stages.BEACON_DESIGN / "design.npz" if rec.beacons is not None else None)
    html_path = out / "report.html"
    atomic_write_text(html_path, report_html(rec.name, run.report))
    run.report["report"] = str(html_path)
    return run.report


def stage_keys(rec: PipelineRecipe, out: Path) -> dict[str, str]:
    """The key of every stage of ``rec`` that can be known before any runs (all but an evaluation of a
    model still to be trained), by name."""
    keys = _Keys(Run(rec, Path(out), lambda s: None, steps=False), strict=True)
    found = {}
    for st in STAGES:
        if st.when(rec):
            try:
                found[st.name] = keys.stage(st)
            except FileNotFoundError:  # reads a file not made yet
                continue
    return found


class Run:
    """One run of :func:`run_pipeline`: the typed recipe, the output folder, where each product lies
    (``lib_path``, ``ddir``, ``lay``, ``dsdir``, ``model``), the keys, and the report the stages write:
    each stage records its key, tables and figures and is skipped when its key and outputs are unchanged."""

    def __init__(self, rec: PipelineRecipe, out: Path, log: Callable[[str], None], steps: bool = True):
        self.rec, self.out, self.log = rec, out, log
        p, t = rec.pipeline, rec.train
        self.lib_path = out / "library.npz" if p.library_recipe is not None else p.library
        self.lib = None  # the loaded library (once its stage ran)
        self.ddir = out / "design"
        self.lay = self.ddir / "layout.oas"
        self.dsdir = out / "dataset"
        self.model = None if t is None else (t.model if t.model is not None else out / "run" / "model.safetensors")
        self.keys = _Keys(self)
        self.steps = TaskFolder(out / ".steps") if steps else None
        self.report: dict = {"stages": {}, "figures": {}, "tables": {}, "checks": [], "headline": {}, "sections": {}}

    def check(self, what: str, value: str, threshold: str, passed: bool, why: str = "") -> None:
        """A pass/fail line of the report's headline."""
        self.report["checks"].append({"check": what, "value": value, "threshold": threshold, "passed": bool(passed),
                                      "why": why})

    def section(self, name: str, table: tuple | None = None, figures: tuple = (), raw=None) -> None:
        """A report section: a table (title, rows with human labels and units) beside its figures ((title,
        path, caption), ...); ``raw``: the table's numbers as the JSON summary gives them (default: the rows)."""
        sec = self.report["sections"].setdefault(name, {"tables": [], "figures": []})
        if table is not None:
            sec["tables"].append(table)
            self.report["tables"][table[0]] = table[1] if raw is None else raw
        for title, path, caption in figures:
            sec["figures"].append((title, Path(path), caption))
            self.report["figures"][title] = Path(path)

    def previous(self, name: str) -> dict:
        """What the step ``name`` recorded when it last ran (empty: never)."""
        m = self.steps.marked(name) or {}
        return m.get("result") or {}

    def stage(self, name: str, key: str, outputs: list[Path], fn) -> dict:
        """Run ``fn`` (returning the stage's record) unless the step ``name`` last ran with ``key`` and its
        ``outputs`` are all there; the record, with its timings, goes into the report."""
        t0 = time.perf_counter()

        def work():
            info = fn()
            info["ran_seconds"] = time.perf_counter() - t0
            info["ran_at"] = time.strftime("%Y-%m-%d %H:%M:%S")
            return json.loads(json.dumps(info, default=str))

        info, skipped = self.steps.step(name, key, work, outputs)
        info["skipped"] = skipped
        info["seconds"] = time.perf_counter() - t0
        self.report["stages"][name] = info
        return info

    def say(self, name: str, line: str) -> None:
        """A stage's summary line: recorded in its report entry and logged, numbered, as it completes."""
        info = self.report["stages"][name]
        info["line"] = line
        n = list(self.report["stages"]).index(name) + 1
        self.log(f"  {n}. {name:<10} {line}" + (" (up to date)" if info.get("skipped") else ""))

"""``metadesign run RECIPE``: every stage from a pipeline recipe, skipping stages whose inputs did not
change (each stage's key is the sha256 of its inputs: recipe sections, upstream products), and one
self-contained HTML report (figures embedded, readable offline).

Stages: library (the committed one, or built from a library recipe), design, layout (OASIS, exact
read-back, design rules), as-fabricated PSFs and fab study (Fig. 2c), turbulence validation (Figs. S5,
S6), dataset, training (or a given model), evaluation (Figs. 3b-d), report."""

from __future__ import annotations

import base64
import dataclasses
import html
import json
import shutil
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..cliutil import progress_bar
from ..config import Param, Section, load_toml, parse
from ..design.plot import plot_design
from ..design.recipe import load_design_recipe
from ..design.store import load_design, run_design
from ..io import atomic_write_text
from ..layouts.make import make_layout
from ..layouts.preview import preview_layout
from ..layouts.rules import DESIGN_RULES
from ..library.build import build_library
from ..library.plot import plot_library
from ..library.rcwa import SolverSettings, solve_cell
from ..library.recipe import load_recipe
from ..library.store import load_library
from ..reconstruction.dataset import TENSOR_SIZE, build_dataset, dataset_recipe_from_dict, received_crop
from ..reconstruction.evaluate import evaluate_model, plot_fig3, summarise, write_results
from ..reconstruction.metrics import captured_fraction_ci
from ..reconstruction.model import check_sizes
from ..reconstruction.refine import load_network
from ..reconstruction.train import load_train_recipe, train
from ..sensing.model import load_sensing_recipe
from ..sensing.plot import plot_fab_study, plot_frames
from ..sensing.render import fab_study, render_psf, save_psf
from ..tasks import TaskFolder, content_key, file_key, path_key
from ..turbulence.scenario import load_scenario
from ..turbulence.system import build_system
from ..turbulence.validate import plot_validation, validate
from ..validation import ValidationError
from .beacons import LABELS, fresh_beacons

__all__ = ["run_pipeline", "load_pipeline_recipe"]

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


def load_pipeline_recipe(path: str | Path) -> dict:
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
    v.setdefault("dataset", None)
    v.setdefault("train", None)
    v.setdefault("beacons", None)
    base = path.parent

    def rel(p):
        return None if p is None else (Path(p) if Path(p).is_absolute() else base / p)

    p = v["pipeline"]
    for k in ("library", "library_recipe", "design", "sensor", "turbulence"):
        p[k] = rel(p[k])
    p["library_recheck"] = tuple((int(i), int(j)) for i, j in p["library_recheck"])
    p["fab_bias_nm"] = tuple(round(x * 1e9, 6) for x in p["fab_bias_nm"])  # fab_study takes nm
    p["fab_jitter_nm"] = tuple(round(x * 1e9, 6) for x in p["fab_jitter_nm"])
    if 0.0 not in p["fab_bias_nm"]:
        raise ValidationError(f"{path}: pipeline.fab_bias_nm: expected the nominal device (0) among the etch biases, "
                              f"got {list(p['fab_bias_nm'])}")
    if v["train"] is not None:
        v["train"]["model"] = rel(v["train"]["model"])
        v["train"]["recipe"] = rel(v["train"]["recipe"])
        if (v["train"]["model"] is None) == (v["train"]["recipe"] is None):
            raise ValidationError(f"{path}: [train] needs exactly one of model (weights to evaluate) or recipe "
                                  "(a training recipe)")
    for k in ("design", "sensor", "turbulence"):
        if not p[k].exists():
            raise ValidationError(f"{path}: pipeline.{k}: {p[k]}: no such file")
    b = v["beacons"]
    if b is not None:
        for k in ("design", "sensor", "model"):
            b[k] = rel(b[k])
            if not b[k].exists():
                raise ValidationError(f"{path}: beacons.{k}: {b[k]}: no such file")
        if b["rytov_min"] > b["rytov_max"]:
            raise ValidationError(f"{path}: beacons.rytov_min {b['rytov_min']:g} is above beacons.rytov_max "
                                  f"{b['rytov_max']:g}")
        if not b["noise_percent"]:
            raise ValidationError(f"{path}: beacons.noise_percent: expected at least one level (0: a clean camera)")
    v["name"] = path.stem
    return v


def _h(*parts) -> str:
    """A stage's key: the one content key (:func:`metadesign.tasks.content_key`) of its inputs, files by
    their bytes (never by where they lie: a copied run folder is up to date)."""
    def content(x):
        if isinstance(x, Path):
            return path_key(x)
        if isinstance(x, dict):
            return {k: content(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [content(v) for v in x]
        return x

    return content_key(*(content(x) for x in parts))


def run_pipeline(recipe_path: str | Path, out: Path, log: Callable[[str], None] = print) -> dict:
    """Every stage of a pipeline recipe into ``out`` (stages whose inputs did not change are skipped), and
    ``report.html``; returns the report (stages, tables, figures)."""
    t_start = time.perf_counter()
    rec = load_pipeline_recipe(recipe_path)
    out = Path(out)
    if rec["train"] is not None and rec["train"]["model"] is not None:  # a given model must fit the dataset it
        model, _ = load_network(rec["train"]["model"])  # will be evaluated on: check now (a U-Net or a refiner)
        check_sizes(model.config, rec["dataset"]["tensor_size"],
                    received_crop(load_scenario(rec["pipeline"]["turbulence"]))[1], f"[train] model {rec['train']['model']}")
    if rec["pipeline"]["library_recheck"] and rec["pipeline"]["library_recipe"] is None:  # cells of the table
        _check_cells(load_library(rec["pipeline"]["library"]), rec["pipeline"]["library_recheck"])
    if rec["beacons"] is not None:  # the beacons' model: loadable, and its output the scenario's crop
        model, _ = load_network(rec["beacons"]["model"])
        check_sizes(model.config, model.config.input_size,
                    received_crop(load_scenario(rec["pipeline"]["turbulence"]))[1], f"[beacons] model {rec['beacons']['model']}")
    out.mkdir(exist_ok=True)
    run = _Pipeline(rec, out, log)
    steps = [run.library, run.design, run.layout, run.sensing, run.turbulence]
    if rec["dataset"] is not None:
        steps += [run.dataset, run.train, run.evaluate]
    if rec["beacons"] is not None:
        steps.append(run.beacons)
    for step in steps:
        step()
    run.report["provenance"] = _provenance(Path(recipe_path), rec, run, time.perf_counter() - t_start)
    html_path = out / "report.html"
    atomic_write_text(html_path, _html(rec["name"], run.report))
    run.report["report"] = str(html_path)
    return run.report


class _Pipeline:
    """The steps of :func:`run_pipeline`, in order; each records its key (a hash of its inputs and of the
    upstream keys), tables and figures, and is skipped when its key and outputs are unchanged."""

    def __init__(self, rec: dict, out: Path, log: Callable[[str], None]):
        self.rec, self.out, self.log, self.p = rec, out, log, rec["pipeline"]
        self.steps = TaskFolder(out / ".steps")
        self.state = {}  # this run's stages: name -> {"key", "info"}
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

    def _previous(self, name: str) -> dict:
        """What the step ``name`` recorded when it last ran (empty: never)."""
        m = self.steps.marked(name) or {}
        return m.get("result") or {}

    def stage(self, name: str, key: str, outputs: list[Path], fn) -> dict:
        t0 = time.perf_counter()

        def run():
            info = fn()
            info["ran_seconds"] = time.perf_counter() - t0
            info["ran_at"] = time.strftime("%Y-%m-%d %H:%M:%S")
            return json.loads(json.dumps(info, default=str))

        info, skipped = self.steps.step(name, key, run, outputs)
        info["skipped"] = skipped
        self.state[name] = {"key": key, "info": info}
        info["seconds"] = time.perf_counter() - t0
        self.report["stages"][name] = info
        return info

    def say(self, name: str, line: str) -> None:
        """A stage's summary line: recorded in its report entry and logged, numbered, as it completes."""
        info = self.report["stages"][name]
        info["line"] = line
        n = list(self.report["stages"]).index(name) + 1
        self.log(f"  {n}. {name:<10} {line}" + (" (up to date)" if info.get("skipped") else ""))

    def library(self) -> None:
        p, out = self.p, self.out
        self.lib_path = p["library"]
        if p["library_recipe"] is not None:
            self.lib_path = lib_path = out / "library.npz"
            self.k_lib = _h(p["library_recipe"])
            self.stage("library", _h(self.k_lib, [list(c) for c in p["library_recheck"]]), [lib_path], lambda: {
                "report": build_library(load_recipe(p["library_recipe"]), lib_path, workers=2)[1]["cells"],
                **_recheck(load_library(lib_path), p["library_recheck"])})
        else:
            self.k_lib = _h(self.lib_path)
            recheck = p["library_recheck"]
            self.stage("library", _h(self.k_lib, [list(c) for c in recheck]), [self.lib_path], lambda: {
                "file": str(self.lib_path), **_recheck(load_library(self.lib_path), recheck)})
        self.lib = load_library(self.lib_path)
        li = self.report["stages"]["library"]
        sm = self.lib.summary()
        line = (f"{sm['grid']['n_wx']}x{sm['grid']['n_wy']} cells, nG {sm['solver']['n_harmonics']}, convergence "
                f"{sm['convergence']['max_phase_change_rad']:.4f} rad, {100 * sm['fraction_above_threshold']:.1f} % "
                "cells with T0 >= 70 %")
        if li.get("recheck_max_abs_error") is not None:
            err = li["recheck_max_abs_error"]
            line += f", RCWA re-check {err:.1e}"
            self.check(f"library re-check: {len(li['recheck_cells'])} cells solved again with RCWA",
                       f"{err:.1e} (largest Jones-matrix difference)", "<= 1e-6", err <= 1e-6,
                       "the committed table against fresh solves with its own solver settings")
        li["summary"] = sm
        fig_s1 = out / "fig-s1.png"
        if not fig_s1.exists() or not self.report["stages"]["library"]["skipped"]:
            plot_library(self.lib, fig_s1)
        li["figures"] = [str(fig_s1)]
        self.say("library", line)
        self.section("1. Unit-cell library", None, [(
            "Fig. S1: unit-cell library", fig_s1,
            "Phase and transmission of every pillar for x and y polarisation: the 16 x 16 birefringent bins need "
            "pillars whose two phases cover 0-2 pi independently with high transmission.")])

    def design(self) -> None:
        out = self.out
        dr = dataclasses.replace(load_design_recipe(self.p["design"]), library_path=self.lib_path)
        self.k_des = _h(self.k_lib, self.p["design"])
        self.ddir = out / "design"

        def do_design():
            d, _ = run_design(dr, self.ddir)
            plot_design(d, out / "fig-s2.png", self.lib)
            return {"metrics": {k: d.metrics[k] for k in ("rmse_rad", "peak_error_rad", "mean_T0", "n_atoms",
                                                          "n_empty_bins", "n_cells_in_aperture")},
                    "n_cells": int(d.spec.n_cells), "figures": [str(out / "fig-s2.png")]}

        des = self.stage("design", self.k_des, [self.ddir / "design.npz", out / "fig-s2.png"], do_design)
        m = des["metrics"]
        self.say("design", f"{des.get('n_cells', 0)}x{des.get('n_cells', 0)} cells, {m['n_atoms']} atoms, RMSE x "
                 f"{m['rmse_rad'][0]:.3f} y {m['rmse_rad'][1]:.3f} rad, peak {m['peak_error_rad'][0]:.3f}/"
                 f"{m['peak_error_rad'][1]:.3f} rad, mean T0 {m['mean_T0'][0]:.3f}/{m['mean_T0'][1]:.3f}")
        self.check("design: every one of the 16 x 16 phase bins has an atom", f"{m['n_empty_bins']} empty bins",
                   "0", m["n_empty_bins"] == 0 and m["n_atoms"] > 0,
                   "a bin without an atom falls back to a neighbour's and adds its phase error")
        q = 2 * np.pi / 16 / np.sqrt(12)  # a uniform quantiser of 16 phase bins
        rmse = max(m["rmse_rad"])
        self.check("design phase error (RMSE, worse polarisation)", f"{rmse:.3f} rad", f"<= {1.1 * q:.3f} rad",
                   rmse <= 1.1 * q, "16 x 16 binning: a uniform quantiser's error is (2 pi / 16) / sqrt(12) = "
                   f"{q:.3f} rad; 10 % allowance for empty or uneven bins")
        rows = [{"quantity": "phase RMSE x / y", "value": f"{m['rmse_rad'][0]:.4f} / {m['rmse_rad'][1]:.4f} rad"},
                {"quantity": "peak phase error x / y", "value": f"{m['peak_error_rad'][0]:.3f} / "
                                                                f"{m['peak_error_rad'][1]:.3f} rad"},
                {"quantity": "mean transmission x / y", "value": f"{m['mean_T0'][0]:.3f} / {m['mean_T0'][1]:.3f}"},
                {"quantity": "atoms used", "value": f"{m['n_atoms']:,} ({m['n_empty_bins']} empty bins)"},
                {"quantity": "cells in the aperture", "value": f"{m['n_cells_in_aperture']:,}"}]
        self.section("2. Design", ("Design metrics", rows), [(
            "Fig. S2: design", out / "fig-s2.png",
            "(a) the atoms' phases, x- against y-polarisation (the 16 x 16 bins should be covered evenly); (b) the "
            "atoms' widths; (c, d) the discretised phase of one supercell lens (QI) per polarisation: smooth rings "
            "centred on the lens's offset; (e, f) the pillar widths across that lens; (g) how many cells use each "
            "atom. The phase error itself is in the table (RMSE against the 16-bin quantiser's).")])

    def layout(self) -> None:
        out = self.out
        self.lay = lay = self.ddir / "layout.oas"
        self.k_lay = _h(self.k_des)

        klayout = self.p["klayout"]

        def do_layout():
            made = make_layout(load_design(self.ddir), lay, klayout=klayout)
            preview_layout(made.contents, out / "layout-preview.png")
            at = made.drc["from_atom_table"]
            return {"pillars": made.write["pillars"], "bytes": made.write["bytes"], "exact": made.exact,
                    "gdstk_exact": bool(made.verify["exact"]),
                    "klayout_exact": None if made.verify_klayout is None else bool(made.verify_klayout["exact"]),
                    "drc_passed": bool(made.drc["passed"]), "write_seconds": made.write["seconds"],
                    "min_feature_nm": at["min_feature_nm"], "min_gap_nm": min(at["min_gap_x_nm"], at["min_gap_y_nm"]),
                    "figures": [str(out / "layout-preview.png")]}

        li = self.stage("layout", _h(self.k_lay, klayout), [lay, out / "layout-preview.png"], do_layout)
        if not (li["exact"] and li["drc_passed"]):
            raise ValidationError(f"{lay}: the layout failed its read-back or design-rule check")
        k = li.get("klayout_exact")
        self.say("layout", f"{li['pillars']:,} pillars, {li['bytes'] / 1e3:.0f} kB OASIS in "
                 f"{li.get('write_seconds', float('nan')):.2f} s; read-back exact {li.get('gdstk_exact', li['exact'])} "
                 "(gdstk)" + ("" if k is None else f" / {k} (KLayout)") + f"; DRC {'pass' if li['drc_passed'] else 'FAIL'}"
                 f" (min feature {li.get('min_feature_nm')} nm, min gap {li.get('min_gap_nm')} nm)")
        if k is not None:
            self.check("layout read-back through KLayout", "exact" if k else "differs", "every pillar as designed", k,
                       "an independent OASIS reader: the file a mask shop would open")
        self.check("layout read-back", "exact" if li["exact"] else "differs", "every pillar as designed", li["exact"],
                   "the OASIS file read back pillar by pillar against the design")
        self.check(f"design rules ({DESIGN_RULES.label()})", "passed" if li["drc_passed"] else "violated",
                   "no violation", li["drc_passed"])
        self.section("3. Layout", ("Layout", [
            {"quantity": "pillars", "value": f"{li['pillars']:,}"},
            {"quantity": "OASIS file", "value": f"{li['bytes'] / 1e6:.2f} MB"},
            {"quantity": "read-back", "value": "exact" if li["exact"] else "differs"},
            {"quantity": "design rules", "value": "passed" if li["drc_passed"] else "violated"}]), [(
            "Layout preview", out / "layout-preview.png",
            "16 x 16 cells at the centre of the written OASIS layout, read back from the file: every rectangle "
            "one pillar at its drawn width, as a mask shop would see it.")])

    def sensing(self) -> None:
        """As-fabricated PSFs, the Table S1 focal check, a fab study and one scintillated beacon through
        the device."""
        out, p = self.out, self.p
        sr = load_sensing_recipe(p["sensor"])
        self.k_psf = _h(self.k_lay, p["sensor"])
        cases = [("nominal" if b == 0 else f"bias {b:+g} nm", b, 0.0, 0) for b in p["fab_bias_nm"]]
        cases += [(f"jitter {j:g} nm", 0.0, j, 1) for j in p["fab_jitter_nm"]]
        figs = [out / "fig-2c.png", out / "fab-study.png", out / "psf-turbulent.png"]

        def do_sensing():
            system = build_system(self.lay, sr, p["turbulence"])
            fab = system.device
            res = render_psf(fab, sr)
            save_psf(self.ddir / "psf.npz", res, fab, sr)
            plot_frames(res.frames, sr.sensor, figs[0], fab.channels, "as-fabricated sensor frames")
            rows = []
            for i, (label, b, j, seed) in enumerate(cases):
                for r in fab_study(fab, sr, [b], [j], [0.0], seed=seed):
                    rows.append({**r, "case": i, "label": label})
            plot_fab_study(rows, figs[1])
            smp = system.chain().sample(seed=1, rytov=0.3)
            plot_frames(smp.frames, sr.sensor, figs[2], fab.channels,
                        "scintillated beacon at Rytov 0.3 through the as-fabricated device")
            nominal = [r for r in rows if r["label"] == "nominal"]
            focal = [{"pol": r["pol"], "k": r["k"], "design_f_mm": r["design_focal_length_mm"],
                      "best_focus_mm": r["design_focal_length_mm"] + r["focal_shift_mm"], "strehl": r["strehl"]}
                     for r in nominal]
            study = [{"case": label, "bias_nm": b, "jitter_nm": j,
                      "mean_strehl": float(np.mean([r["strehl"] for r in rows if r["case"] == i])),
                      "mean_efficiency": float(np.mean([r["focusing_efficiency"] for r in rows if r["case"] == i]))}
                     for i, (label, b, j, _) in enumerate(cases)]
            return {"focal_check": focal, "fab_study": study, "channels": nominal,
                    "figures": [str(f) for f in figs]}

        ps = self.stage("sensing", _h(self.k_psf, p["turbulence"], [list(c) for c in cases]), figs, do_sensing)
        nom = ps["channels"]
        self.say("sensing", f"8 PSFs from the layout file: focusing efficiency "
                 f"{np.mean([r['focusing_efficiency'] for r in nom]):.3f} per channel, Strehl "
                 f"{min(r['strehl'] for r in nom):.3f}..{max(r['strehl'] for r in nom):.3f}, crosstalk "
                 f"{max(r['crosstalk'] for r in nom):.3f}; fab study: Strehl "
                 + ", ".join(f"{r['case']} {r['mean_strehl']:.3f}" for r in ps["fab_study"]))
        focal = [{"channel": f"{r['pol']}-pol {['QI', 'QII', 'QIII', 'QIV'][r['k'] - 1]}",
                  "design f (mm)": f"{r['design_f_mm']:.4f}",
                  "best focus - design (um)": f"{1e3 * (r['best_focus_mm'] - r['design_f_mm']):+.1f}",
                  "Strehl": f"{r['strehl']:.3f}"} for r in ps["focal_check"]]
        worst = max(abs(r["best_focus_mm"] - r["design_f_mm"]) for r in ps["focal_check"])
        self.check("focal lengths (Table S1): worst best-focus shift", f"{1e3 * worst:.1f} um", "<= 100 um",
                   worst <= 0.1, "through-focus peak of each of the 8 as-fabricated spots against its design focal "
                   "length; the spots' depth of focus, +-2 lambda N^2 at f-number N ~ 20, is ~1 mm")
        strehl = min(r["strehl"] for r in ps["focal_check"])
        self.check("as-fabricated Strehl ratio, worst spot", f"{strehl:.3f}", ">= 0.8", strehl >= 0.8,
                   "Marechal's criterion: a diffraction-limited spot")
        study = [{"device": r["case"], "mean Strehl": f"{r['mean_strehl']:.3f}",
                  "mean focusing efficiency (%)": f"{100 * r['mean_efficiency']:.2f}"} for r in ps["fab_study"]]
        self.section("4. As-fabricated sensor", ("Table S1 focal check (through-focus peak)", focal),
                     raw=ps["focal_check"], figures=[(
            "Fig. 2c: sensor frames", figs[0],
            "The 8 spots on the sensor (2 polarisations x 4 quadrants), each with its own defocus: all 8 should be "
            "compact and centred in their quadrant."), (
            "A scintillated beacon", figs[2],
            "One beacon through the turbulence (Rytov 0.3) onto the same sensor: the 8 spots break up, each "
            "differently, and that difference is what the reconstruction reads.")])
        self.section("4. As-fabricated sensor", ("Fab study", study), raw=ps["fab_study"], figures=[(
            "Fab study", figs[1],
            "Per spot (8 markers per device, x-pol filled, y-pol open) and per fabrication case: focusing "
            "efficiency, Strehl ratio at best focus, best-focus shift from the design focal length, and crosstalk "
            "into the other quadrants: how much a fab process may drift before the spots degrade.")])

    def turbulence(self) -> None:
        p, out = self.p, self.out
        sc = load_scenario(p["turbulence"])
        self.k_scn = _h(p["turbulence"])  # what the dataset depends on: the scenario, not its validation
        self.k_tu = _h(self.k_scn, p["turbulence_samples"])

        def do_turb():
            res = validate(sc, (0.1, 0.3, 0.5), samples=p["turbulence_samples"], pib_samples=5)
            figs = plot_validation(res, out)
            return {"figures": [str(f) for f in figs],
                    "levels": [{"rytov_nominal": x["rytov_nominal"], "rytov_measured": x["rytov_measured"],
                                "rytov_theory": x["rytov_weak_theory_inner_scale"], "D_over_r0": x["D_over_r0"],
                                "npib_mean": {m: float(np.mean(x["npib"][m])) for m in ("complex", "phase", "none")}}
                               for x in res["levels"]],
                    "structure_function_ratio": [float(r) for r in res["structure_function"]["ratio"]]}

        figs = [out / Path(f).name for f in self._previous("turbulence").get("figures", [])]
        tu = self.stage("turbulence", self.k_tu, figs or [out / "__none__"], do_turb)
        sf, top = tu.get("structure_function_ratio") or [float("nan")], tu["levels"][-1]
        self.say("turbulence", f"structure function / theory {min(sf):.3f}..{max(sf):.3f}; Rytov nominal -> measured "
                 f"({p['turbulence_samples']} samples) " + ", ".join(f"{x['rytov_nominal']:g} -> {x['rytov_measured']:.3f}"
                                                                     for x in tu["levels"])
                 + f"; NPiB complex/phase/none at {top['rytov_nominal']:g}: "
                 + "/".join(f"{top.get('npib_mean', {}).get(m, float('nan')):.2f}" for m in ("complex", "phase", "none")))
        rows = [{"Rytov (nominal)": f"{x['rytov_nominal']:g}",
                 "weak theory with inner scale": f"{x.get('rytov_theory', float('nan')):.3f}",
                 "Rytov (measured)": f"{x['rytov_measured']:.3f}", "D / r0": f"{x['D_over_r0']:.1f}"}
                for x in tu["levels"]]

        def ref(x):  # the prediction for this path: weak-fluctuation theory with the inner scale
            return x.get("rytov_theory") or x["rytov_nominal"]

        w = max(tu["levels"], key=lambda x: abs(x["rytov_measured"] / ref(x) - 1))
        dev = abs(w["rytov_measured"] / ref(w) - 1)
        self.check("turbulence: measured log-amplitude variance against theory",
                   f"worst level (Rytov {w['rytov_nominal']:g}): {w['rytov_measured']:.3f} vs {ref(w):.3f} "
                   f"({100 * (w['rytov_measured'] / ref(w) - 1):+.0f} %)", "within 25 %", dev <= 0.25,
                   f"{self.p['turbulence_samples']} beacons per level against weak-fluctuation theory with the inner "
                   "scale (the nominal Rytov number leaves the inner scale out; saturation lowers the measured "
                   "value above ~0.5)")
        captions = {"fig-s5": "Fig. S5: the screens' phase structure function against theory (the points should sit "
                              "on the line); (S5a) the log-amplitude variance against the nominal Rytov number "
                              "and weak-fluctuation theory; (S5b) the coherence factor against theory: beyond r0 "
                              "the points level off at the finite ensemble's floor (dotted: each beacon's own "
                              "coherence x sqrt(pi / 4N), falling as 1 / sqrt(beacons)) instead of 0; (S5c) the "
                              "long-exposure MTF.",
                    "fig-s6": "Fig. S6: normalised power in bucket (NPiB, the power a corrected beam puts in the "
                              "target bucket over a vacuum beam's) for uncorrected, phase-conjugate and complex-"
                              "conjugate correction per beacon; triangles: the mean of each group. NPiB can exceed 1: "
                              "turbulence can focus more power into the bucket than vacuum does."}
        self.section("5. Turbulence", ("Turbulence: Rytov nominal vs measured", rows), raw=tu["levels"], figures=[
            (next((c.split(":")[0] for k, c in captions.items() if k in Path(f).stem), Path(f).stem), Path(f),
             next((c for k, c in captions.items() if k in Path(f).stem), "")) for f in tu["figures"]])

    def dataset(self) -> None:
        p = self.p
        ds_sec = dict(self.rec["dataset"])
        workers = ds_sec.pop("workers")
        self.dsdir = self.out / "dataset"
        ds_raw = {"dataset": {"layout": str(self.lay.resolve()), "sensor": str(p["sensor"].resolve()),
                              "turbulence": str(p["turbulence"].resolve()), "samples": ds_sec["samples"],
                              "rytov_min": ds_sec["rytov_min"], "rytov_max": ds_sec["rytov_max"],
                              "split": list(ds_sec["split"]), "seed": ds_sec["seed"],
                              "tensor_size": ds_sec["tensor_size"], "shard_size": ds_sec["shard_size"]}}
        self.k_ds = _h(self.k_psf, self.k_scn, {k: v for k, v in ds_raw["dataset"].items()
                                                 if k not in ("layout", "sensor", "turbulence")})
        ds = self.stage("dataset", self.k_ds, [self.dsdir / "zarr.json"], lambda: {
            k: v for k, v in build_dataset(dataset_recipe_from_dict(ds_raw, "dataset"), self.dsdir, workers=workers,
                                           overwrite=True, progress=progress_bar("dataset", "sample")).items()
            if k in ("samples", "bytes_per_sample", "split_counts")})
        sc = ds.get("split_counts") or {}
        self.say("dataset", f"{ds.get('samples', 0):,} samples (train / val / test "
                 + " / ".join(f"{sc.get(k, 0):,}" for k in ("train", "val", "test"))
                 + f"), {ds.get('bytes_per_sample', 0) / 1e3:.1f} kB each")
        self.section("6. Reconstruction", ("Dataset", [
            {"quantity": "samples", "value": f"{ds.get('samples', 0):,}"},
            {"quantity": "train / val / test", "value": " / ".join(f"{sc.get(k, 0):,}" for k in ("train", "val", "test"))},
            {"quantity": "storage per sample", "value": f"{ds.get('bytes_per_sample', 0) / 1e3:.1f} kB"}]))

    def train(self) -> None:
        """Training (or the given model)."""
        t = self.rec["train"]
        if t["model"] is not None:
            self.model = t["model"]
            self.stage("train", _h(self.model), [self.model], lambda: {"model": str(self.model)})
            self.say("train", f"the given model {self.model}")
            return
        run = self.out / "run"

        def do_train():
            shutil.rmtree(run, ignore_errors=True)  # the pipeline's own run folder
            r = train(load_train_recipe(t["recipe"]), run, dataset=self.dsdir, log=self.log, progress=True)
            return {"epochs": r["epochs_done"], "best_val_npib": r["best_val_npib"]}

        tr = self.stage("train", _h(self.k_ds, t["recipe"]), [run / "model.safetensors"], do_train)
        self.model = run / "model.safetensors"
        self.say("train", f"{tr.get('epochs')} epochs, best validation NPiB {tr.get('best_val_npib', float('nan')):.3f}")
        if (run / "curves.png").exists():
            self.section("6. Reconstruction", None, [(
                "Training curves", run / "curves.png",
                "Loss and validation NPiB per epoch: validation should rise and level off, not fall (over-fitting).")])

    def evaluate(self) -> None:
        ev_dir = self.out / "evaluation"
        ev_opts = self.rec["evaluate"]
        k_ev = _h(self.k_ds, Path(self.model), {k: v for k, v in ev_opts.items() if not isinstance(v, Path)})

        def do_eval():
            ev_dir.mkdir(exist_ok=True)
            # noise levels stay in percent of the peak (config: "percent" is not rescaled)
            res = evaluate_model(self.model, self.dsdir, ev_opts["split"], list(ev_opts["noise_percent"]),
                                 progress=progress_bar("evaluate", "sample"))
            write_results(res, ev_dir)
            figs = plot_fig3(res, ev_dir)
            summary = {k: summarise(res["rows"][k]) for k in res["rows"]}
            for k, r in res["rows"].items():  # how well the test set pins the captured fraction down
                summary[k]["captured_fraction_ci95"] = list(captured_fraction_ci(r["none"], r["unet"],
                                                                                 r["phase_conjugate"]))
            return {"figures": [str(f) for f in figs], "summary": summary}

        figs = [ev_dir / Path(f).name for f in self._previous("evaluate").get("figures", [])]
        ev = self.stage("evaluate", k_ev, figs or [ev_dir / "__none__"], do_eval)
        levels = sorted(ev["summary"], key=_noise_value)  # numerically: 0, 2, 5, 10 (not as strings)
        refines = any("start" in v for v in ev["summary"].values())
        est = "U-Net + refinement" if refines else "U-Net"
        summary = [{"noise_percent": _noise_value(k), **{f"npib_{m}": v["npib"][m] for m in v["npib"]},
                    "captured_fraction": v["captured_fraction"],
                    **({"npib_unet_alone": v["start"]["npib"],
                        "captured_fraction_unet_alone": v["start"]["captured_fraction"]} if "start" in v else {}),
                    "gain_median": v["gain"]["median"], "gain_ratio_of_means": v["gain"]["ratio_of_means"]}
                   for k, v in ((k, ev["summary"][k]) for k in levels)]
        rows = [{"sensor noise (% of peak)": f"{r['noise_percent']:g}", "NPiB uncorrected": f"{r['npib_none']:.3f}",
                 **({"NPiB U-Net alone": f"{r['npib_unet_alone']:.3f}"} if refines else {}),
                 f"NPiB {est}": f"{r['npib_unet']:.3f}", "NPiB phase conjugate": f"{r['npib_phase_conjugate']:.3f}",
                 "captured fraction": f"{r['captured_fraction']:.2f}",
                 **({"captured, U-Net alone": f"{r['captured_fraction_unet_alone']:.2f}"} if refines else {}),
                 "gain (median)": f"{r['gain_median']:.1f}x"} for r in summary]
        self.report["headline"] = {"estimator": est, "rows": rows, "n": ev.get("n")}
        self.say("evaluate", f"{est}, mean NPiB at " + " / ".join(f"{r['noise_percent']:g}" for r in summary)
                 + " % noise: " + " / ".join(f"{r['npib_unet']:.3f}" for r in summary) + " (captured "
                 + " / ".join(f"{r['captured_fraction']:.2f}" for r in summary) + f"); uncorrected "
                 f"{summary[0]['npib_none']:.3f}, phase conjugate {summary[0]['npib_phase_conjugate']:.3f}")
        card_cf = _validated_captured_fraction(self.model)
        for k in levels:
            v = ev["summary"][k]
            lo, hi = v.get("captured_fraction_ci95", [float("nan")] * 2)
            if card_cf is not None:
                self.check(f"reconstruction at {_noise_value(k):g} % noise: captured fraction against the model card's",
                           f"{v['captured_fraction']:.2f} (95 % interval {lo:.2f}..{hi:.2f}, n {v['n']})",
                           f">= {card_cf - CAPTURED_MARGIN:.2f} (card's validation {card_cf:.2f} - "
                           f"{CAPTURED_MARGIN:g})", hi >= card_cf - CAPTURED_MARGIN,
                           "the model must do on this device and turbulence what its card says it did on its "
                           "validation set: the interval's upper end within the margin of the card's figure")
        for r in summary:
            self.check(f"reconstruction at {r['noise_percent']:g} % noise: {est} beats uncorrected",
                       f"NPiB {r['npib_unet']:.3f} vs {r['npib_none']:.3f} (captured {r['captured_fraction']:.2f})",
                       "NPiB above the uncorrected beam's", r["npib_unet"] > r["npib_none"],
                       "captured fraction = (NPiB estimator - NPiB uncorrected) / (NPiB phase conjugate - NPiB "
                       "uncorrected): 1 is the phase-only oracle")
        captions = {"fig-3b": "Fig. 3b: NPiB of each test beacon against its measured Rytov number; the estimator "
                              "should sit close under the phase conjugate and far above the uncorrected beam. NPiB "
                              "(power in the bucket over a vacuum beam's) can exceed 1 where turbulence focuses.",
                    "fig-3cd": "Fig. 3c/d: NPiB against the sensor noise (% of each channel's peak: each of the 8 "
                               "channels is exposed on its own spot).",
                    "phase": "Phases: predicted against true received phase for a few test beacons (piston removed)."}
        self.section("6. Reconstruction", ("NPiB summary", rows), raw=summary, figures=[
            (next((c.split(":")[0] for k, c in captions.items() if k in Path(f).stem), Path(f).stem), Path(f),
             next((c for k, c in captions.items() if k in Path(f).stem), "")) for f in ev["figures"]])

    def beacons(self) -> None:
        """Fresh beacons through a second device (the ``[beacons]`` section) estimated by a given model:
        no dataset (:func:`metadesign.studies.beacons.fresh_beacons`)."""
        b, out = self.rec["beacons"], self.out
        fig = out / "fig-3b-beacons.png"
        opts = {k: v for k, v in b.items() if k not in ("design", "sensor", "model")}
        key = _h(self.k_lib, self.k_scn, b["design"], b["sensor"], b["model"], opts)
        info = self.stage("beacons", key, [fig], lambda: fresh_beacons(
            b["model"], b["design"], b["sensor"], self.p["turbulence"], out / "beacon-design", fig, b["samples"],
            b["seed"], b["noise_percent"], (b["rytov_min"], b["rytov_max"]), library=self.lib_path))
        self.say("beacons", info["line"])
        m, cap = info["npib"], info["captured_fraction"]
        rows = []
        for lv in info["noise_percent"]:
            for k in info["methods"]:
                rows.append({"sensor noise (% of peak)": f"{lv:g}", "estimator": LABELS[k],
                             "NPiB": f"{m[f'{k}@{lv:g}']:.3f}", "NPiB uncorrected": f"{m['none']:.3f}",
                             "NPiB phase conjugate": f"{m['phase_conjugate']:.3f}",
                             "captured fraction": f"{cap[f'{k}@{lv:g}']:.2f}"})
                self.check(f"fresh beacons at {lv:g} % noise: {LABELS[k]} beats uncorrected",
                           f"NPiB {m[f'{k}@{lv:g}']:.3f} vs {m['none']:.3f} (captured {cap[f'{k}@{lv:g}']:.2f})",
                           "NPiB above the uncorrected beam's", m[f"{k}@{lv:g}"] > m["none"],
                           f"{b['samples']} beacons through {b['design'].stem} never seen in training (root seed "
                           f"{b['seed']})")
        if not self.report["headline"]:
            self.report["headline"] = {"estimator": LABELS[info["methods"][-1]], "rows": rows, "n": b["samples"]}
        self.section("6. Reconstruction: fresh beacons", ("Fresh beacons", rows), raw={"npib": m, "captured_fraction": cap},
                     figures=[("Fig. 3b: fresh beacons", fig,
                               "NPiB of each beacon against its measured Rytov number, at the highest noise level: "
                               "the estimator should sit close under the phase conjugate and far above the "
                               "uncorrected beam.")])


def _check_cells(lib, cells) -> None:
    n = (len(lib.wx), len(lib.wy))
    for i, j in cells:
        if not (0 <= i < n[0] and 0 <= j < n[1]):
            raise ValidationError(f"pipeline.library_recheck: cell [{i}, {j}] is outside the library's "
                                  f"{n[0]} x {n[1]} grid")


def _recheck(lib, cells) -> dict:
    """The library's Jones matrices at ``cells`` ((i, j) indices) against fresh RCWA solves with the
    table's own stack and truncation: the largest absolute difference (nothing when no cell is given)."""
    if not cells:
        return {}
    stack = lib.stack
    settings = SolverSettings(lib.meta["solver"]["n_harmonics_requested"])
    _check_cells(lib, cells)
    err = max(float(np.abs(solve_cell(lib.wx[i], lib.wy[j], stack, settings).jones - lib.jones[i, j]).max())
              for i, j in cells)
    return {"recheck_max_abs_error": err, "recheck_cells": [list(c) for c in cells]}


def _table(obj, raw: tuple = ()) -> str:
    """An HTML table of rows (dicts); cells are escaped except in the ``raw`` columns (markup)."""
    rows = obj if isinstance(obj, list) else [obj]
    if not rows:
        return "<p>(empty)</p>"
    cols = list(rows[0])

    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        if isinstance(v, (list, tuple)):
            return ", ".join(fmt(x) for x in v)
        if isinstance(v, dict):
            return "; ".join(f"{k}: {fmt(x)}" for k, x in v.items())
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{r.get(c) if c in raw else fmt(r.get(c))}</td>" for c in cols) + "</tr>"
                   for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _noise_value(key: str) -> float:
    """The level of an evaluation key ("gaussian:5" -> 5.0; photon levels after every Gaussian one)."""
    kind, _, v = str(key).partition(":")
    return float(v) + (0 if kind == "gaussian" else 1e6)


def _img(title: str, f: Path) -> str:
    b64 = base64.b64encode(Path(f).read_bytes()).decode()
    return f"<img alt='{html.escape(title)}' src='data:image/png;base64,{b64}'>"


#: how far below its card's validated captured fraction a model may score on the pipeline's test set
CAPTURED_MARGIN = 0.10


def _validated_captured_fraction(model) -> float | None:
    """The captured fraction on the validation set recorded in a model's card (None: not recorded)."""
    try:
        card = json.loads(Path(str(model) + ".json").read_text())
    except (OSError, ValueError, TypeError):
        return None
    m = card.get("metrics") if isinstance(card, dict) else None
    if not isinstance(m, dict):
        return None
    if m.get("val_captured_fraction") is not None:
        return float(m["val_captured_fraction"])
    try:
        return float((m["val_npib"] - m["val_npib_none"]) / (m["val_npib_phase_conjugate"] - m["val_npib_none"]))
    except (KeyError, TypeError, ZeroDivisionError):
        return None


def _git_commit() -> str | None:
    """The checkout's commit (None outside a git checkout, e.g. a wheel install)."""
    import subprocess

    try:
        r = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent), "rev-parse", "HEAD"],
                           capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def _provenance(recipe_path: Path, rec: dict, run: "_Pipeline", elapsed: float) -> dict:
    """What the report is a record of: recipe, design, model, seeds, code, machine, date, time taken."""
    import os
    import platform

    def named(p):
        p = Path(p)
        return {"path": str(p), "sha256": file_key(p) if p.is_file() else None}

    t = rec["train"] or {}
    model = getattr(run, "model", None) or (rec["beacons"] or {}).get("model")
    return {"recipe": named(recipe_path), "design_recipe": named(rec["pipeline"]["design"]),
            "library": named(run.lib_path), "sensor": named(rec["pipeline"]["sensor"]),
            "turbulence": named(rec["pipeline"]["turbulence"]),
            "model": named(model) if model is not None else None,
            "training_recipe": named(t["recipe"]) if t.get("recipe") else None,
            "dataset_seed": (rec["dataset"] or {}).get("seed"), "metadesign": __version__, "commit": _git_commit(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "machine": f"{platform.node()} ({platform.system()} {platform.machine()}, {os.cpu_count()} cores, "
                       f"Python {platform.python_version()})",
            "elapsed_seconds": round(elapsed, 1)}


def _html(name: str, rep: dict) -> str:
    """The report: a headline (did it pass, what it achieved) first, then a section per stage, each table
    beside its figures with a caption saying what to look at."""
    css = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222;line-height:1.4}"
           "table{border-collapse:collapse;margin:0.5em 0 1em}td,th{border:1px solid #bbb;padding:3px 8px;"
           "font-size:13px;text-align:left}th{background:#eee}img{max-width:100%;border:1px solid #ddd}"
           "h2{border-bottom:1px solid #ccc;margin-top:2em}.pass{color:#070;font-weight:bold}"
           ".fail{color:#b00;font-weight:bold}.verdict{font-size:20px;padding:0.6em 1em;border-radius:6px;"
           "display:inline-block}.ok{background:#e6f4e6}.bad{background:#fbe3e3}figcaption{font-size:13px;"
           "color:#444;margin:0.3em 0 1.2em}.small{font-size:12px;color:#555}")
    checks = rep.get("checks", [])
    passed = all(c["passed"] for c in checks)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>metadesign report: {html.escape(name)}</title>",
             f"<style>{css}</style></head><body>", f"<h1>metadesign pipeline report: {html.escape(name)}</h1>",
             f"<p class='verdict {'ok' if passed else 'bad'}'>"
             + (f"All {len(checks)} checks passed" if passed else
                f"{sum(not c['passed'] for c in checks)} of {len(checks)} checks FAILED") + "</p>"]
    hl = rep.get("headline") or {}
    if hl.get("rows"):
        parts.append(f"<h2>What it achieved</h2><p>Wavefront estimate of the {html.escape(hl['estimator'])} from the 8 "
                     "sensor spots, applied as a phase correction to a beam sent back through the same turbulence; "
                     "NPiB: the power in the target bucket over a vacuum beam's.</p>" + _table(hl["rows"]))
    parts.append("<h2>Checks</h2>" + _table([
        {"check": c["check"], "value": c["value"], "threshold": c["threshold"],
         "result": "<span class='pass'>pass</span>" if c["passed"] else "<span class='fail'>FAIL</span>",
         "why": c["why"]} for c in checks], raw=("result",)))
    pv = rep.get("provenance")
    if pv:
        rows = []
        for k, v in pv.items():
            if isinstance(v, dict):
                v = f"{v['path']}" + (f" (sha256 {v['sha256'][:16]}...)" if v.get("sha256") else "")
            rows.append({"what": k.replace("_", " "), "value": "-" if v is None else str(v)})
        parts.append("<h2>Provenance</h2>" + _table(rows))
    parts.append("<p class='small'>metadesign " + html.escape(__version__) + "; stages: " + ", ".join(
        f"{k} ({'up to date, ran in %.1f s' % v.get('ran_seconds', float('nan')) if v.get('skipped') else '%.1f s' % v['seconds']})"
        for k, v in rep["stages"].items()) + "</p>")
    for sec, body in rep.get("sections", {}).items():
        parts.append(f"<h2>{html.escape(sec)}</h2>")
        for title, rows in body["tables"]:
            parts.append(f"<h3>{html.escape(title)}</h3>{_table(rows)}")
        for title, f, caption in body["figures"]:
            if Path(f).exists():
                parts.append(f"<figure><h3>{html.escape(title)}</h3>{_img(title, f)}"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)

"""The commands of the studies that combine stages: ``demo``, ``run`` (pipeline), ``compare``, ``retrieve``,
``tolerance``, ``transfer``, ``table-s2``, ``library lpa-check`` and ``dataset synth-captures``."""

from __future__ import annotations

import argparse
import contextlib
import json
from dataclasses import replace
from pathlib import Path

from ..cliutil import emit, integer, limit_arg, log_to, num, out_dir, out_file, progress_bar, workers_arg
from ..cards import card_path
from ..design.store import design_file
from ..io import atomic_write_text
from ..outputs import path_fields, product, zarr_input
from ..paths import recipe_path, repo_root
from ..validation import InputError

__all__ = ["register"]

#: the estimators metadesign registers (metadesign.reconstruction.estimators), named here so that ``--help``
#: need not import them; ``compare`` checks ``--methods`` against the live registry
BUILTIN_ESTIMATORS = ("shack_hartmann", "retrieval", "unet", "hybrid", "refine")


def _settings(a: argparse.Namespace, methods):
    from .compare import CompareSettings

    st = CompareSettings(split=a.split, limit=a.limit, noise_percent=a.noise, batch=a.batch, methods=tuple(methods))
    if a.iterations is not None:
        st = replace(st, retrieval=replace(st.retrieval, zonal_iterations=a.iterations))
    if getattr(a, "hybrid_iterations", None) is not None:
        st = replace(st, hybrid=replace(st.hybrid, zonal_iterations=a.hybrid_iterations))
    if a.starts is not None:
        st = replace(st, retrieval=replace(st.retrieval, starts=a.starts))
    return st


def _model_arg(model: str):
    if model.lower() == "none":
        return None
    from ..validation import ValidationError

    p = Path(model)
    if not p.is_file() and not p.with_name(p.name + ".json").is_file():
        raise ValidationError(f"{model}: no such model (give .safetensors with its .json card, or NONE)")
    return str(p)


def _lines(res, summ, out, tuning) -> list[str]:
    from .compare import BUDGETS_MS, label, methods_present

    ms = methods_present(res["rows"])
    lat = summ["latency_ms"]
    lines = [f"{res['n']} {res['settings'].split} samples, noise {res['settings'].noise_percent:g} % "
             f"({res['wall_seconds']:.0f} s) -> {out}",
             f"  {'method':<27} {'NPiB':>6} {'median':>7} {'latency':>11}   " + "   ".join(
                 f"@{b:g} ms" for b in BUDGETS_MS)]
    for m in ms:
        bud = "   ".join(f"{summ['budgets_ms'][f'{b:g}'][m]:6.3f}" if m in summ["budgets_ms"][f"{b:g}"] else "     -"
                         for b in BUDGETS_MS)
        lines.append(f"  {label(m):<27} {summ['npib'][m]:6.3f} {summ['npib_median'][m]:7.3f} "
                     f"{(f'{lat[m]:.3g} ms' if m in lat else '-'):>11}   {bud}")
    for k, b in summ["by_rytov"].items():
        lines.append(f"  Rytov {k:>8} (n {b['n']:3d}): " + ", ".join(f"{m} {b[m]:.3f}" for m in ms))
    if tuning:
        lines.append(f"  tuned on {tuning['samples']} {tuning['split']} samples: "
                     + "; ".join(f"{k} {v['npib']:.3f}" for k, v in tuning.items() if isinstance(v, dict)))
    return lines


def _cmd_compare(a: argparse.Namespace) -> int:
    from .compare import ESTIMATORS, run_compare, tune, write_compare
    from .madewith import made_with

    if a.methods is None:
        a.methods = list(ESTIMATORS)
    bad = [m for m in a.methods if m not in ESTIMATORS]
    if bad:
        raise InputError(f"--methods: {bad[0]!r} is not an estimator (registered: {', '.join(ESTIMATORS)})")

    model = _model_arg(a.model)
    out = out_dir(a.output or Path(a.dataset) / "compare")
    st = _settings(a, a.methods)
    log = log_to(a.json)
    inputs = {"model": a.model if model is not None else None, "dataset": zarr_input(a.dataset)}
    with product(out, "compare", inputs):
        tuning = None
        if a.tune:
            st, tuning = tune(model, a.dataset, st, a.tune, log=log)
        res = run_compare(model, a.dataset, st, workers=a.workers, progress=progress_bar("compare", unit="sample"))
        files = write_compare(res, out, tuning, made_with(model, a.dataset))
    from .compare import summarise

    summ = summarise(res)
    emit({"summary": summ, "settings": res["settings"].to_dict(), "tuning": tuning, "files": [str(f) for f in files],
          "wall_seconds": res["wall_seconds"]}, a.json, "\n".join(_lines(res, summ, out, tuning)))
    return 0


def _cmd_retrieve(a: argparse.Namespace) -> int:
    from .compare import run_compare, summarise, write_compare
    from .madewith import made_with

    model = _model_arg(a.model)
    methods = ("retrieval",) if model is None else ("unet", "hybrid")
    st = _settings(a, methods)
    if model is not None and a.iterations is not None:
        st = replace(st, hybrid=replace(st.hybrid, zonal_iterations=a.iterations))
    out = out_dir(a.output) if a.output else None
    inputs = {"model": a.model if model is not None else None, "dataset": zarr_input(a.dataset)}
    with product(out, "compare", inputs) if out else contextlib.nullcontext():
        res = run_compare(model, a.dataset, st, workers=a.workers, progress=progress_bar("retrieve", unit="sample"))
        summ = summarise(res)
        files = write_compare(res, out, made_with=made_with(model, a.dataset)) if out else []
        if out:
            files.append(_plot_convergence(res, out))
    name = methods[-1]
    mis = res["rows"][f"{name}_misfit"].mean(axis=1)
    doc = {"summary": summ, "settings": res["settings"].to_dict(), "files": [str(f) for f in files],
           "convergence": {"misfit_mean": mis.tolist(), "npib": summ["curves"].get(name)},
           "seconds_per_sample": res["wall_seconds"] / res["n"]}
    lines = _lines(res, summ, out or "(no output folder)", None)
    lines.append(f"  {name}: {res['wall_seconds'] / res['n'] * 1e3:.0f} ms per sample in batches of {st.batch}; "
                 "NPiB along the iterations: " + ", ".join(f"{c['iterations']}: {c['npib']:.3f}"
                                                        for c in summ["curves"].get(name, [])))
    emit(doc, a.json, "\n".join(lines))
    return 0


def _plot_convergence(res, out: Path) -> Path:
    import numpy as np

    from ..plotting import pyplot, save_figure
    from .compare import summarise

    plt = pyplot()
    summ = summarise(res)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for name in ("retrieval", "hybrid"):
        if f"{name}_misfit" in res["rows"]:
            m = res["rows"][f"{name}_misfit"]
            a1.semilogy(np.arange(1, len(m) + 1), m.mean(axis=1), label=name)
            cv = summ["curves"][name]
            a2.plot([c["iterations"] for c in cv], [c["npib"] for c in cv], "o-", label=name)
    a2.axhline(summ["npib"]["phase_conjugate"], ls="--", c="g", label="phase conjugate")
    a2.axhline(summ["npib"]["none"], ls=":", c="k", label="uncorrected")
    a1.set(xlabel="iteration", ylabel="mean misfit", title="convergence")
    a2.set(xlabel="iteration", ylabel="mean NPiB", title="NPiB along the iterations")
    a1.legend(fontsize=8)
    a2.legend(fontsize=8)
    return save_figure(fig, out / "convergence.png")


def _common(p, iterations_help: str) -> None:
    p.add_argument("dataset", help="dataset folder (its device pupil and provenance define the forward model)")
    p.add_argument("--split", default="test", choices=["test", "val", "train", "all"])
    p.add_argument("--limit", type=integer(1, 10**8), help="at most this many samples of the split")
    p.add_argument("--noise-percent", "--noise", dest="noise", type=num(0, 100, unit="%"), default=5.0,
                   help="sensor noise for every method, %% of each frame's peak (default 5, the demo model's)")
    p.add_argument("--iterations", type=integer(0, 100000), help=iterations_help)
    p.add_argument("--starts", type=integer(1, 64), help="retrieval: starts per sample in the modal stage (default 3)")
    p.add_argument("--batch", type=integer(1, 4096), default=8, help="samples per batch (default 8)")
    workers_arg(p)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


#: the recipe ``metadesign demo`` runs (packaged: sensing/demo-run.toml)
DEMO_RECIPE = "demo-run"


def _cmd_demo(a: argparse.Namespace) -> int:
    """``run`` on the packaged demo recipe, into ``./demo-out`` (a folder of kind "demo")."""
    return _run(recipe_path(DEMO_RECIPE, "sensing"), out_dir(a.output), "demo", a.json)


def _cmd_run(a: argparse.Namespace) -> int:
    recipe = recipe_path(a.recipe, "sensing")  # a path, or a packaged recipe's name: `run pipeline-demo`
    # the default output: beside a recipe of the user's, in the working directory for a packaged one
    packaged = recipe.resolve().is_relative_to(repo_root().resolve()) and not recipe.resolve().is_relative_to(
        Path.cwd().resolve())
    out = out_dir(a.output or (Path.cwd() if packaged else recipe.parent) / f"{recipe.stem}-out")
    return _run(recipe, out, "pipeline", a.json)


def _run(recipe: Path, out: Path, kind: str, as_json: bool) -> int:
    """A pipeline recipe into ``out``: each stage's line as it completes, then the headline, the checks and
    the report (``--json``: the summary alone, also written to OUT/summary.json); exit 1 on a failed check."""
    import time

    from .pipeline import run_pipeline

    def say(s):
        if not as_json:
            print(s, flush=True)

    t0 = time.perf_counter()
    with product(out, kind, {"recipe": recipe}):
        say(f"metadesign {'demo' if kind == 'demo' else 'run ' + str(recipe)} -> {out}/")
        rep = run_pipeline(recipe, out, log=say)
        failed = [c for c in rep["checks"] if not c["passed"]]
        summary = {"output": str(out), "recipe": str(recipe), "stages": rep["stages"], "tables": rep["tables"],
                   "checks": rep["checks"], "passed": not failed, "report": rep["report"],
                   "provenance": rep.get("provenance"), "seconds": time.perf_counter() - t0}
        atomic_write_text(out / "summary.json", json.dumps(summary, indent=2, sort_keys=True, default=str))
    lines = []
    est = (rep.get("headline") or {}).get("estimator", "U-Net")
    for row in rep["tables"].get("NPiB summary", []):
        lines.append(f"  NPiB at {row['noise_percent']:g} % noise: none {row['npib_none']:.3f}, {est} "
                     f"{row['npib_unet']:.3f}, phase conjugate {row['npib_phase_conjugate']:.3f}; captured "
                     f"{row['captured_fraction']:.2f}"
                     + (f" (U-Net alone {row['captured_fraction_unet_alone']:.2f})"
                        if "captured_fraction_unet_alone" in row else ""))
    figs = [Path(f).name for st in rep["stages"].values() for f in st.get("figures", [])]
    lines.append(f"  figures       {', '.join(figs)}")
    lines.append(f"  time          {summary['seconds']:.1f} s")
    lines.append(f"  checks        {len(rep['checks']) - len(failed)}/{len(rep['checks'])} passed"
                 + "".join(f"\n    FAILED: {c['check']}: {c['value']} (needs {c['threshold']})" for c in failed))
    lines.append(f"  report        {rep['report']}")
    emit(summary, as_json, "\n".join(lines))
    return 1 if failed else 0  # a failed check is a failed run


def _cmd_table_s2(a: argparse.Namespace) -> int:
    from .table_s2 import run_table_s2

    out = out_dir(a.output or Path(a.recipe).with_suffix("").with_name(Path(a.recipe).stem + "-out"))
    with product(out, "table-s2", {"recipe": a.recipe}):
        rep = run_table_s2(a.recipe, out, workers=a.workers, log=log_to(a.json))
    lines = [f"Table S2 ({rep['samples']} samples at Rytov {rep['rytov']}, {rep['epochs']} epochs) -> {out}",
             "  model split  PiB ratio (mean of NPiB_unet / NPiB_pc)  ratio of means   NPiB U-Net / none / conjugate"]
    for r in rep["rows"]:
        lines.append(f"  {r['model']:<5} {r['split']:<5}  {100 * r['pib_ratio']:6.1f} %                        "
                     f"{100 * r['pib_ratio_of_means']:6.1f} %          {r['npib_unet']:.3f} / {r['npib_none']:.3f} / "
                     f"{r['npib_phase_conjugate']:.3f}")
    lines.append("  paper: E2E 96.3 % / 96.0 %, MSE 94.6 % / 71.5 % (train / test)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_tolerance(a: argparse.Namespace) -> int:
    from .tolerance import load_tolerance_recipe, run_tolerance

    rec = load_tolerance_recipe(a.recipe)
    out = out_dir(a.output or Path(a.recipe).with_suffix("").with_name(Path(a.recipe).stem + "-out"))
    with product(out, "tolerance", {"recipe": a.recipe, **path_fields(rec)}):
        rep = run_tolerance(rec, out, workers=a.workers, log=log_to(a.json))
    lines = [f"fab tolerance of {rec.model.name} at {rep['noise_percent']:g} % noise -> {out} ({Path(rep['figure']).name})",
             "  case              NPiB U-Net  captured  gain(median) | fine-tuned U-Net  captured | conjugate  none"]
    for r in rep["rows"]:
        b, f = r["before"], r.get("after")
        lines.append(f"  {r['case']:<16}  {b['npib_unet']:.3f}       {b['captured_fraction']:5.2f}     "
                     f"{b['gain_median']:6.1f}     | " + (f"{f['npib_unet']:.3f}             {f['captured_fraction']:5.2f}"
                                                           if f else "  -                  -  ")
                     + f"     | {b['npib_phase_conjugate']:.3f}      {b['npib_none']:.3f}")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_codesign(a: argparse.Namespace) -> int:
    from .codesign import read_diversity, run_codesign_report

    read_diversity(a.run)  # a bad run is one line before anything is written
    out = out_dir(a.output)
    run_file = Path(a.run) / "diversity.json" if Path(a.run).is_dir() else Path(a.run)
    inputs = {"run": run_file, "--dataset": zarr_input(a.dataset), "--base": a.base}
    recipe = out_file(a.recipe, "--recipe", suffixes=(".toml",)) if a.recipe else None
    with product(out, "codesign", inputs), \
            (product(recipe, "design-recipe", {**inputs, "-o": out}) if recipe else contextlib.nullcontext()):
        rep = run_codesign_report(a.run, a.dataset, a.base, out, modes=a.modes, samples=a.fisher_samples,
                                  photons=a.photons, read_noise_e=a.read_noise_e, random=a.random,
                                  recipe=recipe, log=log_to(a.json))
    m = rep["fisher"]["mean_crb_rad2"]
    lines = [f"co-designed sensor -> {out}: design recipe {Path(rep['design_recipe']).name}, "
             + ", ".join(Path(f).name for f in rep["figures"]),
             f"  mean Cramer-Rao bound over Noll 2..{1 + a.modes} at {a.photons:.0e} photons (rms rad): "
             + ", ".join(f"{k} {v ** 0.5:.3g}" for k, v in m.items())]
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_synth(a: argparse.Namespace) -> int:
    from ..sensing.camera import Alignment, CameraSpec
    from .captures import synth_captures

    out = out_dir(a.output)
    al = Alignment(a.shift[0], a.shift[1], a.rotation_deg, a.scale)
    cam = CameraSpec(peak_counts=a.peak_counts, photons_at_peak=a.photons, read_noise_e=a.read_noise_e,
                     dark_counts=a.dark_counts, hot_pixels=a.hot_pixels, seed=a.seed)
    rep = synth_captures(a.phases, a.device, out, al, cam, samples=a.samples, split=a.split, fmt=a.format,
                         saturate=a.saturate, seed=a.seed, progress=progress_bar("captures", unit="frame"))
    emit(rep, a.json, f"wrote {out}: {rep['samples']} samples ({rep['format']}), {rep['flats']} flat and "
         f"{rep['darks']} dark captures, {rep['saturated']} over-exposed; manifest {out / 'manifest.csv'}")
    return 0


def _cmd_transfer(a: argparse.Namespace) -> int:
    from .transfer import load_transfer_recipe, run_transfer

    rec = load_transfer_recipe(a.recipe)
    out = out_dir(a.output or Path(a.recipe).with_name(Path(a.recipe).stem + "-out"))
    with product(out, "transfer", {"recipe": a.recipe, **path_fields(rec)}):
        rep = run_transfer(rec, out, workers=a.workers, log=log_to(a.json),
                           progress=None if a.json else progress_bar("captures", unit="frame"))
    r = rep["rows"]
    tr, fi = rep["truth_alignment"], rep["fitted_alignment"]
    lines = [f"transfer to captured frames -> {out} ({Path(rep['figure']).name}); relay true "
             f"({tr['shift_x_px']:+.2f}, {tr['shift_y_px']:+.2f}) px {tr['rotation_deg']:+.3f} deg x{tr['scale']:.4f}, "
             f"fitted ({fi['shift_x_px']:+.2f}, {fi['shift_y_px']:+.2f}) px {fi['rotation_deg']:+.3f} deg x{fi['scale']:.4f}",
             "  model                 NPiB mean  median  captured"]
    for k in ("unadapted", "scratch", "finetuned"):
        if k in r:
            lines.append(f"  {k:<20}  {r[k]['npib_unet']:.3f}      {r[k]['npib_unet_median']:.3f}   "
                         f"{r[k]['captured_fraction']:.2f}")
    lines.append(f"  uncorrected {r['unadapted']['npib_none']:.3f}, phase conjugate "
                 f"{r['unadapted']['npib_phase_conjugate']:.3f} ({r['unadapted']['n']} test captures)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_lpa(a: argparse.Namespace) -> int:
    import json

    import numpy as np

    from ..io import atomic_write_text
    from ..sensing.model import AsFabricated
    from .lpa import lpa_check, lpa_downstream, plot_lpa

    src = Path(a.design)
    out = out_dir(a.output or (src.parent if src.is_file() else src) / "lpa-check")
    if (a.dataset is None) != (a.model is None):
        from ..validation import ValidationError

        raise ValidationError("--dataset and --model go together (the downstream NPiB needs both)")
    log = log_to(a.json)
    inputs = {"design": design_file(src), "--dataset": zarr_input(a.dataset) if a.dataset else None,
              "--model": a.model}
    with product(out, "lpa-check", inputs):
        if src.is_dir():
            from ..design.store import load_design

            fab = AsFabricated.from_design(load_design(src))
        else:
            fab = AsFabricated.from_files(src)
        im, w = fab.layout.index_map, fab.layout.atom_widths_nm
        mask = None
        if (fab.aperture or {}).get("kind") == "circle":
            n2 = im.shape[0] // 2
            x = (np.arange(n2) - (n2 - 1) / 2) * 2 * fab.period
            mask = x[None, :] ** 2 + x[:, None] ** 2 <= (im.shape[0] * fab.period / 2) ** 2 * 0.98
        log(f"lpa-check: {a.supercells} supercells of {src} (period {fab.period * 1e6:.3f} um, 2 x 2) ...")
        rep = lpa_check(im, w, fab.lib, a.supercells, a.harmonics, a.seed, a.workers, a.check, mask,
                        progress=None if a.json else progress_bar("supercells", unit="cell"))
        eps = rep.pop("_eps")
        rep.pop("_contrast"), rep.pop("_spread")
        if a.dataset is not None:
            log("downstream: channel metrics and NPiB with the measured error ...")
            rep["downstream"] = lpa_downstream(eps, a.dataset, a.model, fab, a.samples, a.noise, a.seed, log)
        atomic_write_text(out / "lpa.json", json.dumps(rep, indent=1))
        rep["figure"] = str(plot_lpa(rep, out / "lpa.png"))
    L, Ll = rep["lpa"], rep["lpa_library"]
    lines = [f"LPA error on {rep['supercells']} supercells (RCWA nG {rep['n_harmonics_supercell']}, unit cells nG "
             f"{rep['n_harmonics_unit']}; 1.5x harmonics change <= "
             + ("/".join(f"{v:.1e}" for v in rep["convergence_rel_change_max"]) if rep["convergence_rel_change_max"]
                else "-") + f") -> {out}",
             "                       x-pol        y-pol",
             f"  |eps| mean          {L['rel_magnitude_mean'][0]:.4f}       {L['rel_magnitude_mean'][1]:.4f}",
             f"  |eps| median / p90  {L['rel_magnitude_median'][0]:.3f}/{L['rel_magnitude_p90'][0]:.3f}  "
             f"{L['rel_magnitude_median'][1]:.3f}/{L['rel_magnitude_p90'][1]:.3f}",
             f"  phase RMS [rad]     {L['phase_rms_rad'][0]:.4f}       {L['phase_rms_rad'][1]:.4f}",
             f"  |dt| / rms|t_i|     {L['abs_error_over_unit_rms_mean'][0]:.4f}       "
             f"{L['abs_error_over_unit_rms_mean'][1]:.4f}",
             f"  |1+eps| mean        {L['amplitude_ratio_mean'][0]:.4f}       {L['amplitude_ratio_mean'][1]:.4f}",
             f"  vs library |eps|    {Ll['rel_magnitude_mean'][0]:.4f}       {Ll['rel_magnitude_mean'][1]:.4f}",
             "  corr(|eps|, width contrast) "
             + " / ".join("-" if v is None else f"{v:+.2f}" for v in rep["corr_error_vs_width_contrast"])]
    d = rep.get("downstream")
    if d:
        lines.append(f"  NPiB ({d['samples']} test samples, {d['noise_percent']:g} % noise): nominal "
                     f"{d['nominal']['npib_unet']:.4f}, independent {d['independent']['npib_unet']:.4f}, correlated "
                     f"{d['correlated']['npib_unet']:.4f} (none {d['npib_none']:.3f}, conjugate "
                     f"{d['npib_phase_conjugate']:.3f})")
        for k in ("focusing_efficiency", "strehl", "crosstalk"):
            v = [np.mean([c[k] for c in d[m]["channels"]]) for m in ("nominal", "independent", "correlated")]
            lines.append(f"  mean {k:<20} {v[0]:.4f} -> {v[1]:.4f} (independent), {v[2]:.4f} (correlated)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_supercells(a: argparse.Namespace) -> int:
    from .supercells import build_table, load_supercell_recipe, supercell_need

    rec = load_supercell_recipe(a.recipe)
    out = out_file(Path(a.output) if a.output else rec.default_output(), suffixes=(".npz",))
    log = log_to(a.json)
    n = a.supercells or rec.supercells
    inputs = {"recipe": rec.source, "table.library": rec.library, "table.design": rec.design,
              "table.extra_design": rec.extra_design}
    with product(out, "supercells", inputs, scratch=(out.with_name(out.name + ".partial"),),
                 need=supercell_need(n, rec.n_harmonics, a.workers)):
        rep = build_table(rec, out, supercells=a.supercells, workers=a.workers, scheduler=a.scheduler,
                          progress=None if a.json else progress_bar("supercells", unit="cell"), log=log)
    emit(rep, a.json, f"wrote {out}: {rep['supercells']} supercells ({rep['held_out']} held out), nG "
                      f"{rep['n_harmonics']}; {rep['solve_seconds']:.0f} s solving here "
                      f"({rep['seconds_per_supercell_core']:.1f} s per supercell per core)")
    return 0


def _cmd_ladder(a: argparse.Namespace) -> int:
    import numpy as np

    from ..library.locate import find_library
    from ..library.store import load_library
    from ..library.supercells import load_table
    from .supercells import convergence_ladder

    table = load_table(a.table)
    tp = Path(a.table)
    held = np.flatnonzero(table.test)
    if not len(held):
        raise InputError(f"{tp}: the table has no held-out rows")
    lib_path = Path(a.library) if a.library else find_library(table.meta["library"]["sha256"],
                                                                table.meta["library"]["path"], tp.parent)
    lib = load_library(lib_path)
    out = out_file(Path(a.output) if a.output else tp.with_name(tp.stem + "-ladder.json"), suffixes=(".json",))
    log = log_to(a.json)
    with product(out, "ladder", {"table": tp, "--library": lib_path}, scratch=(out.with_name(out.name + ".partial"),)):
        rep = convergence_ladder(table, lib, held[:a.rows], a.harmonics, out.with_name(out.name + ".partial"),
                                 workers=a.workers, scheduler=a.scheduler,
                                 progress=None if a.json else progress_bar("supercells", unit="cell"), log=log)
        rep.pop("_labels")
        rep = {"format": "metadesign.ladder/1", **rep,
               "table": {"path": tp.name, "n_harmonics": table.meta.get("n_harmonics")}}
        atomic_write_text(out, json.dumps(rep, indent=1))
    lines = [f"wrote {out}: {len(rep['rows'])} held-out supercells of {tp.name}"]
    for st in rep["steps"]:
        lines.append(f"  nG {st['from']} -> {st['to']}: label change mean {st['label_change_mean_both']:.4f}, max "
                     f"{st['label_change_max_both']:.4f} of rms|t_i| (raw t: mean "
                     f"{np.mean(st['raw_t_change']['mean']):.4f}); converged (<= 0.01): "
                     + ("yes" if st["label_change_max_both"] <= 0.01 else "no"))
    tl = rep["table_labels"]["vs_top_level"]
    lines.append(f"  the table's labels (nG {rep['table']['n_harmonics']}) vs the top level: mean "
                 f"{np.mean(tl['mean']):.4f}, max {np.max(tl['max']):.4f}")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_patches(a: argparse.Namespace) -> int:
    import numpy as np

    from ..design.store import design_library
    from ..library.supercells import remove_partial
    from .supercells import design_source, patch_study, plot_patches

    ring_levels = sorted(set(a.ring_levels or ()))
    if ring_levels and a.patches < 4:
        raise InputError(f"--ring-levels: calibrating the ring's coefficients needs >= 4 patches, got {a.patches}")
    src = Path(a.design)
    d, _ = design_source(src if src.suffix == ".toml" else Path(design_file(src)), log_to(a.json))
    lib = design_library(d, a.library)
    base = src.parent if src.suffix in (".toml", ".npz") else src
    out = out_file(Path(a.output) if a.output else base / "patches.json", suffixes=(".json",))
    log = log_to(a.json)
    partial = out.with_name(out.name + ".partial")
    with product(out, "patches", {"design": src, "--library": a.library, "--peds": a.peds},
                 also=(out.with_suffix(".png"),) if ring_levels or a.windows else (), scratch=(partial,)):
        rep = patch_study(d, lib, a.patches, a.seed, a.harmonics, partial,
                          workers=a.workers, scheduler=a.scheduler,
                          progress=None if a.json else progress_bar("patches", unit="patch"), log=log,
                          ring_levels=ring_levels, windows=a.windows, peds=a.peds)
        rep = {"format": "metadesign.patches/1", "design": str(src), **rep}
        if ring_levels or a.windows:
            rep["figure"] = plot_patches(rep, out.with_suffix(".png")).name
        atomic_write_text(out, json.dumps(rep, indent=1))
        remove_partial(partial)
    nh = rep["n_harmonics"]
    lines = [f"wrote {out}: {rep['patches']} 4 x 4 patches (nG {nh['patch']}; supercells {nh['supercell']}, "
             f"unit cells {nh['unit']}): beyond the 2 x 2 cell, mean "
             f"{rep['beyond_2x2_mean_both']:.4f} (p90 {rep['beyond_2x2_p90_both']:.4f}) of rms|t_i|; the LPA "
             f"vs the patch {np.mean(rep['lpa_vs_patch']['mean']):.4f}"]
    if "ring" in rep:
        rg = rep["ring"]
        for h, st in rg["raw_per_level"].items():
            lines.append(f"  ring low fidelity at supercell nG request {h}, uncalibrated: mean {np.mean(st['mean']):.4f}"
                         f" (p90 {np.mean(st['p90']):.4f})")
        lines.append(f"  ring low fidelity calibrated ({len(rg['levels'])} complex coefficients, each patch held out):"
                     f" mean {rg['calibrated_held_out_mean_both']:.4f} (p90 {rg['calibrated_held_out_p90_both']:.4f});"
                     f" {rg['seconds_per_patch_core']:.2f} core-s per patch")
    for k, what in (("windows_exact", "solved at the patch's supercell truncation"),
                    ("windows_peds", "under the certified (PEDS) model")):
        if k in rep:
            st = rep[k]
            lines.append(f"  overlapping windows, {what}: the ring left {st['mean_both']:.4f} mean "
                         f"(p90 {st['p90_both']:.4f})")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_active(a: argparse.Namespace) -> int:
    from ..library.coupling import CouplingConfig
    from ..library.store import load_library
    from ..library.supercells import load_table
    from .active import ActiveConfig, active_learning, plot_active
    from .supercells import load_supercell_recipe, pool_widths

    rec = load_supercell_recipe(a.recipe)
    tp = rec.default_output()
    if not tp.exists():
        raise InputError(f"{a.recipe}: its table {tp} is not built (metadesign library supercells {a.recipe})")
    table, ref = load_table(tp), load_table(a.reference)
    if ref.meta.get("library", {}).get("sha256") != table.meta.get("library", {}).get("sha256"):
        raise InputError(f"--reference {a.reference}: solved against another library than {tp.name}")
    if int((~table.test).sum()) < a.start + a.rounds * a.batch:
        raise InputError(f"--start + --rounds x --batch = {a.start + a.rounds * a.batch} solves: the random "
                         f"baseline needs as many fitting rows; {tp.name} has {int((~table.test).sum())}")
    out = out_file(Path(a.output) if a.output else rec.source.with_name(rec.source.stem + "-active.json"),
                   suffixes=(".json",))
    cfg = ActiveConfig(a.start, a.batch, a.rounds, a.members, a.pool, steps=a.steps,
                       model=CouplingConfig(hidden=a.hidden, layers=3, interaction="environment"))
    log = log_to(a.json)
    lib = load_library(rec.library)
    with product(out, "active", {"recipe": rec.source, "table": tp, "--reference": a.reference},
                 scratch=(out.with_name(out.name + ".partial"),), also=(out.with_suffix(".png"),)):
        pool = pool_widths(rec, a.pool, log)
        rep = active_learning(table, ref, lib, pool, out.with_name(out.name + ".partial"), cfg, workers=a.workers,
                              scheduler=a.scheduler, log=log)
        rep.pop("members")
        rep = {"format": "metadesign.active/1", **rep}
        fig = plot_active(rep, out.with_suffix(".png"))
        rep["figure"] = fig.name
        atomic_write_text(out, json.dumps(rep, indent=1))
    act, rnd = rep["active"][-1], rep["random"][-1]
    emit(rep, a.json, f"wrote {out} and {fig.name}: after {act['solves']} solves, held-out mean error "
                      f"{act['mean']:.4f} (p90 {act['p90']:.4f}) active vs {rnd['mean']:.4f} (p90 {rnd['p90']:.4f}) "
                      "random")
    return 0


def _cmd_coupling(a: argparse.Namespace) -> int:
    from ..library.locate import find_library
    from ..library.store import load_library
    from ..library.supercells import load_table

    table = load_table(a.table)
    tp = Path(a.table)
    lib_path = Path(a.library) if a.library else find_library(table.meta["library"]["sha256"],
                                                                table.meta["library"]["path"], tp.parent)
    lib = load_library(lib_path)
    out = out_file(Path(a.output) if a.output else
                   tp.with_name(tp.stem.replace("-supercells", "") + "-coupling.safetensors"),
                   suffixes=(".safetensors",))
    if not table.test.any() or table.test.all():
        raise InputError(f"{tp}: the table has {int(table.test.sum())} held-out rows of {len(table.test)}: "
                         "certification needs both fitting and held-out rows (table.test_every >= 2)")
    ref = None
    if a.reference:
        ref = load_table(a.reference)
        if ref.meta.get("library", {}).get("sha256") != table.meta.get("library", {}).get("sha256"):
            raise InputError(f"--reference {a.reference}: solved against another library than {tp.name}")
        if not ref.test.any():
            raise InputError(f"--reference {a.reference}: the table has no held-out rows")
    log = log_to(a.json)
    with product(out, "coupling", {"table": tp, "--library": lib_path, "--reference": a.reference},
                 also=(card_path(out), out.with_suffix(".png"))):
        return _coupling_fit(a, table, tp, lib, lib_path, out, log, ref)


def _coupling_fit(a, table, tp, lib, lib_path, out, log, ref=None) -> int:
    import numpy as np

    from ..library.coupling import CouplingConfig, save_coupling
    from ..library.locate import file_sha256
    from .supercells import certify_coupling, plot_coupling

    cfg = CouplingConfig(a.hidden, a.layers, a.ensemble, a.interaction)
    log(f"coupling model on {tp.name}: {int((~table.test).sum())} fitting rows, {int(table.test.sum())} held out")
    model, rep = certify_coupling(table, lib, a.sizes, cfg, a.steps, a.seed, weight_decay=a.weight_decay,
                                  reference=ref, log=log)
    fig = plot_coupling(rep, out.with_suffix(".png"))
    rep.pop("_e"), rep.pop("_e_lpa")
    card = {"certification": rep, "table": {"path": tp.name, "sha256": file_sha256(tp)}, "figure": fig.name,
            "reference_table": {"path": Path(a.reference).name, "sha256": file_sha256(a.reference)}
            if ref is not None else None,
            "structure": "t = mean_i t_lib(w_i) + 1/4 sum_i [G(f_i, f_H, f_V, f_D) - G(f_i, f_i, f_i, f_i)]; "
                         "t_y(w) = t_x(transpose(w))"}
    save_coupling(out, model, lib_path, card)
    rep["output"], rep["figure"] = str(out), str(fig)
    m, l = rep["model"], rep["lpa"]
    lines = [f"wrote {out} (+ .json card, {fig.name}): held-out |t - t_RCWA| / rms|t_i| on "
             f"{rep['held_out_supercells']} supercells never fitted",
             "                    x-pol mean / p90     y-pol mean / p90",
             f"  coupling model    {m['mean'][0]:.4f} / {m['p90'][0]:.4f}      {m['mean'][1]:.4f} / {m['p90'][1]:.4f}",
             f"  LPA               {l['mean'][0]:.4f} / {l['p90'][0]:.4f}      {l['mean'][1]:.4f} / {l['p90'][1]:.4f}",
             f"  goal              <= {rep['goal']['mean']:g} / <= {rep['goal']['p90']:g}: "
             + ("met" if rep["passed"] else "NOT met"),
             "  learning curve: " + ", ".join(f"{c['supercells']}: {np.mean(c['held_out']['mean']):.4f}"
                                               for c in rep["learning_curve"])]
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_peds(a: argparse.Namespace) -> int:
    import numpy as np

    from ..cards import read_card
    from ..library.coupling import CARD_FORMAT
    from ..library.locate import file_sha256, find_library
    from ..library.peds import save_peds
    from ..library.store import load_library
    from ..library.supercells import load_table, matched_unit_harmonics, remove_partial
    from .supercells import certify_peds, plot_peds

    table = load_table(a.table)
    tp = Path(a.table)
    if not table.test.any() or table.test.all():
        raise InputError(f"{tp}: the table has {int(table.test.sum())} held-out rows of {len(table.test)}: "
                         "certification needs both fitting and held-out rows (table.test_every >= 2)")
    if table.t_unit is not None:
        raise InputError(f"{tp}: a table solved at nG {table.meta.get('n_harmonics')} with matched unit cells is a "
                         "low fidelity itself; calibrate on a converged table (solved at the library's truncation)")
    top = table.meta.get("n_harmonics") or 0
    if a.select and len(set(a.harmonics)) > 8:
        raise InputError(f"--select: at most 8 candidate levels (2^K - 1 subsets are cross-validated), got "
                         f"{len(set(a.harmonics))}")
    if max(a.harmonics) >= top:
        raise InputError(f"--harmonics {max(a.harmonics)}: the levels must lie below the table's truncation (nG {top})")
    lib_path = Path(a.library) if a.library else find_library(table.meta["library"]["sha256"],
                                                                table.meta["library"]["path"], tp.parent)
    lib = load_library(lib_path)
    resolved: dict[int, list[int]] = {}
    for h in sorted(set(a.harmonics)):
        resolved.setdefault(matched_unit_harmonics(h, lib.stack)[0] - 1, []).append(h)
    for nG, hs in resolved.items():
        if len(hs) > 1:
            raise InputError(f"--harmonics {' '.join(map(str, hs))}: these requests solve the same truncation "
                             f"(nG {nG}); give distinct levels")
    networks = {}
    for i, path in enumerate(a.network or ()):
        _, _, card = read_card(path, CARD_FORMAT, "coupling model")
        if not isinstance(card.get("certification"), dict) or "learning_curve" not in card["certification"]:
            raise InputError(f"--network {path}: its card holds no certification (learning curve) to draw")
        name = f"{Path(path).name.split('.')[0]}, on {(card.get('table') or {}).get('path', '?')}"
        networks[name if name not in networks else f"{name} ({i + 1})"] = card["certification"]
    out = out_file(Path(a.output) if a.output else tp.with_name(tp.stem.replace("-supercells", "") + "-peds.json"),
                   suffixes=(".json",))
    partial = out.with_name(out.name + ".partial")
    log = log_to(a.json)
    with product(out, "peds", {"table": tp, "--library": lib_path,
                               **{f"--network {i + 1}": p for i, p in enumerate(a.network or ())}},
                 also=(out.with_suffix(".png"),), scratch=(partial,)):
        model, rep = certify_peds(table, lib, a.harmonics, a.sizes, partial, workers=a.workers, scheduler=a.scheduler,
                                  select=a.select, progress=None if a.json else progress_bar("supercells", unit="cell"),
                                  log=log)
        fig = plot_peds(rep, out.with_suffix(".png"), networks)
        rep.pop("_e"), rep.pop("_e_lpa")
        rep["networks"] = {k: {"learning_curve": v["learning_curve"], "mean_both": v.get("mean_both"),
                               "p90_both": v.get("p90_both")} for k, v in networks.items()}
        card = {"certification": rep, "figure": fig.name,
                "table": {"path": tp.name, "sha256": file_sha256(tp)},
                "library_path": lib_path.name}
        save_peds(out, replace(model, card=card))
        remove_partial(partial)
    rep["output"], rep["figure"] = str(out), str(fig)
    m, l = rep["model"], rep["lpa"]
    lines = [f"wrote {out} (+ {fig.name}): PEDS surrogate, levels nG "
             + ", ".join(str(v["n_harmonics"]) for v in rep["levels"] if v.get("chosen", True)) + ", coefficients "
             + ", ".join(f"{complex(*c):.3f}" for c in rep["learning_curve"][-1]["coef"]),
             f"  held-out |t - t_RCWA| / rms|t_i| on {rep['held_out_supercells']} supercells never fitted",
             "                    x-pol mean / p90     y-pol mean / p90",
             f"  PEDS              {m['mean'][0]:.4f} / {m['p90'][0]:.4f}      {m['mean'][1]:.4f} / {m['p90'][1]:.4f}",
             f"  LPA               {l['mean'][0]:.4f} / {l['p90'][0]:.4f}      {l['mean'][1]:.4f} / {l['p90'][1]:.4f}"]
    for v in rep["levels"]:
        lines.append(f"  nG {v['n_harmonics']:<4d} alone      {np.mean(v['alone']['mean']):.4f} / "
                     f"{np.mean(v['alone']['p90']):.4f} (both)   {v['seconds_per_supercell_core']:.3f} s per supercell"
                     + ("" if v.get("chosen", True) else "   (not chosen)"))
    if rep["selection"]:
        sel = rep["selection"]
        lines.append(f"  levels by {sel['folds']}-fold cross-validation on {sel['rows']} fitting rows (mean / p90, "
                     "s per supercell; the cheapest by nG^3 within 2 % of the best is kept):")
        for r in sorted(sel["subsets"], key=lambda r: r["cv_mean"]):
            lines.append(f"    nG {'+'.join(str(rep['levels'][j]['n_harmonics']) for j in r['levels']):<20s}"
                         f"{r['cv_mean']:.4f} / {r['cv_p90']:.4f}   "
                         f"{sum(rep['levels'][j]['seconds_per_supercell_core'] for j in r['levels']):.3f}"
                         + ("   <- chosen" if r["levels"] == sel["chosen"] else ""))
    lines += [f"  goal              <= {rep['goal']['mean']:g} / <= {rep['goal']['p90']:g}: "
              + ("met" if rep["passed"] else "NOT met") + f" (both: {rep['mean_both']:.4f} / {rep['p90_both']:.4f})",
              "  learning curve: " + ", ".join(f"{c['supercells']}: {np.mean(c['held_out']['mean']):.4f}"
                                               for c in rep["learning_curve"]),
              f"  cost: {rep['cost']['seconds_per_supercell_core']:.3f} s per supercell per core "
              f"({rep['cost']['core_hours_per_million']:.0f} core-hours per million)"
              + (f"; a converged label {rep['cost']['label_seconds_per_supercell_core']:.2f} s"
                 if rep["cost"]["label_seconds_per_supercell_core"] else "")]
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_coupling_check(a: argparse.Namespace) -> int:
    import json

    import numpy as np

    from ..design.store import load_design
    from ..io import atomic_write_text
    from ..library.locate import file_sha256
    from ..library.store import load_library
    from ..library.supercells import remove_partial
    from ..paths import product as packaged
    from ..sensing.model import AsFabricated, load_sensing_recipe
    from ..sensing.transmission import Perturbation
    from ..validation import ValidationError
    from .coupling_check import CASES, coupling_check, plot_case_metrics, plot_coupling_frames

    if (a.dataset is None) != (a.model is None):
        raise ValidationError("--dataset and --model go together (the NPiB needs both)")
    if a.ring and not a.certified:
        raise ValidationError("--ring: the neighbour ring adds to the certified model; give --certified N")
    if a.ring and a.ring < a.replicates:
        raise ValidationError(f"--ring {a.ring}: at least one supercell per replicate (--replicates {a.replicates})")
    if a.reoptimise and not a.certified:
        raise ValidationError("--reoptimise: re-chooses the sampled supercells' atoms; give --certified N")
    if a.reoptimise == 1:
        raise ValidationError("--reoptimise 1: K counts the atom itself, so at least 2 (0: none)")
    if a.reoptimise and (a.bias_nm or a.jitter_nm or a.height_nm or a.sidewall_deg != 90):
        raise ValidationError("--reoptimise: the atoms are re-chosen for the nominal device (no --bias-nm, "
                              "--jitter-nm, --height-nm or --sidewall-deg)")
    if a.certified and a.certified < 2 * a.replicates:
        raise ValidationError(f"--certified {a.certified}: at least two supercells per replicate "
                              f"(--replicates {a.replicates}), so >= {2 * a.replicates}")
    src = Path(a.design)
    out = out_dir(a.output or (src if src.is_dir() else src.parent) / "coupling-check")
    partial = out.with_name(out.name + ".partial")
    log = log_to(a.json)
    inputs = {"design": design_file(src), "--compensated": design_file(a.compensated) if a.compensated else None,
              "--coupling-model": a.coupling_model, "--sensor": a.sensor,
              "--dataset": zarr_input(a.dataset) if a.dataset else None, "--model": a.model,
              "--peds": a.peds, "--fab-library": a.fab_library}
    with product(out, "coupling-check", inputs, scratch=(partial,)):
        designs = {"coupled": load_design(src)}
        fab = AsFabricated.from_design(designs["coupled"])
        if a.fab_library:
            fab.fab_lib = load_library(a.fab_library)
        if a.height_nm or a.sidewall_deg != 90:
            F = fab.fab_lib if fab.fab_lib is not None else fab.lib
            if F.fab is None:
                raise ValidationError("--height-nm / --sidewall-deg need a library with fab axes: pass --fab-library "
                                      "(e.g. library/paper-fab.npz)")
            hs = (np.asarray(F.fab["heights"]) - fab.lib.stack.height) * 1e9
            if not hs.min() - 1e-6 <= a.height_nm <= hs.max() + 1e-6:
                raise ValidationError(f"--height-nm {a.height_nm:g}: the fab library spans {hs.min():+.0f} to "
                                      f"{hs.max():+.0f} nm")
            ws = np.asarray(F.fab["sidewalls"], float)
            if not ws.min() - 1e-9 <= a.sidewall_deg <= ws.max() + 1e-9:
                raise ValidationError(f"--sidewall-deg {a.sidewall_deg:g}: the fab library spans {ws.min():g} to "
                                      f"{ws.max():g} deg")
        fabs = {"lpa": fab, "coupled": fab.with_coupling("supercell", a.coupling_model)}
        if a.compensated:
            designs["compensated"] = load_design(a.compensated)
            fc = AsFabricated.from_design(designs["compensated"])
            fc.fab_lib = fab.fab_lib
            fabs["compensated"] = fc.with_coupling("supercell", a.coupling_model)
            fabs["compensated_lpa"] = fc
        if a.dataset:
            from ..reconstruction.dataset import load_device

            dev = load_device(a.dataset)
            sensor, grid = dev.sensor, dev.pupil.G.shape[-1]
            if dev.pupil.block != fab.pupil_block(grid):
                raise ValidationError(f"{a.dataset}: its device's pupil ({dev.pupil.block}-cell blocks) is not this "
                                      "design's on that grid: use the dataset made with this design")
        else:
            sr = load_sensing_recipe(a.sensor or packaged("sensing", "paper.toml"))
            sensor, grid = sr.sensor, sr.pupil_grid
        log(f"coupling-check: {src} ({', '.join(CASES[k] for k in fabs)}) ...")
        cert = {"supercells": a.certified, "replicates": a.replicates, "partial": partial, "peds": a.peds,
                "workers": a.workers, "scheduler": a.scheduler, "seed": a.seed,
                "taper_slices": a.taper_slices, "ring_supercells": a.ring,
                "reoptimise": (a.reoptimise, a.reoptimise_sweeps) if a.reoptimise else None} if a.certified else None
        rep, frames = coupling_check(fabs, sensor, grid, a.dataset, a.model, a.samples, a.noise, log=log,
                                     certified=cert, pert=Perturbation.from_nm(a.bias_nm, jitter_nm=a.jitter_nm,
                                                                               seed=a.jitter_seed,
                                                                               height_nm=a.height_nm,
                                                                               sidewall_deg=a.sidewall_deg),
                                     designs=designs)
        rep["figure"] = str(plot_coupling_frames(frames, sensor, out / "coupling-frames.png"))
        if cert:
            rep["metrics_figure"] = str(plot_case_metrics(rep, out / "coupling-metrics.png"))
        rep["coupling_model_sha256"] = fabs["coupled"].coupling_card["weights_sha256"]
        rep["design"] = {"path": str(src), "sha256": file_sha256(design_file(src))}  # coupling-sweep matches it
        atomic_write_text(out / "coupling-check.json", json.dumps(rep, indent=1))
        remove_partial(partial)
    wl = max(27, *(len(c["label"]) for c in rep["cases"].values()))
    lines = [f"wrote {out}/coupling-check.json and coupling-frames.png",
             f"  {'case':<{wl}} spot eff.  spot Strehl  stray    |focal shift| um"
             + ("   U-Net NPiB" if "downstream" in rep else "")]
    for name, c in rep["cases"].items():
        mm = c["mean"]
        npib = rep.get("downstream", {}).get(name, {}).get("npib_unet")
        lines.append(f"  {c['label']:<{wl}} {mm['spot_efficiency']:.4f}     {mm['spot_strehl']:.3f}        "
                     f"{mm['stray']:.4f}   {1e3 * mm['focal_shift_mm']:7.1f}"
                     + (f"          {npib:.3f}" if npib is not None else ""))
        if "stderr" in c:
            se = c["stderr"]
            lines.append(f"  {'  +- (standard error)':<{wl}} {se['spot_efficiency']:.4f}     "
                         f"{se['spot_strehl']:.3f}        {se['stray']:.4f}   {1e3 * se['focal_shift_mm']:7.1f}"
                         f"   ({c['sampling']['supercells']} supercells of {c['sampling']['eligible_supercells']:,})"
                         + (f"   NPiB +- {rep['downstream'][name]['npib_unet_se']:.3f}"
                            if name in rep.get("downstream", {}) else ""))
        eff = ((c.get("ring") or {}).get("effect") or (c.get("reoptimise") or {}).get("effect"))
        if eff:  # a case measured on the same replicates as its plain one: the difference and its error
            lines.append(f"  {'  effect (matched replicates)':<{wl}} "
                         + ", ".join(f"{k} {v['mean'] * (1e3 if k == 'focal_shift_mm' else 1):+.4g} +- "
                                     f"{v['stderr'] * (1e3 if k == 'focal_shift_mm' else 1):.2g}"
                                     for k, v in eff.items()).replace("focal_shift_mm", "focal shift (um)"))
    if "downstream" in rep:
        d = rep["downstream"]
        lines.append(f"  NPiB uncorrected {d['npib_none']:.3f}, phase conjugate {d['npib_phase_conjugate']:.3f} "
                     f"({d['samples']} test samples, {d['noise_percent']:g} % noise)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_coupling_sweep(a: argparse.Namespace) -> int:
    from .coupling_check import plot_sweep, sweep_axis, sweep_table

    reports, inputs = [], {}
    for i, folder in enumerate(a.reports):
        path = Path(folder) / "coupling-check.json" if Path(folder).is_dir() else Path(folder)
        try:
            rep = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"{folder}: not a coupling-check output ({exc})") from None
        if not isinstance(rep, dict) or "cases" not in rep:
            raise InputError(f"{folder}: not a coupling-check output (no cases)")
        reports.append(rep)
        inputs[f"report {i + 1}"] = path
    designs = {(r.get("design") or {}).get("sha256") for r in reports} - {None}
    if len(designs) > 1:
        raise InputError("the reports are of different designs (their design sha256 differ): one design per sweep")
    if len(reports) > 1:
        try:
            sweep_axis(reports)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    out = out_file(a.output, suffixes=(".png",))
    table = sweep_table(reports)
    with product(out, "figure", inputs):
        fig = plot_sweep(table, out)
    table["figure"] = str(fig)
    head = {"bias_nm": "  bias nm  ", "height_nm": "  etch nm  ", "sidewall_deg": "  wall deg "}[table["axis"]]
    lines = [f"wrote {fig}", head + "  ".join(f"{r['label'][:30]:>30}" for r in table["cases"].values())]
    for j, b in enumerate(table[table["axis"]]):
        cells = []
        for r in table["cases"].values():
            se = r["spot_efficiency_se"][j]
            cells.append(f"{r['spot_efficiency'][j]:.4f}" + (f" +- {se:.4f}" if se else "        "))
        lines.append(f"  {b:+7.1f}  " + "  ".join(f"{c:>30}" for c in cells))
    emit(table, a.json, "\n".join(lines + ["  (spot efficiency; the figure has Strehl, stray and focal shift)"]))
    return 0


def register(sub, groups: dict) -> None:
    """Add the study commands: top-level ones to ``sub``, ``library lpa-check`` and ``dataset synth-captures``
    to the stage groups in ``groups``."""
    c = sub.add_parser(
        "compare", help="every estimator (Shack-Hartmann, retrieval, U-Net, hybrid, learned refinement) on the same samples: NPiB and latency",
        description="Every wavefront sensor on the same samples and the same sensor noise: uncorrected, a "
        "simulated Shack-Hartmann, model-based phase-diversity retrieval on the 8 PSFs, the U-Net, the "
        "U-Net + retrieval hybrid, the learned refinement (when MODEL is a refiner: its U-Net runs too), and "
        "the phase/complex conjugate bounds. NPiB per sample vs Rytov number, NPiB vs single-sample latency "
        "(and vs iterations or refinement steps), NPiB at 1/10/100 ms budgets; CSV, JSON and figures in -o.")
    c.add_argument("model", help="U-Net or refiner weights (.safetensors with its .json card), or NONE")
    _common(c, "zonal iterations of the retrieval (default 100)")
    c.add_argument("--hybrid-iterations", type=integer(0, 100000), help="iterations of the hybrid (default 50)")
    c.add_argument("--methods", nargs="+", metavar="ESTIMATOR",
                   help="estimators to run (default: all registered: " + ", ".join(BUILTIN_ESTIMATORS)
                   + " and any registered later)")
    c.add_argument("--tune", type=integer(0, 10000), default=0, metavar="N",
                   help="first tune every baseline on N validation samples (grids in metadesign.studies.compare)")
    c.add_argument("-o", "--output", help="output folder (default: DATASET/compare)")
    c.set_defaults(func=_cmd_compare)

    r = sub.add_parser(
        "retrieve", help="baselines: model-based phase-diversity retrieval (or the hybrid) on a dataset split",
        description="Estimate the received phase from the 8 PSFs by fitting the differentiable as-fabricated "
        "model (Zernike start coarse to fine, then per pixel phase and amplitude; Adam). MODEL: start from "
        "the U-Net's prediction (the hybrid); NONE: retrieval alone. Reports NPiB, wall time per sample and "
        "the convergence curve.")
    r.add_argument("model", help="U-Net weights to start from (the hybrid), or NONE")
    _common(r, "zonal iterations (default 100 alone, 50 from the U-Net)")
    r.add_argument("-o", "--output", help="output folder for CSV, JSON and figures (default: print only)")
    r.set_defaults(func=_cmd_retrieve)
    tf = sub.add_parser(
        "transfer", help="stage 6: fab-to-lab transfer learning on (synthetic) captured frames",
        description="Render the lab device (the design as made) and SLM screens, synthesise camera captures "
        "through a misaligned relay, import them against the nominal dataset, and compare the synthetic model "
        "unadapted, fine-tuned from it (--init) and trained from scratch on the same captures.")
    tf.add_argument("recipe", help="transfer recipe (TOML), e.g. sensing/transfer-demo.toml")
    tf.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe)")
    workers_arg(tf)
    tf.add_argument("--json", action="store_true", help="print the summary as JSON")
    tf.set_defaults(func=_cmd_transfer)
    tol = sub.add_parser(
        "tolerance", help="stage 6: reconstruction-level fab tolerance (NPiB vs bias/jitter/corner, fine-tune recovery)",
        description="For each fabrication case of the recipe (one-at-a-time sweeps of width bias, jitter and "
        "corner rounding around the nominal device): render a dataset through the perturbed layout (same "
        "turbulence samples in every case), evaluate the nominal model on its test split, fine-tune it on the "
        "case's small training split (train --init) and evaluate again. Resumable; writes OUT/tolerance.csv, "
        ".json and .png.")
    tol.add_argument("recipe", help="tolerance recipe (TOML), e.g. sensing/tolerance-demo.toml")
    tol.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe)")
    workers_arg(tol)
    tol.add_argument("--json", action="store_true", help="print the table as JSON")
    tol.set_defaults(func=_cmd_tolerance)
    t2 = sub.add_parser("table-s2", help="stage 6: reproduce Table S2 (E2E vs MSE loss: train and test PiB ratio)",
                        description="Build the recipe's dataset, train the same U-Net with the end-to-end PiB loss "
                        "and with the MSE phase loss, and evaluate both on their train and test splits.")
    t2.add_argument("recipe", help="Table S2 recipe (TOML), e.g. sensing/table-s2.toml")
    t2.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe)")
    workers_arg(t2)
    t2.add_argument("--json", action="store_true", help="print the table as JSON")
    t2.set_defaults(func=_cmd_table_s2)
    cd = sub.add_parser(
        "codesign", help="stage 6: the co-designed sensor as a device recipe, its diversity and Fisher information",
        description="From a co-design run (metadesign train with a [codesign] section: diversity.json beside "
        "the U-Net): the design recipe of the device with the learned diversity (OUT/design.toml: --base with "
        "each lens's learned focal length and Zernike terms; build, lay out and simulate it like any design), "
        "the diversity and the PSFs of a flat wavefront beside the paper's (diversity.png), and the Cramer-Rao "
        "bounds of the first Zernike modes for the paper's, the learned and random diversities (fisher.png, "
        "codesign.json).")
    cd.add_argument("run", help="co-design training run folder (or its diversity.json)")
    cd.add_argument("--dataset", required=True, help="the dataset it was trained on (its device and received fields)")
    cd.add_argument("--base", required=True, help="the base design recipe (TOML), e.g. layouts/paper-5mm.toml")
    cd.add_argument("--modes", type=integer(1, 64), default=20, help="Zernike modes Noll 2..N+1 (default 20)")
    cd.add_argument("--fisher-samples", type=integer(0, 1000), default=4,
                    help="received fields of the test split the information is averaged over, besides a flat one")
    cd.add_argument("--photons", type=num(1.0, 1e15), default=1e6, help="photo-electrons per frame (default 1e6)")
    cd.add_argument("--read-noise-e", type=num(0.0, 1e6), default=0.0, help="read noise per pixel (e-)")
    cd.add_argument("--random", type=integer(0, 100), default=2, help="random diversities to compare (default 2)")
    cd.add_argument("-o", "--output", required=True, help="output folder")
    cd.add_argument("--recipe", help="also write the design recipe here (e.g. layouts/codesign-demo.toml: its "
                    "library named relative to it, ready to commit beside the other design recipes)")
    cd.add_argument("--json", action="store_true", help="print the summary as JSON")
    cd.set_defaults(func=_cmd_codesign)
    lsub, dsub = groups["library"], groups["dataset"]
    lp = lsub.add_parser(
        "lpa-check", help="measure the local-periodic approximation's error with supercell RCWA",
        description="Solve random 2 x 2 supercells of a design with RCWA (four different pillars, both "
        "polarisations) and compare their 0th-order transmission with the LPA (the mean of the four unit-cell "
        "values); with --dataset and --model, apply the measured error to the device pupil and report the "
        "channel metrics and the model's NPiB.")
    lp.add_argument("design", help="layout (.oas/.gds) or design folder")
    lp.add_argument("--supercells", type=integer(1, 100000), default=32, help="supercells to solve (default 32)")
    lp.add_argument("--harmonics", type=integer(50, 5000), default=800,
                    help="supercell harmonics requested (default 800: the library's resolution at period 2p)")
    lp.add_argument("--check", type=integer(0, 100), default=2,
                    help="supercells re-solved at 1.5x the harmonics (convergence; default 2)")
    lp.add_argument("--seed", type=integer(0, 2**63 - 1), default=0)
    lp.add_argument("--dataset", help="dataset whose device pupil and test samples serve the downstream study")
    lp.add_argument("--model", help="U-Net weights for the downstream NPiB")
    limit_arg(lp, "at most this many test samples downstream (64)", type=integer(1, 100000), default=64)
    lp.add_argument("--noise-percent", "--noise", dest="noise", type=num(0, 100, unit="%"), default=5.0,
                    help="sensor noise downstream, %% of peak (5)")
    lp.add_argument("-o", "--output", help="output folder (default: lpa-check/ beside the design)")
    workers_arg(lp)
    lp.add_argument("--json", action="store_true", help="print the report as JSON")
    lp.set_defaults(func=_cmd_lpa)
    sc = lsub.add_parser(
        "supercells", help="solve a design's 2 x 2 supercells with RCWA: the coupling model's table (resumable)",
        description="Draw supercells from what the design uses (its layout's 4-tuples, a second design's, random "
        "atom 4-tuples, jittered atoms; each row from its own seeded generator), solve each with supercell RCWA "
        "at the harmonics matched to the library, and write the table (.npz, with provenance). Chunks are kept "
        "in OUT.partial/ as they finish: run again after any interruption; --supercells N grows a table "
        "without re-solving its rows. Same bytes on any worker count or scheduler.")
    sc.add_argument("recipe", help="supercell recipe (TOML), e.g. library/paper-supercells.toml")
    sc.add_argument("--supercells", type=integer(1, 10_000_000), help="rows (default: the recipe's)")
    sc.add_argument("-o", "--output", help="table file (default: RECIPE with .npz)")
    sc.add_argument("--scheduler", help="Dask scheduler address (default: the local pool)")
    workers_arg(sc)
    sc.add_argument("--json", action="store_true", help="print the summary as JSON")
    sc.set_defaults(func=_cmd_supercells)
    cp = lsub.add_parser(
        "coupling", help="fit and certify the supercell coupling model on a supercell table",
        description="Fit the coupling model (LPA mean + a learned neighbour term, symmetric by construction) on "
        "the first N fitting rows of TABLE for each N of --sizes (a learning curve), certify it on every held-out "
        "row, and write the weights (.safetensors), the card (.json: certification, learning curve) and a "
        "figure.")
    cp.add_argument("table", help="supercell table (.npz) from `library supercells`")
    cp.add_argument("--library", help="the unit-cell library (default: the table's, found by sha256)")
    cp.add_argument("--reference", metavar="TABLE", help="certify on this table's held-out rows instead of the "
                    "fitted table's (e.g. a cheaper table fitted, the converged one certifying)")
    cp.add_argument("--sizes", type=integer(10, 10_000_000), nargs="+", default=[250, 500, 1000],
                    help="fitting rows of the learning curve (default 250 500 1000; the last is the model)")
    cp.add_argument("--steps", type=integer(1, 10_000_000), default=2000, help="optimiser steps per fit (2000)")
    cp.add_argument("--hidden", type=integer(4, 4096), default=32, help="hidden width of the network (32)")
    cp.add_argument("--layers", type=integer(2, 16), default=3, help="layers of the network (3)")
    cp.add_argument("--ensemble", type=integer(1, 64), default=1, help="networks averaged (1)")
    cp.add_argument("--interaction", choices=("pair", "environment"), default="pair",
                    help="pair: two-body terms over the row, column and diagonal neighbour (a design's pupil "
                    "becomes table look-ups, and `design compensate` needs it); environment: one term sees all "
                    "three neighbours (default pair)")
    cp.add_argument("--weight-decay", type=num(0, 1), default=1e-3, help="Adam weight decay (1e-3)")
    cp.add_argument("--seed", type=integer(0, 2**31 - 1), default=0)
    cp.add_argument("-o", "--output", help="weights file (default: TABLE's name with -coupling.safetensors)")
    cp.add_argument("--json", action="store_true", help="print the report as JSON")
    cp.set_defaults(func=_cmd_coupling)
    pe = lsub.add_parser(
        "peds", help="calibrate and certify the PEDS supercell surrogate (cheap solves + fitted coefficients)",
        description="Solve every row of a converged supercell TABLE at the low truncations of --harmonics (each "
        "with its unit cells at the matched truncation; resumable chunks in OUT.partial/), fit one complex "
        "coefficient per level on the first N fitting rows for each N of --sizes (a learning curve), certify each "
        "fit on every held-out row, and write the model with its card (.json) and a figure (.png).")
    pe.add_argument("table", help="converged supercell table (.npz) from `library supercells`")
    pe.add_argument("--harmonics", type=integer(20, 5000), nargs="+", default=[97, 220],
                    help="requested low-fidelity truncations (97 220: nG 89 and 213)")
    pe.add_argument("--sizes", type=integer(1, 10_000_000), nargs="+", default=[10, 25, 50, 100, 250, 500, 1000],
                    help="fitting rows of the learning curve (the largest, at most the table's fitting rows, is "
                    "the model)")
    pe.add_argument("--select", action="store_true",
                    help="treat --harmonics as candidates: keep the cheapest subset within 2 %% of the best by "
                    "5-fold cross-validation on the fitting rows (the held-out rows play no part)")
    pe.add_argument("--network", nargs="+", metavar="CARD",
                    help="coupling models' cards whose learning curves to draw beside (the network alone)")
    pe.add_argument("--library", help="the unit-cell library (default: the table's, found by sha256)")
    pe.add_argument("-o", "--output", help="model (.json; default: TABLE's name with -peds.json)")
    pe.add_argument("--scheduler", help="Dask scheduler address (default: the local pool)")
    workers_arg(pe)
    pe.add_argument("--json", action="store_true", help="print the report as JSON")
    pe.set_defaults(func=_cmd_peds)
    ld = lsub.add_parser(
        "ladder", help="convergence of a supercell table's labels: held-out rows re-solved at rising truncation",
        description="Re-solve the first --rows held-out rows of TABLE at each truncation of --harmonics (each with "
        "its unit cells at the matched truncation; resumable chunks in OUT.partial/), and report per step the "
        "change of each row's label (the library's LPA plus the coupling measured at that truncation) in units "
        "of the pillars' rms |t| (a converged label moves by <= 0.01), and how far the table's own labels lie "
        "from the top level. Writes OUT (.json).")
    ld.add_argument("table", help="supercell table (.npz)")
    ld.add_argument("--rows", type=integer(1, 100000), default=8, help="held-out rows re-solved (8)")
    ld.add_argument("--harmonics", type=integer(20, 5000), nargs="+", default=[320, 800, 1300],
                    help="requested supercell truncations, ascending (320 800 1300)")
    ld.add_argument("--library", help="the unit-cell library (default: the table's, found by sha256)")
    ld.add_argument("-o", "--output", help="report (.json; default: TABLE-ladder.json)")
    ld.add_argument("--scheduler", help="Dask scheduler address (default: the local pool)")
    workers_arg(ld)
    ld.add_argument("--json", action="store_true", help="print the report as JSON")
    ld.set_defaults(func=_cmd_ladder)
    pa = lsub.add_parser(
        "patches", help="beyond the periodic 2 x 2 cell: 4 x 4 patches of a design against their four supercells",
        description="Cut 4 x 4 patches from DESIGN (aligned to its supercells), solve each as a periodic 4 x 4 "
        "cell (its supercells see other supercells around them, as in the device) and its four 2 x 2 "
        "supercells periodically at the matched truncation, and report the difference (the error of every "
        "2 x 2 model, the certified one included) beside the LPA's, in units of the pillars' rms |t|. "
        "Resumable (OUT.partial/). Writes OUT (.json).")
    pa.add_argument("design", help="design folder, design.npz or design recipe (.toml)")
    pa.add_argument("--patches", type=integer(1, 100000), default=8, help="patches (8)")
    pa.add_argument("--harmonics", type=integer(50, 20000), default=1300,
                    help="requested patch harmonics (1300: the supercells at 325, the unit cells at 81)")
    pa.add_argument("--seed", type=integer(0, 2**63 - 1), default=0)
    pa.add_argument("--library", help="the unit-cell library (default: the design's)")
    pa.add_argument("--ring-levels", type=integer(20, 2000), nargs="+", metavar="N",
                    help="the neighbour-ring low fidelity: requested supercell truncations at which each patch and "
                         "its four supercells are solved again, matched (e.g. 45 97: the PEDS levels' range)")
    pa.add_argument("--windows", action="store_true",
                    help="also the overlapping-window ring: each patch as the mean of its sixteen 2 x 2 windows, "
                         "solved at the supercells' matched truncation and under the certified (PEDS) model")
    pa.add_argument("--peds", help="with --windows: the certified model (default: the PEDS model calibrated "
                                   "against the library)")
    pa.add_argument("-o", "--output", help="report (.json; default: patches.json beside the design)")
    pa.add_argument("--scheduler", help="Dask scheduler address (default: the local pool)")
    workers_arg(pa)
    pa.add_argument("--json", action="store_true", help="print the report as JSON")
    pa.set_defaults(func=_cmd_patches)
    al = lsub.add_parser(
        "active", help="active learning of the coupling model: new solves where an ensemble disagrees (#34)",
        description="From the first --start fitting rows of the recipe's table (built by `library supercells`), "
        "fit --members coupling models, rank a pool of candidate supercells drawn like the table's rows by the "
        "members' spread, solve the --batch most uncertain (the table's truncation, resumable chunks in "
        "OUT.partial/), add them and repeat for --rounds; after each round the ensemble is certified on "
        "--reference's held-out rows beside the same number of random solves. Writes OUT (.json) and a figure.")
    al.add_argument("recipe", help="supercell recipe (TOML) whose table exists (e.g. library/paper-supercells-fast.toml)")
    al.add_argument("--reference", required=True, metavar="TABLE", help="the converged table whose held-out rows certify")
    al.add_argument("--start", type=integer(2, 1_000_000), default=250, help="initial random solves (250)")
    al.add_argument("--batch", type=integer(1, 1_000_000), default=250, help="solves per round (250)")
    al.add_argument("--rounds", type=integer(1, 100), default=4, help="rounds (4)")
    al.add_argument("--members", type=integer(2, 16), default=4, help="ensemble members (4)")
    al.add_argument("--pool", type=integer(10, 10_000_000), default=8000, help="candidates drawn (8000)")
    al.add_argument("--steps", type=integer(1, 1_000_000), default=2000, help="optimiser steps per fit (2000)")
    al.add_argument("--hidden", type=integer(4, 4096), default=64, help="hidden width (64)")
    al.add_argument("-o", "--output", help="report (.json; default: RECIPE-active.json)")
    al.add_argument("--scheduler", help="Dask scheduler address (default: the local pool)")
    workers_arg(al)
    al.add_argument("--json", action="store_true", help="print the report as JSON")
    al.set_defaults(func=_cmd_active)
    cc = lsub.add_parser(
        "coupling-check", help="a design under the LPA vs the supercell coupling model (and compensated)",
        description="Channel metrics (focusing efficiency, Strehl, crosstalk, focal shift) and the 8-PSF frames "
        "of DESIGN under the LPA and under the supercell coupling model, and of --compensated (a `design "
        "compensate` output) under both; with --dataset and --model, the U-Net's NPiB on the dataset's test "
        "samples re-rendered through each. Writes OUT/coupling-check.json and figures.")
    cc.add_argument("design", help="design folder (nearest-atom)")
    cc.add_argument("--compensated", help="the compensated design folder")
    cc.add_argument("--coupling-model", help="coupling model (default: the one fitted against the library)")
    cc.add_argument("--sensor", help="sensing recipe (default: sensing/paper.toml; the dataset's with --dataset)")
    cc.add_argument("--dataset", help="dataset whose test samples are re-rendered (its device's sensor and grid)")
    cc.add_argument("--model", help="U-Net weights for the NPiB")
    limit_arg(cc, "at most this many test samples (64)", type=integer(1, 100000), default=64)
    cc.add_argument("--noise-percent", "--noise", dest="noise", type=num(0, 100, unit="%"), default=5.0,
                    help="sensor noise, %% of peak (5)")
    cc.add_argument("--certified", type=integer(0, 10_000_000), default=0, metavar="N",
                    help="also each coupled design under the certified (PEDS) model, its correction measured on N "
                    "supercells drawn at random (0.2 s each per core; resumable in OUT.partial/); 0: off (default)")
    cc.add_argument("--replicates", type=integer(3, 256), default=8,
                    help="independent replicates of the --certified sample (jackknife error bars; 8)")
    cc.add_argument("--peds", help="certified model (default: the PEDS model calibrated against the library)")
    cc.add_argument("--ring", type=integer(0, 10_000_000), default=0, metavar="N",
                    help="with --certified: also the neighbour ring on the first N of the sampled supercells, by "
                         "overlapping windows (the certified model on each one's three 2 x 2 windows straddling "
                         "towards its neighbours; 0: none)")
    cc.add_argument("--reoptimise", type=integer(0, 256), default=0, metavar="K",
                    help="with --certified, nominal widths: also each sampled supercell's atoms re-chosen under the "
                         "certified model (each position tries its atom's K nearest atoms in phase, as the "
                         "compensating discretizer does under the pair model): the device re-optimised under the "
                         "certified model, estimated from the same sample without making it (0: none)")
    cc.add_argument("--reoptimise-sweeps", type=integer(1, 8), default=1,
                    help="sweeps over the four positions of --reoptimise (1)")
    cc.add_argument("--seed", type=integer(0, 2**63 - 1), default=0, help="seed of the --certified sample (0)")
    cc.add_argument("--bias-nm", type=num(-50, 50, unit="nm"), default=0.0,
                    help="every device made with this width bias (nm; a fab study under each model; 0)")
    cc.add_argument("--jitter-nm", type=num(0, 20, unit="nm"), default=0.0,
                    help="every device made with this random width error per pillar (nm, sigma; 0)")
    cc.add_argument("--jitter-seed", type=integer(0, 2**63 - 1), default=0, help="seed of the jitter (0)")
    cc.add_argument("--height-nm", type=num(-100, 100, unit="nm"), default=0.0,
                    help="every device made with this etch-depth error (pillar height - nominal, nm; needs "
                    "--fab-library; the certified model solves at that height; 0)")
    cc.add_argument("--sidewall-deg", type=num(60, 90, unit="deg"), default=90.0,
                    help="every device made with this wall angle (90 = vertical; needs --fab-library; the certified "
                    "model's low fidelity tapers its pillars in --taper-slices slices; 90)")
    cc.add_argument("--taper-slices", type=integer(0, 64), default=4,
                    help="slices of the certified model's tapered supercells with --sidewall-deg (0: vertical at "
                    "mid-height widths; 4)")
    cc.add_argument("--fab-library", help="library with height / sidewall axes for --height-nm / --sidewall-deg "
                    "(e.g. library/paper-fab.npz)")
    cc.add_argument("--scheduler", help="Dask scheduler address for the certified solves (default: the local pool)")
    workers_arg(cc)
    cc.add_argument("-o", "--output", help="output folder (default: coupling-check/ beside the design)")
    cc.add_argument("--json", action="store_true", help="print the report as JSON")
    cc.set_defaults(func=_cmd_coupling_check)
    sw = lsub.add_parser(
        "coupling-sweep", help="fab-tolerance curves from coupling-check reports at several width biases or etch "
        "depths",
        description="Reads coupling-check outputs of one design (the same --seed, so the certified points "
        "share their sample) made with different --bias-nm (or different --height-nm) and draws spot "
        "efficiency, Strehl, stray light and focal shift against that perturbation under each device model (LPA, "
        "coupling model, certified with its error bars); reports of different designs, or differing in both, "
        "are refused. Writes OUT (.png).")
    sw.add_argument("reports", nargs="+", help="coupling-check output folders (or their coupling-check.json)")
    sw.add_argument("-o", "--output", required=True, help="figure (.png)")
    sw.add_argument("--json", action="store_true", help="print the table as JSON")
    sw.set_defaults(func=_cmd_coupling_sweep)
    sy = dsub.add_parser(
        "synth-captures", help="synthetic camera captures from a dataset's phases through a (perturbed) device",
        description="The SLM shows the received phases of PHASES' samples; frames are rendered through DEVICE's "
        "coarse pupil onto a misaligned camera with shot and read noise, dark offset and hot pixels (16-bit PNG, "
        "TIFF or .npy), with flat and dark captures and a manifest: input for `dataset import`.")
    sy.add_argument("phases", help="dataset whose received phases the SLM shows (also the sensor geometry)")
    sy.add_argument("--device", required=True, help="dataset of the device to render (older datasets: or their device-pupil.npz)")
    sy.add_argument("-o", "--output", required=True, help="capture folder to write")
    sy.add_argument("--split", choices=("train", "val", "test", "all"), default="all", help="samples of PHASES")
    limit_arg(sy, "at most this many samples of the split", type=integer(1, 10_000_000))
    sy.add_argument("--shift", nargs=2, type=num(-200, 200), default=(0.0, 0.0), metavar=("DX", "DY"),
                    help="relay shift, camera pixels")
    sy.add_argument("--rotation-deg", type=num(-10, 10), default=0.0)
    sy.add_argument("--scale", type=num(0.8, 1.25), default=1.0, help="relay magnification / nominal")
    sy.add_argument("--format", choices=("png", "tiff", "fits", "npy"), default="png")
    sy.add_argument("--peak-counts", type=num(1, 65535), default=40000.0)
    sy.add_argument("--photons", type=num(0, 1e9), default=20000.0, help="photo-electrons at the peak (0: none)")
    sy.add_argument("--read-noise-e", type=num(0, 1e4), default=5.0)
    sy.add_argument("--dark-counts", type=num(0, 65535), default=100.0)
    sy.add_argument("--hot-pixels", type=integer(0, 100000), default=20)
    sy.add_argument("--saturate", type=integer(0, 10_000_000), default=0,
                    help="over-expose the last N samples (2x: clipped at full scale)")
    sy.add_argument("--seed", type=integer(0, 2**63 - 1), default=0)
    sy.add_argument("--json", action="store_true", help="print the report as JSON")
    sy.set_defaults(func=_cmd_synth)


def register_main(sub) -> None:
    """``demo`` and ``run``: the commands a new user starts with."""
    demo = sub.add_parser("demo", help="run the embedded demo through every stage",
                          description="Run the small embedded demo through every stage (from the committed "
                          "unit-cell library): `run` on the packaged recipe demo-run (sensing/demo-run.toml); "
                          "writes summary.json, the figures and report.html; a second run is up to date.")
    demo.add_argument("-o", "--output", default="demo-out", help="output folder (default: ./demo-out)")
    demo.add_argument("--json", action="store_true", help="print the summary as JSON")
    demo.set_defaults(func=_cmd_demo)
    run = sub.add_parser("run", help="every stage from a pipeline recipe, with an HTML report",
                         description="Run a pipeline recipe: library, design, layout (verified), as-fabricated "
                         "PSFs and fab study, turbulence validation, dataset, training (or a given model), "
                         "evaluation (or fresh beacons through a second device: [beacons]); stages whose inputs "
                         "did not change are skipped; writes OUT/summary.json and OUT/report.html "
                         "(self-contained: every figure and table).")
    run.add_argument("recipe", help="pipeline recipe (TOML), e.g. sensing/pipeline-demo.toml, or the name of a "
                     "packaged one (pipeline-demo: works from a wheel install)")
    run.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe; for a packaged "
                     "recipe, in the working directory)")
    run.add_argument("--json", action="store_true", help="print the summary as JSON")
    run.set_defaults(func=_cmd_run)

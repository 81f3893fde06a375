"""The supercell commands of the ``library`` group: ``supercells``, ``coupling``, ``peds``, ``ladder``,
``patches`` and ``active``."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

from ..cliutil import emit, integer, log_to, num, out_file, progress_bar, workers_arg
from ..cards import card_path
from ..design.store import design_file
from ..execution import Execution, scratch_path
from ..io import atomic_write_text
from ..outputs import product
from ..validation import InputError

__all__ = ["register"]


def _cmd_supercells(a: argparse.Namespace) -> int:
    from .supercells import build_table, load_supercell_recipe, supercell_need

    rec = load_supercell_recipe(a.recipe)
    out = out_file(Path(a.output) if a.output else rec.default_output(), suffixes=(".npz",))
    log = log_to(a.json)
    n = a.supercells or rec.supercells
    inputs = {"recipe": rec.source, "table.library": rec.library, "table.design": rec.design,
              "table.extra_design": rec.extra_design}
    with product(out, "supercells", inputs, scratch=(scratch_path(out),),
                 need=supercell_need(n, rec.n_harmonics, a.workers)):
        rep = build_table(rec, out, a.supercells, Execution(workers=a.workers, scheduler=a.scheduler, log=log,
                                                            progress=None if a.json else progress_bar("supercells",
                                                                                                      unit="cell")))
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
    with product(out, "ladder", {"table": tp, "--library": lib_path}, scratch=(scratch_path(out),)):
        run = Execution(workers=a.workers, scheduler=a.scheduler, log=log,
                        progress=None if a.json else progress_bar("supercells", unit="cell"))
        rep = convergence_ladder(table, lib, held[:a.rows], a.harmonics, scratch_path(out), run)
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

    from .supercell_patches import patch_need
    from .supercells import PatchSettings, design_source, patch_study, plot_patches

    settings = PatchSettings(a.patches, a.seed, a.harmonics, tuple(a.ring_levels or ()), a.windows, a.peds)
    src = Path(a.design)
    d, _ = design_source(src if src.suffix == ".toml" else Path(design_file(src)), log_to(a.json))
    lib = design_library(d, a.library)
    base = src.parent if src.suffix in (".toml", ".npz") else src
    out = out_file(Path(a.output) if a.output else base / "patches.json", suffixes=(".json",))
    partial = scratch_path(out)
    run = Execution(workers=a.workers, scheduler=a.scheduler, log=log_to(a.json),
                    progress=None if a.json else progress_bar("patches", unit="patch"))
    with product(out, "patches", {"design": src, "--library": a.library, "--peds": a.peds},
                 also=(out.with_suffix(".png"),) if settings.ring_levels or a.windows else (), scratch=(partial,),
                 need=patch_need(settings, lib.stack, run.workers)):
        rep = patch_study(d, lib, settings, partial, run)
        rep = {"format": "metadesign.patches/1", "design": str(src), **rep}
        if settings.ring_levels or a.windows:
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
                 scratch=(scratch_path(out),), also=(out.with_suffix(".png"),)):
        pool = pool_widths(rec, a.pool, log)
        rep = active_learning(table, ref, lib, pool, scratch_path(out), cfg,
                              Execution(workers=a.workers, scheduler=a.scheduler, log=log))
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
    import numpy as np

    from ..library.coupling import CouplingConfig
    from .coupling_cert import CouplingFit, check_coupling_inputs, coupling_study, load_coupling_inputs

    table, lib_path, lib = load_coupling_inputs(a.table, a.library)
    tp = Path(a.table)
    out = out_file(Path(a.output) if a.output else
                   tp.with_name(tp.stem.replace("-supercells", "") + "-coupling.safetensors"),
                   suffixes=(".safetensors",))
    inputs = check_coupling_inputs(table, lib, tp, lib_path, a.reference)
    fit = CouplingFit(tuple(a.sizes), CouplingConfig(a.hidden, a.layers, a.ensemble, a.interaction), a.steps, a.seed,
                      a.weight_decay)
    with product(out, "coupling", {"table": tp, "--library": lib_path, "--reference": a.reference},
                 also=(card_path(out), out.with_suffix(".png"))):
        rep = coupling_study(inputs, fit, out, log_to(a.json))
    fig = Path(rep["figure"])
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


    from ..library.locate import file_sha256
    from ..library.peds import save_peds
    from ..library.supercells import remove_partial
    from .peds_cert import PedsSettings, certify_peds, load_peds_inputs, plot_peds

    settings = PedsSettings(tuple(a.harmonics), tuple(a.sizes), select=a.select)
    table, lib_path, lib, networks = load_peds_inputs(a.table, settings, a.library, a.network)
    tp = Path(a.table)
    out = out_file(Path(a.output) if a.output else tp.with_name(tp.stem.replace("-supercells", "") + "-peds.json"),
                   suffixes=(".json",))
    partial = scratch_path(out)
    run = Execution(workers=a.workers, scheduler=a.scheduler, log=log_to(a.json),
                    progress=None if a.json else progress_bar("supercells", unit="cell"))
    with product(out, "peds", {"table": tp, "--library": lib_path,
                               **{f"--network {i + 1}": p for i, p in enumerate(a.network or ())}},
                 also=(out.with_suffix(".png"),), scratch=(partial,)):
        model, rep = certify_peds(table, lib, settings, partial, run)
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


def _add_supercells(sub) -> None:
    sc = sub.add_parser(
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


def _add_coupling(sub) -> None:
    cp = sub.add_parser(
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


def _add_peds(sub) -> None:
    pe = sub.add_parser(
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


def _add_ladder(sub) -> None:
    ld = sub.add_parser(
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


def _add_patches(sub) -> None:
    pa = sub.add_parser(
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


def _add_active(sub) -> None:
    al = sub.add_parser(
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


def register(sub, groups: dict) -> None:
    """Add the supercell commands to the ``library`` group."""
    lsub = groups["library"]
    _add_supercells(lsub)
    _add_coupling(lsub)
    _add_peds(lsub)
    _add_ladder(lsub)
    _add_patches(lsub)
    _add_active(lsub)

"""The stages of ``metadesign run`` (see :data:`metadesign.studies.pipeline.STAGES`, which declares each
stage's inputs and so its key): each takes the run (:class:`~metadesign.studies.pipeline.Run`: the typed
recipe, the output folder, where each product lies, the report being written) and its content key, runs
its work through :meth:`Run.stage` (skipped when the key and its outputs are unchanged), and records its
line, checks, tables and figures."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
import numpy as np

from ..cards import model_card
from ..cliutil import progress_bar
from ..design.plot import plot_design
from ..design.recipe import load_design_recipe
from ..design.store import load_design, run_design
from ..layouts.make import make_layout
from ..layouts.preview import preview_layout
from ..layouts.rules import DESIGN_RULES
from ..library.build import build_library
from ..library.plot import plot_library
from ..library.rcwa import SolverSettings, solve_cell
from ..library.recipe import load_recipe
from ..library.store import load_library
from ..reconstruction.dataset import build_dataset, dataset_recipe_from_dict
from ..reconstruction.evaluate import evaluate_model, plot_fig3, summarise, write_results
from ..reconstruction.metrics import captured_fraction_ci
from ..reconstruction.train import load_train_recipe
from ..reconstruction.train import train as train_network
from ..sensing.model import load_sensing_recipe
from ..sensing.plot import plot_fab_study, plot_frames
from ..sensing.render import FabCases, fab_study, render_psf, save_psf
from ..sensing.sensor import quadrant_slices
from ..turbulence.scenario import load_scenario
from ..turbulence.system import build_system
from ..turbulence.validate import plot_validation, validate
from ..validation import ValidationError
from .beacons import LABELS, fresh_beacons
from .pipeline_check import check_cells

__all__ = ["library", "design", "layout", "sensing", "turbulence", "dataset", "train", "evaluate", "beacons",
           "CAPTURED_MARGIN", "BEACON_DESIGN", "BEACON_SEED", "BEACON_RYTOV"]

#: the folder of the run where the ``[beacons]`` device is designed (its ``design.npz`` is the device)
BEACON_DESIGN = "beacon-design"
#: the scintillated beacon of the sensing stage's figure: its screens' seed and nominal Rytov number
BEACON_SEED, BEACON_RYTOV = 1, 0.3


def library(run, key: str) -> None:
    """The committed table (or one built from its recipe), a few of its cells solved again, Fig. S1."""
    p, out = run.rec.pipeline, run.out
    if p.library_recipe is not None:
        run.stage("library", key, [run.lib_path], lambda: {
            "report": build_library(load_recipe(p.library_recipe), run.lib_path, workers=2)[1]["cells"],
            **_recheck(load_library(run.lib_path), p.library_recheck)})
    else:
        run.stage("library", key, [run.lib_path], lambda: {
            "file": str(run.lib_path), **_recheck(load_library(run.lib_path), p.library_recheck)})
    run.lib = load_library(run.lib_path)
    li = run.report["stages"]["library"]
    sm = run.lib.summary()
    line = (f"{sm['grid']['n_wx']}x{sm['grid']['n_wy']} cells, nG {sm['solver']['n_harmonics']}, convergence "
            f"{sm['convergence']['max_phase_change_rad']:.4f} rad, {100 * sm['fraction_above_threshold']:.1f} % "
            "cells with T0 >= 70 %")
    if li.get("recheck_max_abs_error") is not None:
        err = li["recheck_max_abs_error"]
        line += f", RCWA re-check {err:.1e}"
        run.check(f"library re-check: {len(li['recheck_cells'])} cells solved again with RCWA",
                  f"{err:.1e} (largest Jones-matrix difference)", "<= 1e-6", err <= 1e-6,
                  "the committed table against fresh solves with its own solver settings")
    li["summary"] = sm
    fig_s1 = out / "fig-s1.png"
    if not fig_s1.exists() or not run.report["stages"]["library"]["skipped"]:
        plot_library(run.lib, fig_s1)
    li["figures"] = [str(fig_s1)]
    run.say("library", line)
    run.section("1. Unit-cell library", None, [(
        "Fig. S1: unit-cell library", fig_s1,
        "Phase and transmission of every pillar for x and y polarisation: the 16 x 16 birefringent bins need "
        "pillars whose two phases cover 0-2 pi independently with high transmission.")])


def design(run, key: str) -> None:
    """The design (atoms per cell) on the pipeline's library, Fig. S2."""
    out = run.out
    dr = dataclasses.replace(load_design_recipe(run.rec.pipeline.design), library_path=run.lib_path)

    def do_design():
        d, _ = run_design(dr, run.ddir)
        plot_design(d, out / "fig-s2.png", run.lib)
        return {"metrics": {k: d.metrics[k] for k in ("rmse_rad", "peak_error_rad", "mean_T0", "n_atoms",
                                                      "n_empty_bins", "n_cells_in_aperture")},
                "n_cells": int(d.spec.n_cells), "figures": [str(out / "fig-s2.png")]}

    des = run.stage("design", key, [run.ddir / "design.npz", out / "fig-s2.png"], do_design)
    m = des["metrics"]
    run.say("design", f"{des.get('n_cells', 0)}x{des.get('n_cells', 0)} cells, {m['n_atoms']} atoms, RMSE x "
            f"{m['rmse_rad'][0]:.3f} y {m['rmse_rad'][1]:.3f} rad, peak {m['peak_error_rad'][0]:.3f}/"
            f"{m['peak_error_rad'][1]:.3f} rad, mean T0 {m['mean_T0'][0]:.3f}/{m['mean_T0'][1]:.3f}")
    run.check("design: every one of the 16 x 16 phase bins has an atom", f"{m['n_empty_bins']} empty bins",
              "0", m["n_empty_bins"] == 0 and m["n_atoms"] > 0,
              "a bin without an atom falls back to a neighbour's and adds its phase error")
    q = 2 * np.pi / 16 / np.sqrt(12)  # a uniform quantiser of 16 phase bins
    rmse = max(m["rmse_rad"])
    run.check("design phase error (RMSE, worse polarisation)", f"{rmse:.3f} rad", f"<= {1.1 * q:.3f} rad",
              rmse <= 1.1 * q, "16 x 16 binning: a uniform quantiser's error is (2 pi / 16) / sqrt(12) = "
              f"{q:.3f} rad; 10 % allowance for empty or uneven bins")
    rows = [{"quantity": "phase RMSE x / y", "value": f"{m['rmse_rad'][0]:.4f} / {m['rmse_rad'][1]:.4f} rad"},
            {"quantity": "peak phase error x / y", "value": f"{m['peak_error_rad'][0]:.3f} / "
                                                            f"{m['peak_error_rad'][1]:.3f} rad"},
            {"quantity": "mean transmission x / y", "value": f"{m['mean_T0'][0]:.3f} / {m['mean_T0'][1]:.3f}"},
            {"quantity": "atoms used", "value": f"{m['n_atoms']:,} ({m['n_empty_bins']} empty bins)"},
            {"quantity": "cells in the aperture", "value": f"{m['n_cells_in_aperture']:,}"}]
    run.section("2. Design", ("Design metrics", rows), [(
        "Fig. S2: design", out / "fig-s2.png",
        "(a) the atoms' phases, x- against y-polarisation (the 16 x 16 bins should be covered evenly); (b) the "
        "atoms' widths; (c, d) the discretised phase of one supercell lens (QI) per polarisation: smooth rings "
        "centred on the lens's offset; (e, f) the pillar widths across that lens; (g) how many cells use each "
        "atom. The phase error itself is in the table (RMSE against the 16-bin quantiser's).")])


def layout(run, key: str) -> None:
    """The OASIS layout, read back (gdstk, and KLayout when asked) and checked against the design rules."""
    out, lay = run.out, run.lay
    klayout = run.rec.pipeline.klayout

    def do_layout():
        made = make_layout(load_design(run.ddir), lay, klayout=klayout)
        preview_layout(made.contents, out / "layout-preview.png")
        at = made.drc["from_atom_table"]
        return {"pillars": made.write["pillars"], "bytes": made.write["bytes"], "exact": made.exact,
                "gdstk_exact": bool(made.verify["exact"]),
                "klayout_exact": None if made.verify_klayout is None else bool(made.verify_klayout["exact"]),
                "drc_passed": bool(made.drc["passed"]), "write_seconds": made.write["seconds"],
                "min_feature_nm": at["min_feature_nm"], "min_gap_nm": min(at["min_gap_x_nm"], at["min_gap_y_nm"]),
                "figures": [str(out / "layout-preview.png")]}

    li = run.stage("layout", key, [lay, out / "layout-preview.png"], do_layout)
    if not (li["exact"] and li["drc_passed"]):
        raise ValidationError(f"{lay}: the layout failed its read-back or design-rule check")
    k = li.get("klayout_exact")
    run.say("layout", f"{li['pillars']:,} pillars, {li['bytes'] / 1e3:.0f} kB OASIS in "
            f"{li.get('write_seconds', float('nan')):.2f} s; read-back exact {li.get('gdstk_exact', li['exact'])} "
            "(gdstk)" + ("" if k is None else f" / {k} (KLayout)") + f"; DRC {'pass' if li['drc_passed'] else 'FAIL'}"
            f" (min feature {li.get('min_feature_nm')} nm, min gap {li.get('min_gap_nm')} nm)")
    if k is not None:
        run.check("layout read-back through KLayout", "exact" if k else "differs", "every pillar as designed", k,
                  "an independent OASIS reader: the file a mask shop would open")
    run.check("layout read-back", "exact" if li["exact"] else "differs", "every pillar as designed", li["exact"],
              "the OASIS file read back pillar by pillar against the design")
    run.check(f"design rules ({DESIGN_RULES.label()})", "passed" if li["drc_passed"] else "violated",
              "no violation", li["drc_passed"])
    run.section("3. Layout", ("Layout", [
        {"quantity": "pillars", "value": f"{li['pillars']:,}"},
        {"quantity": "OASIS file", "value": f"{li['bytes'] / 1e6:.2f} MB"},
        {"quantity": "read-back", "value": "exact" if li["exact"] else "differs"},
        {"quantity": "design rules", "value": "passed" if li["drc_passed"] else "violated"}]), [(
        "Layout preview", out / "layout-preview.png",
        "16 x 16 cells at the centre of the written OASIS layout, read back from the file: every rectangle "
        "one pillar at its drawn width, as a mask shop would see it.")])


def sensing(run, key: str) -> None:
    """As-fabricated PSFs, the Table S1 focal check, a fab study and one scintillated beacon through
    the device."""
    out, p = run.out, run.rec.pipeline
    sr = load_sensing_recipe(p.sensor)
    cases = p.fab_cases
    figs = [out / "fig-2c.png", out / "fab-study.png", out / "psf-turbulent.png"]

    def do_sensing():
        system = build_system(run.lay, sr, p.turbulence)
        fab = system.device
        res = render_psf(fab, sr)
        save_psf(run.ddir / "psf.npz", res, fab, sr)
        plot_frames(res.frames, sr.sensor, figs[0], fab.channels, "as-fabricated sensor frames")
        rows = []
        for i, (label, b, j, seed) in enumerate(cases):
            for r in fab_study(fab, sr, FabCases((b,), (j,), seed=seed)):
                rows.append({**r, "case": i, "label": label})
        plot_fab_study(rows, figs[1])
        smp = system.chain().sample(seed=BEACON_SEED, rytov=BEACON_RYTOV)
        plot_frames(smp.frames, sr.sensor, figs[2], fab.channels,
                    f"one scintillated beacon (seed {BEACON_SEED}, nominal Rytov {BEACON_RYTOV:g}) through the "
                    "as-fabricated device")
        nominal = [r for r in rows if r["label"] == "nominal"]
        focal = [{"pol": r["pol"], "k": r["k"], "design_f_mm": r["design_focal_length_mm"],
                  "best_focus_mm": r["design_focal_length_mm"] + r["focal_shift_mm"], "strehl": r["strehl"]}
                 for r in nominal]
        study = [{"case": label, "bias_nm": b, "jitter_nm": j,
                  "mean_strehl": float(np.mean([r["strehl"] for r in rows if r["case"] == i])),
                  "mean_efficiency": float(np.mean([r["focusing_efficiency"] for r in rows if r["case"] == i]))}
                 for i, (label, b, j, _) in enumerate(cases)]
        return {"focal_check": focal, "fab_study": study, "channels": nominal,
                "beacon": {"seed": BEACON_SEED, "rytov": BEACON_RYTOV, **spot_changes(res.frames, smp.frames, sr.sensor)},
                "figures": [str(f) for f in figs]}

    ps = run.stage("sensing", key, figs, do_sensing)
    nom = ps["channels"]
    run.say("sensing", f"8 PSFs from the layout file: focusing efficiency "
            f"{100 * np.mean([r['focusing_efficiency'] for r in nom]):.2f} % per channel, Strehl "
            f"{min(r['strehl'] for r in nom):.3f}..{max(r['strehl'] for r in nom):.3f}, crosstalk "
            f"{100 * max(r['crosstalk'] for r in nom):.1f} %; fab study: Strehl "
            + ", ".join(f"{r['case']} {r['mean_strehl']:.3f}" for r in ps["fab_study"]))
    focal = [{"channel": f"{r['pol']}-pol {['QI', 'QII', 'QIII', 'QIV'][r['k'] - 1]}",
              "design f (mm)": f"{r['design_f_mm']:.4f}",
              "best focus - design (um)": f"{1e3 * (r['best_focus_mm'] - r['design_f_mm']):+.1f}",
              "Strehl": f"{r['strehl']:.3f}"} for r in ps["focal_check"]]
    worst = max(abs(r["best_focus_mm"] - r["design_f_mm"]) for r in ps["focal_check"])
    run.check("focal lengths (Table S1): worst best-focus shift", f"{1e3 * worst:.1f} um", "<= 100 um",
              worst <= 0.1, "through-focus peak of each of the 8 as-fabricated spots against its design focal "
              "length; the spots' depth of focus, +-2 lambda N^2 at f-number N ~ 20, is ~1 mm")
    strehl = min(r["strehl"] for r in ps["focal_check"])
    run.check("as-fabricated Strehl ratio, worst spot", f"{strehl:.3f}", ">= 0.8", strehl >= 0.8,
              "Marechal's criterion: a diffraction-limited spot")
    study = [{"device": r["case"], "mean Strehl": f"{r['mean_strehl']:.3f}",
              "mean focusing efficiency (%)": f"{100 * r['mean_efficiency']:.2f}"} for r in ps["fab_study"]]
    run.section("4. As-fabricated sensor", ("Table S1 focal check (through-focus peak)", focal),
                raw=ps["focal_check"], figures=[(
        "Fig. 2c: sensor frames", figs[0],
        "The 8 spots on the sensor (2 polarisations x 4 quadrants), each with its own defocus: all 8 should be "
        "compact and centred in their quadrant."), (
        "A scintillated beacon", figs[2], beacon_caption(ps.get("beacon")))])
    run.section("4. As-fabricated sensor", ("Fab study", study), raw=ps["fab_study"], figures=[(
        "Fab study", figs[1],
        "Per spot (8 markers per device, x-pol filled, y-pol open) and per fabrication case: focusing "
        "efficiency, Strehl ratio at best focus, best-focus shift from the design focal length, and crosstalk "
        "into the other quadrants: how much a fab process may drift before the spots degrade.")])


def spot_changes(frames, beacon_frames, sensor) -> dict:
    """How one beacon's frames differ from the device's own: per quadrant (x-pol QI..QIV, y-pol QI..QIV) the
    peak over its frame's brightest, with and without the turbulence, and how far the spot's intensity
    centroid moved on the camera (um)."""
    def spots(fr):
        peaks, cents = [], []
        for f in np.asarray(fr, np.float64):
            top = max(float(f.max()), 1e-30)
            for k in range(1, 5):
                r, c = quadrant_slices(sensor, k)
                q = f[r, c]
                w = max(float(q.sum()), 1e-30)
                y, x = np.indices(q.shape)
                peaks.append(float(q.max()) / top)
                cents.append((float((q * y).sum()) / w, float((q * x).sum()) / w))
        return peaks, np.array(cents)

    p0, c0 = spots(frames)
    p1, c1 = spots(beacon_frames)
    moved = np.hypot(*(c1 - c0).T) * sensor.pixel_pitch * 1e6
    return {"peaks": p1, "peaks_without": p0, "moved_um": [float(v) for v in moved]}


def beacon_caption(b: dict | None) -> str:
    """The scintillated-beacon figure's caption, from what its frames show (:func:`spot_changes`)."""
    if not b or "moved_um" not in b:  # a run folder made before the figure was measured
        return ("One scintillated beacon through the turbulence onto the same sensor, each quadrant on its own "
                "scale: the 8 spots move and change brightness, each differently; those differences are what "
                "the reconstruction reads.")
    mv = b["moved_um"]
    return (f"One beacon (screens' seed {b['seed']}, nominal Rytov {b['rytov']:g}) through the turbulence onto the "
            "same sensor, each quadrant on its own scale (compare Fig. 2c): the turbulence tilts and scintillates "
            f"the received wave, so the spots move off their places ({min(mv):.0f}-{max(mv):.0f} um on the camera) "
            f"and their peaks spread to {min(b['peaks']):.2f}-1.00 of their frame's brightest (without turbulence "
            f"{min(b['peaks_without']):.2f}-1.00), each spot differently since each has its own defocus: those "
            "differences are what the reconstruction reads.")


def turbulence(run, key: str) -> None:
    """The scenario's screens validated against theory (Figs. S5, S6)."""
    p, out = run.rec.pipeline, run.out
    sc = load_scenario(p.turbulence)

    def do_turb():
        res = validate(sc, (0.1, 0.3, 0.5), samples=p.turbulence_samples, pib_samples=5)
        figs = plot_validation(res, out)
        return {"figures": [str(f) for f in figs],
                "levels": [{"rytov_nominal": x["rytov_nominal"], "rytov_measured": x["rytov_measured"],
                            "rytov_theory": x["rytov_weak_theory_inner_scale"], "D_over_r0": x["D_over_r0"],
                            "npib_mean": {m: float(np.mean(x["npib"][m])) for m in ("complex", "phase", "none")}}
                           for x in res["levels"]],
                "structure_function_ratio": [float(r) for r in res["structure_function"]["ratio"]]}

    figs = [out / Path(f).name for f in run.previous("turbulence").get("figures", [])]
    tu = run.stage("turbulence", key, figs or [out / "__none__"], do_turb)
    sf, top = tu.get("structure_function_ratio") or [float("nan")], tu["levels"][-1]
    run.say("turbulence", f"structure function / theory {min(sf):.3f}..{max(sf):.3f}; Rytov nominal -> measured "
            f"({p.turbulence_samples} samples) " + ", ".join(f"{x['rytov_nominal']:g} -> {x['rytov_measured']:.3f}"
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
    run.check("turbulence: measured log-amplitude variance against theory",
              f"worst level (Rytov {w['rytov_nominal']:g}): {w['rytov_measured']:.3f} vs {ref(w):.3f} "
              f"({100 * (w['rytov_measured'] / ref(w) - 1):+.0f} %)", "within 25 %", dev <= 0.25,
              f"{p.turbulence_samples} beacons per level against weak-fluctuation theory with the inner "
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
    run.section("5. Turbulence", ("Turbulence: Rytov nominal vs measured", rows), raw=tu["levels"], figures=[
        (next((c.split(":")[0] for k, c in captions.items() if k in Path(f).stem), Path(f).stem), Path(f),
         next((c for k, c in captions.items() if k in Path(f).stem), "")) for f in tu["figures"]])


def dataset(run, key: str) -> None:
    """The dataset (PSF tensors and received fields) through the pipeline's layout, sensor and turbulence."""
    p, d = run.rec.pipeline, run.rec.dataset
    ds_raw = d.document(run.lay, p.sensor, p.turbulence)
    ds = run.stage("dataset", key, [run.dsdir / "zarr.json"], lambda: {
        k: v for k, v in build_dataset(dataset_recipe_from_dict(ds_raw, "dataset"), run.dsdir, workers=d.workers,
                                       overwrite=True, progress=progress_bar("dataset", "sample")).items()
        if k in ("samples", "bytes_per_sample", "split_counts")})
    sc = ds.get("split_counts") or {}
    run.say("dataset", f"{ds.get('samples', 0):,} samples (train / val / test "
            + " / ".join(f"{sc.get(k, 0):,}" for k in ("train", "val", "test"))
            + f"), {ds.get('bytes_per_sample', 0) / 1e3:.1f} kB each")
    run.section("6. Reconstruction", ("Dataset", [
        {"quantity": "samples", "value": f"{ds.get('samples', 0):,}"},
        {"quantity": "train / val / test", "value": " / ".join(f"{sc.get(k, 0):,}" for k in ("train", "val", "test"))},
        {"quantity": "storage per sample", "value": f"{ds.get('bytes_per_sample', 0) / 1e3:.1f} kB"}]))


def train(run, key: str) -> None:
    """Training on the dataset (or the given model)."""
    t = run.rec.train
    if t.model is not None:
        run.stage("train", key, [run.model], lambda: {"model": str(run.model)})
        run.say("train", f"the given model {run.model}")
        return
    folder = run.model.parent

    def do_train():
        shutil.rmtree(folder, ignore_errors=True)  # the pipeline's own run folder
        r = train_network(load_train_recipe(t.recipe), folder, dataset=run.dsdir, log=run.log, progress=True)
        return {"epochs": r["epochs_done"], "best_val_npib": r["best_val_npib"]}

    tr = run.stage("train", key, [run.model], do_train)
    run.say("train", f"{tr.get('epochs')} epochs, best validation NPiB {tr.get('best_val_npib', float('nan')):.3f}")
    if (folder / "curves.png").exists():
        run.section("6. Reconstruction", None, [(
            "Training curves", folder / "curves.png",
            "Loss and validation NPiB per epoch: validation should rise and level off, not fall (over-fitting).")])


def evaluate(run, key: str) -> None:
    """The model on the dataset's split at each noise level (Figs. 3b-d), against the model card's figure."""
    ev_dir = run.out / "evaluation"
    ev_opts = run.rec.evaluate

    def do_eval():
        ev_dir.mkdir(exist_ok=True)
        # noise levels stay in percent of the peak (config: "percent" is not rescaled)
        res = evaluate_model(run.model, run.dsdir, ev_opts.split, list(ev_opts.noise_percent),
                             progress=progress_bar("evaluate", "sample"))
        write_results(res, ev_dir)
        figs = plot_fig3(res, ev_dir)
        summary = {k: summarise(res["rows"][k]) for k in res["rows"]}
        for k, r in res["rows"].items():  # how well the test set pins the captured fraction down
            summary[k]["captured_fraction_ci95"] = list(captured_fraction_ci(r["none"], r["unet"],
                                                                             r["phase_conjugate"]))
        return {"figures": [str(f) for f in figs], "summary": summary}

    figs = [ev_dir / Path(f).name for f in run.previous("evaluate").get("figures", [])]
    ev = run.stage("evaluate", key, figs or [ev_dir / "__none__"], do_eval)
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
    run.report["headline"] = {"estimator": est, "rows": rows, "n": ev.get("n")}
    run.say("evaluate", f"{est}, mean NPiB at " + " / ".join(f"{r['noise_percent']:g}" for r in summary)
            + " % noise: " + " / ".join(f"{r['npib_unet']:.3f}" for r in summary) + " (captured "
            + " / ".join(f"{r['captured_fraction']:.2f}" for r in summary) + f"); uncorrected "
            f"{summary[0]['npib_none']:.3f}, phase conjugate {summary[0]['npib_phase_conjugate']:.3f}")
    card_cf = _validated_captured_fraction(run.model)
    for k in levels:
        v = ev["summary"][k]
        lo, hi = v.get("captured_fraction_ci95", [float("nan")] * 2)
        if card_cf is not None:
            run.check(f"reconstruction at {_noise_value(k):g} % noise: captured fraction against the model card's",
                      f"{v['captured_fraction']:.2f} (95 % interval {lo:.2f}..{hi:.2f}, n {v['n']})",
                      f">= {card_cf - CAPTURED_MARGIN:.2f} (card's validation {card_cf:.2f} - "
                      f"{CAPTURED_MARGIN:g})", hi >= card_cf - CAPTURED_MARGIN,
                      "the model must do on this device and turbulence what its card says it did on its "
                      "validation set: the interval's upper end within the margin of the card's figure")
    for r in summary:
        run.check(f"reconstruction at {r['noise_percent']:g} % noise: {est} beats uncorrected",
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
    run.section("6. Reconstruction", ("NPiB summary", rows), raw=summary, figures=[
        (next((c.split(":")[0] for k, c in captions.items() if k in Path(f).stem), Path(f).stem), Path(f),
         next((c for k, c in captions.items() if k in Path(f).stem), "")) for f in ev["figures"]])


def beacons(run, key: str) -> None:
    """Fresh beacons through a second device (the ``[beacons]`` section) estimated by a given model:
    no dataset (:func:`metadesign.studies.beacons.fresh_beacons`)."""
    b, out = run.rec.beacons, run.out
    fig = out / "fig-3b-beacons.png"
    info = run.stage("beacons", key, [fig], lambda: fresh_beacons(
        b, run.rec.pipeline.turbulence, out / BEACON_DESIGN, fig, library=run.lib_path))
    run.say("beacons", info["line"])
    m, cap = info["npib"], info["captured_fraction"]
    rows = []
    for lv in info["noise_percent"]:
        for k in info["methods"]:
            rows.append({"sensor noise (% of peak)": f"{lv:g}", "estimator": LABELS[k],
                         "NPiB": f"{m[f'{k}@{lv:g}']:.3f}", "NPiB uncorrected": f"{m['none']:.3f}",
                         "NPiB phase conjugate": f"{m['phase_conjugate']:.3f}",
                         "captured fraction": f"{cap[f'{k}@{lv:g}']:.2f}"})
            run.check(f"fresh beacons at {lv:g} % noise: {LABELS[k]} beats uncorrected",
                      f"NPiB {m[f'{k}@{lv:g}']:.3f} vs {m['none']:.3f} (captured {cap[f'{k}@{lv:g}']:.2f})",
                      "NPiB above the uncorrected beam's", m[f"{k}@{lv:g}"] > m["none"],
                      f"{b.samples} beacons through {b.design.stem} never seen in training (root seed "
                      f"{b.seed})")
    if not run.report["headline"]:
        run.report["headline"] = {"estimator": LABELS[info["methods"][-1]], "rows": rows, "n": b.samples}
    run.section("6. Reconstruction: fresh beacons", ("Fresh beacons", rows), raw={"npib": m, "captured_fraction": cap},
                figures=[("Fig. 3b: fresh beacons", fig,
                           "NPiB of each beacon against its measured Rytov number, at the highest noise level: "
                           "the estimator should sit close under the phase conjugate and far above the "
                           "uncorrected beam.")])


def _recheck(lib, cells) -> dict:
    """The library's Jones matrices at ``cells`` ((i, j) indices) against fresh RCWA solves with the
    table's own stack and truncation: the largest absolute difference (nothing when no cell is given)."""
    if not cells:
        return {}
    stack = lib.stack
    settings = SolverSettings(lib.meta["solver"]["n_harmonics_requested"])
    check_cells((len(lib.wx), len(lib.wy)), cells)
    err = max(float(np.abs(solve_cell(lib.wx[i], lib.wy[j], stack, settings).jones - lib.jones[i, j]).max())
              for i, j in cells)
    return {"recheck_max_abs_error": err, "recheck_cells": [list(c) for c in cells]}


def _noise_value(key: str) -> float:
    """The level of an evaluation key ("gaussian:5" -> 5.0; photon levels after every Gaussian one)."""
    kind, _, v = str(key).partition(":")
    return float(v) + (0 if kind == "gaussian" else 1e6)


#: how far below its card's validated captured fraction a model may score on the pipeline's test set
CAPTURED_MARGIN = 0.10


def _validated_captured_fraction(model) -> float | None:
    """The captured fraction on the validation set recorded in a model's card (None: not recorded)."""
    try:
        card = model_card(model)  # sha256 checked: a replaced model has no validated fraction
    except (ValidationError, TypeError):
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

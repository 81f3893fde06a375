"""``metadesign demo``: the embedded demo through every stage (library to reconstruction).

Each stage returns a dict with ``line`` (one summary line), ``figures`` and
its numbers; the demo writes ``summary.json`` and the figures to one folder.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

from ..design.plot import plot_design
from ..design.recipe import load_design_recipe
from ..design.store import load_design, run_design
from ..io import atomic_write_text
from ..layouts.make import make_layout
from ..layouts.preview import preview_layout
from ..library.plot import plot_library
from ..library.rcwa import SolverSettings, Stack, solve_cell
from ..library.store import load_library
from ..paths import default_library_path, repo_root
from ..plotting import pyplot, save_figure
from ..reconstruction.data import apply_noise
from ..reconstruction.dataset import normalise_psf, received_crop, sample_rytov
from ..reconstruction.losses import PiB
from ..reconstruction.metrics import captured_fraction, gain, npib_rows
from ..reconstruction.model import load_model
from ..reconstruction.refine import load_refiner
from ..sensing.model import AsFabricated
from ..sensing.plot import plot_fab_study, plot_frames
from ..sensing.render import fab_study, render_psf, save_psf
from ..turbulence.system import build_system
from ..turbulence.scenario import load_scenario
from ..turbulence.validate import plot_validation, validate
from ..validation import ValidationError

__all__ = ["run_demo"]


def _stage_library(out: Path) -> dict:
    lib = load_library(default_library_path())
    s = lib.summary()
    fig = plot_library(lib, out / "library-fig-s1.png")
    # spot-check the committed table with fresh RCWA solves
    st = lib.meta["stack"]
    stack = Stack(st["wavelength_m"], st["period_m"], st["height_m"], st["n_pillar"], st["n_substrate"],
                  st["n_superstrate"])
    settings = SolverSettings(lib.meta["solver"]["n_harmonics_requested"])
    idx = [(40, 20), (8, 72), (60, 60)]
    err = max(float(np.abs(solve_cell(lib.wx[i], lib.wy[j], stack, settings).jones - lib.jones[i, j]).max())
              for i, j in idx)
    line = (f"{s['grid']['n_wx']}x{s['grid']['n_wy']} cells, nG {s['solver']['n_harmonics']}, convergence "
            f"{s['convergence']['max_phase_change_rad']:.4f} rad, {100 * s['fraction_above_threshold']:.1f} % "
            f"cells with T0 >= 70 %, RCWA re-check {err:.1e}")
    return {"line": line, "summary": s, "recheck_max_abs_error": err, "figures": [str(fig)]}


def _stage_design(out: Path) -> dict:
    recipe = load_design_recipe(repo_root() / "layouts" / "demo.toml")
    d, path = run_design(recipe, out / "design")
    fig = plot_design(d, out / "design-fig-s2.png", load_library(recipe.library_path))
    if not (d.metrics["n_empty_bins"] == 0 and d.metrics["n_atoms"] > 0):
        raise RuntimeError("demo design: the library does not cover every phase bin")
    m = d.metrics
    line = (f"{d.spec.n_cells}x{d.spec.n_cells} cells, {m['n_atoms']} atoms, RMSE x {m['rmse_rad'][0]:.3f} "
            f"y {m['rmse_rad'][1]:.3f} rad, peak {m['peak_error_rad'][0]:.3f}/{m['peak_error_rad'][1]:.3f} rad, "
            f"mean T0 {m['mean_T0'][0]:.3f}/{m['mean_T0'][1]:.3f}")
    return {"line": line, "metrics": m, "path": str(path), "figures": [str(fig)]}


def _stage_layout(out: Path) -> dict:
    d = load_design(out / "design")
    made = make_layout(d, out / "design" / "layout.oas", klayout=True)
    rep, v, k, drc = made.write, made.verify, made.verify_klayout, made.drc
    fig = preview_layout(made.contents, out / "layout-preview.png")
    line = (f"{rep['pillars']:,} pillars, {rep['bytes'] / 1e3:.0f} kB OASIS in {rep['seconds']:.2f} s; read-back exact "
            f"{v['exact']} (gdstk) / {k['exact']} (KLayout); DRC {'pass' if drc['passed'] else 'FAIL'} (min feature "
            f"{drc['from_atom_table']['min_feature_nm']} nm, min gap {min(drc['from_atom_table']['min_gap_x_nm'], drc['from_atom_table']['min_gap_y_nm'])} nm)")
    return {"line": line, "write": rep, "verify_gdstk": v, "verify_klayout": k, "drc": drc, "figures": [str(fig)],
            "passed": made.passed}


def _stage_sensing(out: Path) -> dict:
    system = build_system(out / "design" / "layout.oas", repo_root() / "sensing" / "demo.toml")
    fab, sr = system.device, system.sensing
    res = render_psf(fab, sr)
    save_psf(out / "design" / "psf.npz", res, fab, sr)
    figs = [plot_frames(res.frames, sr.sensor, out / "psf-fig-2c.png", fab.channels,
                        "demo layout: as-fabricated sensor frames (flat wavefront)")]
    rows = fab_study(fab, sr, [0.0], [0.0], [0.0]) + fab_study(fab, sr, [-10.0, 10.0], [0.0], [0.0]) \
        + fab_study(fab, sr, [0.0], [5.0], [0.0], seed=1)
    names = ["nominal", "bias -10 nm", "bias +10 nm", "jitter 5 nm"]
    for i, r in enumerate(rows):
        r["case"] = i // 8
        r["label"] = names[i // 8]
    figs.append(plot_fab_study(rows, out / "fab-study.png"))
    nom = [r for r in rows if r["case"] == 0]
    line = (f"8 PSFs from the layout file: focusing efficiency {np.mean([r['focusing_efficiency'] for r in nom]):.3f} "
            f"per channel, Strehl {min(r['strehl'] for r in nom):.3f}..{max(r['strehl'] for r in nom):.3f}, "
            f"crosstalk {max(r['crosstalk'] for r in nom):.3f}; fab study: Strehl "
            + ", ".join(f"{lab} {np.mean([r['strehl'] for r in rows if r['label'] == lab]):.3f}" for lab in names))
    return {"line": line, "channels": nom, "fab_study": rows, "figures": [str(f) for f in figs]}


def _stage_turbulence(out: Path) -> dict:
    sc = load_scenario(repo_root() / "sensing" / "turbulence.toml")
    res = validate(sc, rytovs=(0.1, 0.3, 0.5), samples=10, pib_samples=5)
    figs = plot_validation(res, out)
    # one scintillated beacon through the demo metasurface onto the sensor (the stage API's chain)
    chain = build_system(out / "design" / "layout.oas", repo_root() / "sensing" / "demo.toml", sc).chain()
    smp = chain.sample(seed=1, rytov=0.3)
    figs.append(plot_frames(smp.frames, chain.sensing.sensor, out / "psf-turbulent.png", chain.fab.channels,
                            "demo metasurface, scintillated beacon at Rytov 0.3"))
    lv = res["levels"]
    sf = res["structure_function"]["ratio"]
    line = (f"structure function / theory {min(sf):.3f}..{max(sf):.3f}; Rytov nominal -> measured (10 samples) "
            + ", ".join(f"{x['rytov_nominal']:g} -> {x['rytov_measured']:.3f}" for x in lv)
            + "; NPiB complex/phase/none at 0.5: "
            + "/".join(f"{np.mean(lv[-1]['npib'][m]):.2f}" for m in ("complex", "phase", "none")))
    return {"line": line, "structure_function": res["structure_function"],
            "levels": [{k: v for k, v in x.items() if k in ("rytov_nominal", "rytov_measured", "D_over_r0")}
                       for x in lv], "figures": [str(f) for f in figs]}


DEMO_MODEL = "sensing/models/demo-unet-robust.safetensors"
DEMO_REFINER = "sensing/models/demo-refine.safetensors"  # names DEMO_MODEL as its U-Net
DEMO_NOISE = (0.0, 5.0)  # % of each channel's peak: a clean camera and the paper's training noise


def _stage_reconstruction(out: Path, n_samples: int = 32) -> dict:
    """The committed robust demo U-Net and its learned refinement on freshly drawn beacons through the
    paper design (not their training samples: another root seed), at 0 % and 5 % sensor noise, against
    no correction and the phase and complex conjugates."""
    import torch

    model, card = load_model(repo_root() / DEMO_MODEL)
    refiner = None
    if (repo_root() / DEMO_REFINER).exists():
        refiner, rcard = load_refiner(repo_root() / DEMO_REFINER)
        if rcard["unet"]["weights_sha256"] != card["weights_sha256"]:
            raise ValidationError(f"{DEMO_REFINER}: refines another U-Net than {DEMO_MODEL}")
    d, _ = run_design(load_design_recipe(repo_root() / "layouts" / "paper-5mm.toml"), out / "paper-design")
    chain = build_system(AsFabricated.from_design(d), repo_root() / "sensing" / "paper.toml",
                         repo_root() / "sensing" / "turbulence.toml", tensor_size=model.config.input_size).chain()
    c0, a = received_crop(chain.turbulence.sc)
    pib = PiB(chain.turbulence.sc, c0, a)
    root = 2026  # fresh samples: the demo dataset was drawn from root seed 0
    methods = ("unet", "refine") if refiner is not None else ("unet",)
    rows: dict = {k: [] for k in ("rytov", "none", "phase_conjugate", "complex_conjugate")}
    rows |= {f"{m}@{lv:g}": [] for m in methods for lv in DEMO_NOISE}
    with torch.no_grad():
        for i in range(n_samples):
            r = sample_rytov(root, i, (0.25, 0.6), None)
            seed = 10_000 + i
            s = chain.sample(seed, r)
            tb = chain.at(r)
            scr = torch.from_numpy(tb.screens(seed))[None]
            rec = torch.from_numpy(s.received[c0:c0 + a, c0:c0 + a])[None]
            psf, _ = normalise_psf(s.tensor)
            rows["rytov"].append(float(np.var(np.log(np.maximum(np.abs(rec[0][pib.ap.bool()].numpy()), 1e-30)))))
            ref = npib_rows(pib, torch.zeros(rec.shape), scr, rec, complex_conjugate=True)
            for k in ("none", "phase_conjugate", "complex_conjugate"):
                rows[k].append(float(ref[k]))
            for lv in DEMO_NOISE:
                rng = np.random.default_rng(np.random.SeedSequence(root, spawn_key=(i, int(10 * lv))))
                x = torch.from_numpy(apply_noise(psf, rng, lv) if lv else psf)[None]
                phi = model(x)
                rows[f"unet@{lv:g}"].append(float(pib.npib_phase(phi, scr)))
                if refiner is not None:
                    rows[f"refine@{lv:g}"].append(float(pib.npib_phase(refiner.trajectory(x, start=phi)[-1]
                                                                       * refiner.mask, scr)))
    m = {k: float(np.mean(v)) for k, v in rows.items()}
    cap = {k: captured_fraction(rows["none"], rows[k], rows["phase_conjugate"])
           for k in rows if "@" in k}
    best = f"{methods[-1]}@{DEMO_NOISE[-1]:g}"
    g = gain(rows["none"], rows[best])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.8), constrained_layout=True)
    lab = {"unet": "U-Net (robust demo model)", "refine": "U-Net + learned refinement"}
    series = [("complex_conjugate", "complex conjugate (oracle)", "^", "tab:olive"),
              ("phase_conjugate", "phase conjugate (oracle)", "s", "tab:green")]
    series += [(f"{k}@{DEMO_NOISE[-1]:g}", f"{lab[k]}, {DEMO_NOISE[-1]:g} % noise", "o" if k == "unet" else "P",
                "tab:blue" if k == "unet" else "tab:cyan") for k in methods]
    series += [("none", "uncorrected", "x", "k")]
    for k, name, mk, col in series:
        ax.scatter(rows["rytov"], rows[k], s=16, marker=mk, color=col, alpha=0.75, label=f"{name}: mean {m[k]:.3f}")
    ax.set(xlabel="Rytov number of the sample (measured)", ylabel="normalised power in bucket",
           title=f"Fig. 3b (demo): {n_samples} fresh beacons through the paper design")
    ax.legend(fontsize=8)
    fig_path = save_figure(fig, out / "fig-3b-demo.png")
    per = "; ".join(f"{lab[k].split(' (')[0]} {m[f'{k}@0']:.3f} / {m[f'{k}@5']:.3f} (captured "
                    f"{cap[f'{k}@0']:.2f} / {cap[f'{k}@5']:.2f})" for k in methods)
    line = (f"{n_samples} fresh beacons through the paper design, mean NPiB at 0 % / 5 % noise: {per}; "
            f"uncorrected {m['none']:.3f}, phase conjugate {m['phase_conjugate']:.3f}, complex conjugate "
            f"{m['complex_conjugate']:.3f}; gain median {np.median(g):.1f}x")
    return {"line": line, "npib": m, "captured_fraction": cap, "gain_median": float(np.median(g)),
            "noise_percent": list(DEMO_NOISE), "model_card": card.get("metrics"),
            "figures": [str(fig_path)], "passed": all(m[k] > m["none"] for k in cap)}


STAGES = (("library", _stage_library), ("design", _stage_design), ("layout", _stage_layout),
          ("sensing", _stage_sensing), ("turbulence", _stage_turbulence), ("reconstruction", _stage_reconstruction))


def run_demo(out: Path, log: Callable[[str], None] = print) -> dict:
    """Every stage on the embedded designs into ``out``; ``log`` gets the summary's lines as they come (the
    header, each stage's line when it completes, then figures, time and checks), each once."""
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result: dict = {"output": str(out), "stages": {}}
    lines = [f"metadesign demo -> {out}/"]
    log(lines[0])
    for name, fn in STAGES:
        if name == "reconstruction" and not (repo_root() / DEMO_MODEL).exists():
            lines.append(f"  {len(lines)}. {name:<9} skipped (no committed demo model at {DEMO_MODEL})")
            log(lines[-1])
            continue
        result["stages"][name] = st = fn(out)
        lines.append(f"  {len(lines)}. {name:<9} {st['line']}")
        log(lines[-1])
    result["seconds"] = time.perf_counter() - t0
    result["passed"] = all(st.get("passed", True) for st in result["stages"].values())
    figs = [Path(f).name for st in result["stages"].values() for f in st["figures"]]
    tail = [f"  figures      {', '.join(figs)}", f"  time         {result['seconds']:.1f} s",
            f"  checks       {'all passed' if result['passed'] else 'FAILED (see summary.json)'}"]
    for t in tail:
        log(t)
    result["text"] = "\n".join(lines + tail)
    atomic_write_text(out / "summary.json", json.dumps({k: v for k, v in result.items() if k != "text"},
                                                      indent=2, sort_keys=True, default=float))
    return result

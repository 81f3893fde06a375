"""``metadesign demo``: the embedded demo through every stage built so far.

Each stage returns a dict with ``line`` (one summary line), ``figures`` and
its numbers; the demo writes ``summary.json`` and the figures to one folder.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .io import atomic_write_text
from .paths import default_library_path, repo_root

__all__ = ["run_demo"]


def _stage_library(out: Path, log) -> dict:
    from .library.plot import plot_library
    from .library.rcwa import SolverSettings, Stack, solve_cell
    from .library.store import load_library

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
    log(f"library: {line}")
    return {"line": line, "summary": s, "recheck_max_abs_error": err, "figures": [str(fig)]}


def _stage_design(out: Path, log) -> dict:
    from .design.plot import plot_design
    from .design.recipe import load_design_recipe
    from .design.store import run_design
    from .library.store import load_library

    recipe = load_design_recipe(repo_root() / "layouts" / "demo.toml")
    d, path = run_design(recipe, out / "design")
    fig = plot_design(d, out / "design-fig-s2.png", load_library(recipe.library_path))
    if not (d.metrics["n_empty_bins"] == 0 and d.metrics["n_atoms"] > 0):
        raise RuntimeError("demo design: the library does not cover every phase bin")
    m = d.metrics
    line = (f"{d.spec.n_cells}x{d.spec.n_cells} cells, {m['n_atoms']} atoms, RMSE x {m['rmse_rad'][0]:.3f} "
            f"y {m['rmse_rad'][1]:.3f} rad, peak {m['peak_error_rad'][0]:.3f}/{m['peak_error_rad'][1]:.3f} rad, "
            f"mean T0 {m['mean_T0'][0]:.3f}/{m['mean_T0'][1]:.3f}")
    log(f"design: {line}")
    return {"line": line, "metrics": m, "path": str(path), "figures": [str(fig)]}


def _stage_layout(out: Path, log) -> dict:
    from .design.store import load_design
    from .layouts import drc_check, read_layout, read_layout_klayout, verify_against_design, write_layout
    from .layouts.preview import preview_layout

    d = load_design(out / "design")
    rep = write_layout(d, out / "design" / "layout.oas", "oas")
    lc = read_layout(out / "design" / "layout.oas")
    v = verify_against_design(lc, d)
    k = verify_against_design(read_layout_klayout(out / "design" / "layout.oas"), d)
    drc = drc_check(lc, 100, 150)
    fig = preview_layout(lc, out / "layout-preview.png")
    line = (f"{rep['pillars']:,} pillars, {rep['bytes'] / 1e3:.0f} kB OASIS in {rep['seconds']:.2f} s; read-back exact "
            f"{v['exact']} (gdstk) / {k['exact']} (KLayout); DRC {'pass' if drc['passed'] else 'FAIL'} (min feature "
            f"{drc['from_atom_table']['min_feature_nm']} nm, min gap {min(drc['from_atom_table']['min_gap_x_nm'], drc['from_atom_table']['min_gap_y_nm'])} nm)")
    log(f"layout: {line}")
    return {"line": line, "write": rep, "verify_gdstk": v, "verify_klayout": k, "drc": drc, "figures": [str(fig)],
            "passed": bool(v["exact"] and k["exact"] and drc["passed"])}


def _stage_sensing(out: Path, log) -> dict:
    from .sensing.model import AsFabricated, load_sensing_recipe
    from .sensing.plot import plot_fab_study, plot_frames
    from .sensing.render import fab_study, render_psf, save_psf

    fab = AsFabricated.from_files(out / "design" / "layout.oas")
    sr = load_sensing_recipe(repo_root() / "sensing" / "demo.toml")
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
    log(f"sensing: {line}")
    return {"line": line, "channels": nom, "fab_study": rows, "figures": [str(f) for f in figs]}


def _stage_turbulence(out: Path, log) -> dict:
    from .sensing.chain import BeaconChain
    from .sensing.model import AsFabricated, load_sensing_recipe
    from .sensing.plot import plot_frames
    from .turbulence.validate import load_scenario, plot_validation, validate

    sc = load_scenario(repo_root() / "sensing" / "turbulence.toml")
    res = validate(sc, rytovs=(0.1, 0.3, 0.5), samples=10, pib_samples=5)
    figs = plot_validation(res, out)
    # one scintillated beacon through the demo metasurface onto the sensor (the stage API's chain)
    chain = BeaconChain.for_device(AsFabricated.from_files(out / "design" / "layout.oas"),
                                   load_sensing_recipe(repo_root() / "sensing" / "demo.toml"), sc)
    smp = chain.sample(seed=1, rytov=0.3)
    figs.append(plot_frames(smp.frames, chain.sensing.sensor, out / "psf-turbulent.png", chain.fab.channels,
                            "demo metasurface, scintillated beacon at Rytov 0.3"))
    lv = res["levels"]
    sf = res["structure_function"]["ratio"]
    line = (f"structure function / theory {min(sf):.3f}..{max(sf):.3f}; Rytov nominal -> measured (10 samples) "
            + ", ".join(f"{x['rytov_nominal']:g} -> {x['rytov_measured']:.3f}" for x in lv)
            + "; NPiB complex/phase/none at 0.5: "
            + "/".join(f"{np.mean(lv[-1]['npib'][m]):.2f}" for m in ("complex", "phase", "none")))
    log(f"turbulence: {line}")
    return {"line": line, "structure_function": res["structure_function"],
            "levels": [{k: v for k, v in x.items() if k in ("rytov_nominal", "rytov_measured", "D_over_r0")}
                       for x in lv], "figures": [str(f) for f in figs]}


STAGES = (("library", _stage_library), ("design", _stage_design), ("layout", _stage_layout),
          ("sensing", _stage_sensing), ("turbulence", _stage_turbulence))


def run_demo(out: Path, log: Callable[[str], None] = print) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result: dict = {"output": str(out), "stages": {}}
    for name, fn in STAGES:
        result["stages"][name] = fn(out, log)
    result["seconds"] = time.perf_counter() - t0
    result["passed"] = all(st.get("passed", True) for st in result["stages"].values())
    figs = [Path(f).name for st in result["stages"].values() for f in st["figures"]]
    lines = [f"metadesign demo -> {out}/"]
    lines += [f"  {i}. {name:<9} {st['line']}" for i, (name, st) in enumerate(result["stages"].items(), 1)]
    lines += [f"  figures      {', '.join(figs)}", f"  time         {result['seconds']:.1f} s",
              f"  checks       {'all passed' if result['passed'] else 'FAILED (see summary.json)'}"]
    result["text"] = "\n".join(lines)
    atomic_write_text(out / "summary.json", json.dumps({k: v for k, v in result.items() if k != "text"},
                                                      indent=2, sort_keys=True, default=float))
    return result

"""The ``metadesign`` command line.

Every subcommand validates its inputs first; a bad input prints one line
``metadesign: error: ...`` and exits with status 2 without writing anything.
"""

from __future__ import annotations

import os

# Single-threaded BLAS/OpenMP unless the user asked otherwise: the machines
# this runs on are small and shared, and we parallelise with processes.
for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_k, "1")

import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from . import __version__  # noqa: E402
from .config import InputError  # noqa: E402
from .paths import default_library_path  # noqa: E402

__all__ = ["main"]


def _progress_bar(desc: str, unit: str = "cell"):
    """A tqdm-backed progress callback ``(done, total)``; silent off a terminal."""
    from tqdm import tqdm

    state: dict = {}

    def cb(done: int, total: int) -> None:
        bar = state.get("bar")
        if bar is None:
            bar = state["bar"] = tqdm(total=total, desc=desc, unit=unit, file=sys.stderr,
                                      disable=None, dynamic_ncols=True)
        bar.n = done
        bar.refresh()
        if done >= total:
            bar.close()

    return cb


def _log(quiet: bool):
    return (lambda s: None) if quiet else (lambda s: print(s, file=sys.stderr))


def _emit(obj: dict, as_json: bool, text: str) -> None:
    if as_json:
        print(json.dumps(obj, indent=2, sort_keys=True, default=float))
    else:
        print(text)


# ---------------------------------------------------------------- library


def _cmd_library_build(a: argparse.Namespace) -> int:
    from .library.build import build_library
    from .library.recipe import load_recipe

    recipe = load_recipe(a.recipe)
    if a.workers < 1:
        raise InputError(f"--workers: expected an integer >= 1, got {a.workers}")
    out = Path(a.output) if a.output else Path(a.recipe).with_suffix(".npz")
    lib, rep = build_library(
        recipe, out, workers=a.workers, allow_unconverged=a.allow_unconverged,
        progress=_progress_bar("library"), log=_log(a.json),
    )
    s = lib.summary()
    rep["summary"] = s
    text = (
        f"wrote {out}: {rep['cells']} cells ({rep['cells_solved']} solved), nG {s['solver']['n_harmonics']}, "
        f"convergence {rep['convergence']['max_phase_change_rad']:.4f} rad, "
        f"{rep['sweep_seconds']:.1f} s sweep on {a.workers} worker(s); "
        f"{100 * s['fraction_above_threshold']:.1f} % of cells have T0 >= 70 % in both polarisations"
    )
    _emit(rep, a.json, text)
    return 0


def _summary_text(s: dict) -> str:
    g, c = s["grid"], s["convergence"]
    st = s["stack"] or {}
    return "\n".join([
        f"library        {s['file_identity'][:16]}",
        f"grid           wx {g['wx_um'][0]:.3f}..{g['wx_um'][1]:.3f} um x wy {g['wy_um'][0]:.3f}..{g['wy_um'][1]:.3f} um, "
        f"{g['n_wx']} x {g['n_wy']} cells, step {g['step_nm']:g} nm",
        f"stack          lambda {st.get('wavelength_m', 0)*1e9:.1f} nm, period {st.get('period_m', 0)*1e6:.3f} um, "
        f"height {st.get('height_m', 0)*1e6:.3f} um, n {st.get('n_pillar')} on {st.get('n_substrate')}",
        f"solver         {s['solver']['name']} ({s['solver']['factorization']} factorization), nG {s['solver']['n_harmonics']}",
        f"convergence    {c['max_phase_change_rad']:.4f} rad vs nG {c['reference_n_harmonics']} "
        f"(tolerance {c['tolerance_rad']:g}): {'PASS' if c['passed'] else 'FAIL'}",
        f"T0 >= {s['transmission_threshold']:.0%}    {s['n_cells_above_threshold']} cells "
        f"({100 * s['fraction_above_threshold']:.1f} %), mean T0 x {s['mean_T0'][0]:.3f} y {s['mean_T0'][1]:.3f}",
        f"coverage       {100 * s['phase_coverage_2d']:.1f} % of 16x16 (phase_x, phase_y) bins reached by kept cells",
        f"checks         max |cross-pol| {s['max_cross_pol']:.1e}, max |R+T-1| {s['max_energy_error']:.1e}",
    ])


def _lib_arg(a) -> Path:
    return Path(a.library) if a.library else default_library_path()


def _cmd_library_show(a: argparse.Namespace) -> int:
    from .library.store import load_library

    if not 0 < a.threshold <= 1:
        raise InputError(f"--threshold: expected a number in (0, 1], got {a.threshold}")
    lib = load_library(_lib_arg(a))
    s = lib.summary(a.threshold)
    _emit(s, a.json, _summary_text(s))
    return 0


def _cmd_library_plot(a: argparse.Namespace) -> int:
    from .library.plot import plot_library
    from .library.store import load_library

    path = _lib_arg(a)
    lib = load_library(path)
    out = Path(a.output) if a.output else path.with_name(path.stem + "-fig-s1.png")
    plot_library(lib, out)
    print(f"wrote {out}")
    return 0


def _cmd_library_export(a: argparse.Namespace) -> int:
    from .library.store import export_csv, load_library

    lib = load_library(_lib_arg(a))
    n = export_csv(lib, a.csv)
    print(f"wrote {a.csv}: {n} rows")
    return 0


# ----------------------------------------------------------------- design


def _design_text(d, out) -> str:
    m = d.metrics
    return "\n".join([
        f"design         {d.meta['name']} -> {out}",
        f"cells          {d.spec.n_cells} x {d.spec.n_cells} ({d.spec.n_cells * d.spec.period * 1e3:.4g} mm), "
        f"{m['n_cells_in_aperture']} in the clear aperture",
        f"atoms          {m['n_atoms']} from {m['n_kept_library_cells']} kept cells (T0 >= "
        f"{d.meta['discretizer']['threshold']:g}), {m['n_empty_bins']} empty bins, {m['n_atoms_used']} used",
        f"mapping        {m['metric']}, constant offsets x {m['phase_offsets_rad'][0]:+.3f} "
        f"y {m['phase_offsets_rad'][1]:+.3f} rad",
        f"phase RMSE     x-pol {m['rmse_rad'][0]:.4f}  y-pol {m['rmse_rad'][1]:.4f} rad",
        f"peak error     x-pol {m['peak_error_rad'][0]:.4f}  y-pol {m['peak_error_rad'][1]:.4f} rad",
        f"mean T0        x-pol {m['mean_T0'][0]:.4f}  y-pol {m['mean_T0'][1]:.4f}",
        "other metric   " + ", ".join(
            f"{k}: RMSE {v['rmse_rad'][0]:.4f}/{v['rmse_rad'][1]:.4f} rad, T0 {v['mean_T0'][0]:.4f}/{v['mean_T0'][1]:.4f}"
            for k, v in m["comparison_on_sample"].items()) + " (sampled cells)",
    ] + ([f"time           {d.seconds['total']:.1f} s"] if d.seconds else []))


def _cmd_design(a: argparse.Namespace) -> int:
    from .design.store import load_design

    if a.target in ("plot", "show"):
        if not a.path:
            raise InputError(f"design {a.target}: give the design folder or design.npz")
        d = load_design(a.path)
        if a.target == "show":
            _emit(d.metrics, a.json, _design_text(d, a.path))
            return 0
        from .design.plot import plot_design
        from .library.store import load_library

        lib = None
        try:
            lib = load_library(d.meta["library"]["path"])
        except InputError:
            pass  # coverage dots need the library; the rest does not
        base = Path(a.path)
        out = Path(a.output) if a.output else (base if base.is_dir() else base.parent) / "fig-s2.png"
        plot_design(d, out, lib)
        print(f"wrote {out}")
        return 0
    from .design.recipe import load_design_recipe
    from .design.store import run_design

    if a.path:
        raise InputError(f"design: unexpected argument {a.path!r} (usage: design RECIPE [-o OUT])")
    recipe = load_design_recipe(a.target)
    d, out = run_design(recipe, Path(a.output) if a.output else None,
                        progress=_progress_bar("design", unit="row"))
    _emit(d.metrics | {"output": str(out), "seconds": d.seconds}, a.json, _design_text(d, out))
    return 0


# ----------------------------------------------------------------- layout


def _find_design_for(layout: Path, given: str | None):
    from .design.store import load_design

    if given:
        return load_design(given)
    cand = layout.parent / "design.npz"
    if not cand.exists():
        raise InputError(f"{layout}: no design.npz beside it; pass --design DESIGN")
    return load_design(cand)


def _cmd_layout(a: argparse.Namespace) -> int:
    from .layouts import LayoutOptions

    if a.target == "verify":
        return _cmd_layout_verify(a)
    if a.target == "preview":
        return _cmd_layout_preview(a)
    if a.path:
        raise InputError(f"layout: unexpected argument {a.path!r} (usage: layout DESIGN [-o OUT])")
    from .design.store import load_design
    from .layouts import write_layout

    d = load_design(a.target)
    opts = LayoutOptions(layer=a.layer, datatype=a.datatype, grid_nm=a.grid_nm,
                         outline_layer=None if a.no_outline else a.outline_layer,
                         label_layer=a.label_layer, label=a.label)
    base = Path(a.target)
    folder = base if base.is_dir() else base.parent
    stem = Path(a.output) if a.output else folder / "layout"
    if stem.suffix in (".oas", ".gds"):
        stem = stem.with_suffix("")
    fmts = ["oas", "gds"] if a.format == "both" else [a.format]
    if a.format not in ("oas", "gds", "both"):
        raise InputError(f"--format: expected oas, gds or both, got {a.format!r}")
    reports = []
    for fmt in fmts:
        if fmt == "gds" and d.index_map.size > 1_000_000:
            print(f"metadesign: warning: GDSII cannot store irregular repetitions: {d.index_map.size:,} pillars "
                  "expand into one SREF each (expect a file of GB size and minutes)", file=sys.stderr)
        reports.append(write_layout(d, stem.with_suffix("." + fmt), fmt, opts))
    text = "\n".join(
        f"wrote {r['file']}: {r['pillars']:,} pillars, {r['atoms']} atoms, {r['bytes'] / 1e6:.2f} MB in "
        f"{r['seconds']:.1f} s; widths snapped to {r['snapping']['grid_nm']} nm (max error "
        f"{r['snapping']['max_error_nm']:.3f} nm, {r['snapping']['odd_width_atoms']} atoms with an odd-nm width "
        "centred 0.5 nm low)" for r in reports)
    _emit({"layouts": reports}, a.json, text)
    return 0


def _cmd_layout_verify(a: argparse.Namespace) -> int:
    from .layouts import drc_check, read_layout, read_layout_klayout, verify_against_design

    if not a.path:
        raise InputError("layout verify: give the layout file")
    path = Path(a.path)
    lc = read_layout(path)
    d = _find_design_for(path, a.design)
    grid = int(lc.provenance.get("grid_nm", 1)) if "grid_nm" in lc.provenance else 1
    rep = {"file": str(path), "gdstk": verify_against_design(lc, d, grid)}
    if a.klayout:
        rep["klayout"] = verify_against_design(read_layout_klayout(path), d, grid)
    rep["drc"] = drc_check(lc, a.min_feature_nm, a.min_gap_nm, a.drc_window_cells)
    ok = rep["gdstk"]["exact"] and rep["drc"]["passed"] and rep.get("klayout", {"exact": True})["exact"]
    rep["passed"] = ok
    g = rep["gdstk"]
    lines = [f"verify {path}: {'PASS' if ok else 'FAIL'}",
             f"  gdstk read-back: {g['pillars']:,} pillars, exact {g['exact']} ({g['read_seconds']:.1f} s)"
             + "".join(f"\n    - {p}" for p in g["problems"])]
    if "klayout" in rep:
        k = rep["klayout"]
        lines.append(f"  KLayout read-back: {k['pillars']:,} pillars, exact {k['exact']}, per-atom counts "
                     f"{'agree' if k['counts_per_atom'] == g['counts_per_atom'] else 'DIFFER'} "
                     f"({k['read_seconds']:.1f} s)" + "".join(f"\n    - {p}" for p in k["problems"]))
    t, w = rep["drc"]["from_atom_table"], rep["drc"]["geometric_window"]
    lines.append(f"  design rules (min feature {a.min_feature_nm} nm, min gap {a.min_gap_nm} nm): atom table min "
                 f"feature {t['min_feature_nm']} nm, min gap x {t['min_gap_x_nm']} / y {t['min_gap_y_nm']} nm; "
                 f"KLayout window {w['window_cells']}x{w['window_cells']} cells: {w['width_violations']} width, "
                 f"{w['space_violations']} space violations -> {'pass' if rep['drc']['passed'] else 'FAIL'}")
    _emit(rep, a.json, "\n".join(lines))
    return 0 if ok else 1


def _cmd_layout_preview(a: argparse.Namespace) -> int:
    from .layouts import read_layout
    from .layouts.preview import preview_layout

    if not a.path:
        raise InputError("layout preview: give the layout file")
    path = Path(a.path)
    lc = read_layout(path)
    out = Path(a.output) if a.output else path.with_name(path.stem + "-preview.png")
    preview_layout(lc, out, tuple(a.window) if a.window else None)
    print(f"wrote {out}")
    return 0


# ---------------------------------------------------------------- sensing


def _sensing_recipe(a):
    from .paths import repo_root
    from .sensing.model import load_sensing_recipe

    return load_sensing_recipe(a.sensor or repo_root() / "sensing" / "paper.toml")


def _perturbation(bias_x_nm, bias_y_nm, jitter_nm, corner_nm, seed):
    from .sensing.transmission import Perturbation

    for name, v in (("--jitter-nm", jitter_nm), ("--corner-nm", corner_nm)):
        if v < 0:
            raise InputError(f"{name}: expected a number >= 0, got {v}")
    for name, v in (("--bias-nm", bias_x_nm), ("--bias-nm", bias_y_nm)):
        if abs(v) > 200:
            raise InputError(f"{name}: expected a bias in [-200, 200] nm, got {v}")
    return Perturbation(bias_x_nm * 1e-9, bias_y_nm * 1e-9, jitter_nm * 1e-9, corner_nm * 1e-9, seed)


def _cmd_psf(a: argparse.Namespace) -> int:
    from .io import write_npz
    from .sensing.forward import sensor_frames
    from .sensing.model import AsFabricated
    from .sensing.plot import plot_frames
    from .sensing.sensor import add_noise, psf_tensor

    sr = _sensing_recipe(a)
    if len(a.bias_nm) > 2:
        raise InputError(f"--bias-nm: one value (both axes) or two (x y), got {len(a.bias_nm)}")
    pert = _perturbation(a.bias_nm[0], a.bias_nm[-1], a.jitter_nm, a.corner_nm, a.seed)
    fab = AsFabricated.from_files(a.layout, a.library)
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid, pert, _progress_bar("pupil", unit="block-row"))
    e_in = None
    if a.wavefront:
        from .io import read_npz

        z = read_npz(a.wavefront, "wavefront file")
        if "field" not in z or z["field"].shape != cp.G.shape[-2:]:
            raise InputError(f"{a.wavefront}: expected a complex array 'field' of shape {cp.G.shape[-2:]} "
                             "(the coarse pupil grid)")
        e_in = z["field"]
    frames = sensor_frames(cp, sr.sensor, e_in)
    full_check = None
    if a.full_resolution:
        import numpy as np

        from .sensing.forward import full_resolution_frames
        from .sensing.sensor import quadrant_slices
        from .sensing.transmission import pillar_transmission

        if e_in is not None:
            raise InputError("--full-resolution checks the flat-wavefront PSFs; omit --wavefront")
        rng = np.random.default_rng(pert.seed)
        full, _ = full_resolution_frames(
            lambda r0, r1: pillar_transmission(fab.layout.index_map, fab.layout.atom_widths_nm, fab.lib, pert,
                                               slice(r0, r1), rng),
            fab.n_cells, fab.period, fab.wavelength, sr.sensor, fab.tn_scale, window=a.full_resolution,
            progress=_progress_bar("full resolution", unit="row"))
        errs = []
        for p in range(2):
            for k in range(1, 5):
                r, c = quadrant_slices(sr.sensor, k)
                m = full[p][r, c] > 0
                errs.append(float(np.linalg.norm(full[p][r, c][m] - frames[p][r, c][m])
                                  / np.linalg.norm(full[p][r, c][m])))
        full_check = {"window_px": a.full_resolution, "rel_l2_per_channel": errs}
    noisy = add_noise(frames, sr.noise) if (sr.noise.gaussian_sigma or sr.noise.photons_at_peak
                                             or sr.noise.bit_depth) else frames
    tensor = psf_tensor(noisy, sr.sensor)
    out = Path(a.output) if a.output else Path(a.layout).with_name("psf")
    out.mkdir(parents=True, exist_ok=True)
    write_npz(out / "psf.npz", {"frames": noisy, "tensor": tensor})
    fig = plot_frames(noisy, sr.sensor, out / "psf-fig-2c.png", fab.channels,
                      f"{Path(a.layout).name}: sensor frames (bias {a.bias_nm} nm, jitter {a.jitter_nm} nm)")
    summary = {"output": str(out), "frames_shape": list(frames.shape), "tensor_shape": list(tensor.shape),
               "pupil_grid": list(cp.G.shape[-2:]), "block_cells": cp.block, "clamped_pillars": cp.n_clamped,
               "power_per_frame": [float(f.sum()) for f in frames], "figure": str(fig),
               "aperture_m2": (fab.n_cells * fab.period) ** 2, "full_resolution_check": full_check}
    text = (f"wrote {out}/psf.npz (frames 2x{sr.sensor.height_px}x{sr.sensor.width_px}, tensor {tuple(tensor.shape)}) "
            f"and {fig.name}; coarse pupil {cp.G.shape[-1]}^2 ({cp.block}x{cp.block} cells per sample); "
            f"power on sensor x {summary['power_per_frame'][0] / summary['aperture_m2']:.3f} "
            f"y {summary['power_per_frame'][1] / summary['aperture_m2']:.3f} of incident; "
            f"{cp.n_clamped} pillars outside the library range (clamped)")
    if full_check:
        text += (f"\nfull-resolution check ({a.full_resolution}x{a.full_resolution} px per quadrant, every pillar): "
                 f"fast path within {max(full_check['rel_l2_per_channel']):.2e} relative L2")
    _emit(summary, a.json, text)
    return 0


def _cmd_fab_study(a: argparse.Namespace) -> int:
    import csv
    import itertools

    import numpy as np

    from .io import atomic_path, atomic_write_text
    from .sensing.model import AsFabricated, channel_metrics
    from .sensing.plot import plot_fab_study

    sr = _sensing_recipe(a)
    if a.seeds < 1:
        raise InputError(f"--seeds: expected an integer >= 1, got {a.seeds}")
    fab = AsFabricated.from_files(a.layout, a.library)
    if not fab.channels[0]:
        raise InputError(f"{a.layout}: layout provenance lacks the design recipe (channel focal lengths)")
    cases = list(itertools.product(a.bias_nm, a.jitter_nm, a.corner_nm, range(a.seeds)))
    rows = []
    bar = _progress_bar("fab-study", unit="case")
    for i, (b, j, c, s) in enumerate(cases):
        pert = _perturbation(b, b, j, c, a.seed + s)
        cp = fab.pupil(sr.sensor.distance, sr.pupil_grid, pert)
        label = f"bias {b:+g} jit {j:g} cr {c:g}"
        for r in channel_metrics(cp, sr.sensor, fab):
            rows.append({"case": i // a.seeds, "label": label, "bias_nm": b, "jitter_nm": j,
                         "corner_nm": c, "seed": a.seed + s, "clamped_pillars": cp.n_clamped, **r})
        bar(i + 1, len(cases))
    out = Path(a.output) if a.output else Path(a.layout).with_name("fab-study")
    out.mkdir(parents=True, exist_ok=True)
    cols = ["bias_nm", "jitter_nm", "corner_nm", "seed", "pol", "k", "quadrant", "design_focal_length_mm",
            "focusing_efficiency", "strehl", "focal_shift_mm", "centroid_shift_x_um", "centroid_shift_y_um",
            "crosstalk", "clamped_pillars"]
    with atomic_path(out / "fab-study.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(cols)
            for r in rows:
                w.writerow([r["bias_nm"], r["jitter_nm"], r["corner_nm"], r["seed"], r["pol"], r["k"], r["quadrant"],
                            f"{r['design_focal_length_mm']:.4f}", f"{r['focusing_efficiency']:.6f}",
                            f"{r['strehl']:.5f}", f"{r['focal_shift_mm']:.5f}", f"{r['centroid_shift_um'][0]:.4f}",
                            f"{r['centroid_shift_um'][1]:.4f}", f"{r['crosstalk']:.5f}", r["clamped_pillars"]])
    fig = plot_fab_study(rows, out / "fab-study.png")
    atomic_write_text(out / "fab-study.json", json.dumps(rows, indent=1, default=float))
    lines = [f"wrote {out}/fab-study.csv, fab-study.png ({len(cases)} cases x 8 channels)",
             "  bias  jitter corner | mean eff  mean Strehl  mean |focal shift| mm  mean crosstalk  clamped"]
    for b, j, c in itertools.product(a.bias_nm, a.jitter_nm, a.corner_nm):
        rr = [r for r in rows if (r["bias_nm"], r["jitter_nm"], r["corner_nm"]) == (b, j, c)]
        lines.append(f"  {b:+5g} {j:6g} {c:6g} | {np.mean([r['focusing_efficiency'] for r in rr]):.4f}    "
                     f"{np.mean([r['strehl'] for r in rr]):.4f}       "
                     f"{np.mean([abs(r['focal_shift_mm']) for r in rr]):.4f}                "
                     f"{np.mean([r['crosstalk'] for r in rr]):.4f}          {rr[0]['clamped_pillars']}")
    _emit({"rows": rows, "figure": str(fig)}, a.json, "\n".join(lines))
    return 0


# ------------------------------------------------------------- turbulence


def _scenario(a):
    from dataclasses import replace

    from .paths import repo_root
    from .turbulence.validate import load_scenario

    sc = load_scenario(a.recipe or repo_root() / "sensing" / "turbulence.toml")
    if getattr(a, "rytov", None) and len(a.rytov) == 1:
        sc = replace(sc, rytov=a.rytov[0])
    return sc


def _cmd_turbulence(a: argparse.Namespace) -> int:
    from dataclasses import replace

    from .turbulence.path import check_sampling, solve_path

    sc = _scenario(a)
    if a.action == "show":
        pm = solve_path(sc)
        rep = check_sampling(sc, pm)
        info = {"rytov": sc.rytov, "cn2": pm.cn2, "r0_m": pm.r0, "D_over_r0": sc.receiver_aperture / pm.r0,
                "r0_screens_m": [float(x) for x in pm.r0_screens], "rytov_screens": pm.rytov_screens.tolist(),
                "rytov_achieved": pm.rytov_achieved, "sampling_ok": rep.ok, "constraints": rep.constraints,
                "failures": list(rep.failures), "magnification": sc.magnification}
        lines = [f"Rytov {sc.rytov:g}: Cn^2 {pm.cn2:.3g} m^-2/3, r0 {pm.r0 * 100:.2f} cm, D/r0 "
                 f"{info['D_over_r0']:.2f}, screens' Rytov " + " ".join(f"{v:.3f}" for v in pm.rytov_screens),
                 f"sampling: {'OK' if rep.ok else 'INFEASIBLE'}"]
        lines += [f"  {k}: {v[0]:.4g} vs {v[1]:.4g}" for k, v in rep.constraints.items()]
        lines += [f"  ! {f}" for f in rep.failures]
        _emit(info, a.json, "\n".join(lines))
        return 0 if rep.ok else 2
    from .turbulence.validate import plot_validation, validate

    if a.samples < 2:
        raise InputError(f"--samples: expected an integer >= 2, got {a.samples}")
    rytovs = a.rytov or [0.1, 0.3, 0.5, 0.7]
    for r in rytovs:
        if not 0 < r <= 5:
            raise InputError(f"--rytov: expected values in (0, 5], got {r}")
    for r in rytovs:  # refuse infeasible sampling before any work
        _ = check_sampling(replace(sc, rytov=r), solve_path(replace(sc, rytov=r)))
        if not _.ok:
            raise InputError(f"Rytov {r:g}: infeasible sampling: " + "; ".join(_.failures))
    res = validate(sc, rytovs, a.samples, a.seed, progress=_progress_bar("turbulence", unit="sample"))
    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    figs = plot_validation(res, out)
    from .io import atomic_write_text

    atomic_write_text(out / "turbulence-validation.json", json.dumps(res, default=float))
    sf = res["structure_function"]
    lines = [f"wrote {', '.join(f.name for f in figs)} and turbulence-validation.json to {out}",
             "structure function / theory: " + " ".join(f"{x:.3f}" for x in sf["ratio"])
             + f" (separations {sf['r_m'][0] * 1e3:g}..{sf['r_m'][-1] * 1e3:g} mm)",
             "Rytov nominal -> measured (weak theory with inner scale), D/r0, NPiB complex / phase / none:"]
    for lv in res["levels"]:
        nb = {k: float(np.mean(v)) for k, v in lv["npib"].items()}
        lines.append(f"  {lv['rytov_nominal']:.2f} -> {lv['rytov_measured']:.3f} ({lv['rytov_weak_theory_inner_scale']:.3f}),"
                     f" D/r0 {lv['D_over_r0']:.2f}, NPiB {nb['complex']:.3f} / {nb['phase']:.3f} / {nb['none']:.3f}")
    summary = {"structure_function": sf, "levels": [{k: v for k, v in lv.items() if k in (
        "rytov_nominal", "rytov_measured", "rytov_weak_theory_inner_scale", "r0_m", "D_over_r0")}
        | {"npib_mean": {k: float(np.mean(v)) for k, v in lv["npib"].items()}} for lv in res["levels"]],
        "figures": [str(f) for f in figs]}
    _emit(summary, a.json, "\n".join(lines))
    return 0


# ------------------------------------------------------------------- demo


def _cmd_demo(a: argparse.Namespace) -> int:
    from .demo import run_demo

    summary = run_demo(Path(a.output), log=_log(a.json))
    _emit(summary, a.json, summary["text"])
    return 0


# ------------------------------------------------------------------ parser


def _forward_args(p: argparse.ArgumentParser) -> None:
    """Arguments shared by the stage-4 commands."""
    p.add_argument("layout", help="layout file (.oas/.gds) written by `metadesign layout`")
    p.add_argument("--sensor", help="sensing recipe (default: sensing/paper.toml)")
    p.add_argument("--library", help="unit-cell library (default: the design's)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="metadesign",
        description="Design, lay out and verify birefringent metasurfaces for single-shot "
        "phase-diversity wavefront sensing.",
    )
    p.add_argument("--version", action="version", version=f"metadesign {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    demo = sub.add_parser("demo", help="run the embedded demo through every stage built so far",
                          description="Run the small embedded demo through every stage built so far "
                          "(from the committed unit-cell library) and write a summary and figures.")
    demo.add_argument("-o", "--output", default="demo-out", help="output folder (default: ./demo-out)")
    demo.add_argument("--json", action="store_true", help="print the summary as JSON")
    demo.set_defaults(func=_cmd_demo)

    des = sub.add_parser(
        "design", help="Eq. 1 supercell design + discretizer; also: design plot|show DESIGN",
        description="Stage 2. `metadesign design RECIPE [-o OUT]` computes the Eq. 1 phases of every cell, "
        "selects the atoms (16x16 binning of the library's (phase_x, phase_y) coverage over cells with T0 >= "
        "threshold) and maps every cell to its nearest atom; writes OUT/design.npz and OUT/metrics.json "
        "(default OUT: a folder named after the recipe, beside it). `metadesign design plot DESIGN [-o PNG]` "
        "draws the Fig. S2 equivalent; `metadesign design show DESIGN [--json]` prints the metrics.")
    des.add_argument("target", help="a design recipe (TOML), or 'plot' / 'show'")
    des.add_argument("path", nargs="?", help="with plot/show: the design folder or design.npz")
    des.add_argument("-o", "--output", help="output folder (design) or PNG path (plot)")
    des.add_argument("--json", action="store_true", help="print the metrics as JSON")
    des.set_defaults(func=_cmd_design)

    lay = sub.add_parser(
        "layout", help="OASIS/GDS layout: layout DESIGN | layout verify LAYOUT | layout preview LAYOUT",
        description="Stage 3. `metadesign layout DESIGN` writes the design as OASIS (default) and/or GDS with "
        "gdstk (one cell per atom, one repetition per atom; 1 nm database unit), with provenance in the file "
        "and a JSON side-car. `metadesign layout verify LAYOUT` reads every pillar back and compares it exactly "
        "with the design (add --klayout for KLayout's independent reader), and runs the design-rule checks. "
        "`metadesign layout preview LAYOUT` renders a pillar window and a thumbnail.")
    lay.add_argument("target", help="design folder / design.npz, or 'verify' / 'preview'")
    lay.add_argument("path", nargs="?", help="with verify/preview: the layout file")
    lay.add_argument("-o", "--output", help="layout path without suffix (default DESIGN/layout), or preview PNG")
    lay.add_argument("--format", default="oas", help="oas (default), gds or both")
    lay.add_argument("--layer", type=int, default=1, help="pillar layer (default 1)")
    lay.add_argument("--datatype", type=int, default=0, help="pillar datatype (default 0)")
    lay.add_argument("--grid-nm", type=int, default=1, help="width snapping grid in nm (default 1)")
    lay.add_argument("--outline-layer", type=int, default=10, help="aperture outline layer (default 10)")
    lay.add_argument("--no-outline", action="store_true", help="no aperture outline")
    lay.add_argument("--label-layer", type=int, default=11, help="text/provenance layer (default 11)")
    lay.add_argument("--label", help="label text written beside the aperture (default: the design name)")
    lay.add_argument("--design", help="verify: the design to compare with (default: design.npz beside the layout)")
    lay.add_argument("--klayout", action="store_true", help="verify: also read the file with KLayout and compare")
    lay.add_argument("--min-feature-nm", type=int, default=100, help="verify: minimum pillar width rule (100)")
    lay.add_argument("--min-gap-nm", type=int, default=150, help="verify: minimum gap rule (150)")
    lay.add_argument("--drc-window-cells", type=int, default=64, help="verify: geometric DRC window (64 cells)")
    lay.add_argument("--window", type=int, nargs=3, metavar=("IX0", "IY0", "CELLS"),
                     help="preview: window of cells to draw (default: 16 x 16 at the centre)")
    lay.add_argument("--json", action="store_true", help="print the report as JSON")
    lay.set_defaults(func=_cmd_layout)

    psf = sub.add_parser(
        "psf", help="as-fabricated 8 PSFs of a layout on the sensor (Fig. 2c)",
        description="Stage 4. Rebuild the complex transmission from the layout file itself (pillars read back, "
        "optional fab perturbations, complex-t interpolation in the full RCWA library), propagate to the sensor "
        "with the fast coarse-pupil Fresnel path, and write OUT/psf.npz (frames 2 x H x W, tensor 8 x S x S in "
        "the order x-pol QI..QIV, y-pol QI..QIV) and OUT/psf-fig-2c.png.")
    _forward_args(psf)
    psf.add_argument("--wavefront", help=".npz with a complex 'field' on the pupil grid (default: flat)")
    psf.add_argument("--bias-nm", type=float, nargs="+", default=[0.0], help="width bias: one value or x y")
    psf.add_argument("--jitter-nm", type=float, default=0.0, help="random width jitter sigma (nm)")
    psf.add_argument("--corner-nm", type=float, default=0.0, help="corner rounding radius (nm)")
    psf.add_argument("--seed", type=int, default=0, help="jitter seed")
    psf.add_argument("--full-resolution", type=int, metavar="PX",
                     help="also evaluate every pillar without block averaging on the central PX x PX pixels of "
                     "each quadrant (chunked, bounded memory) and report the fast path's error")
    psf.add_argument("-o", "--output", help="output folder (default: psf/ beside the layout)")
    psf.add_argument("--json", action="store_true", help="print the summary as JSON")
    psf.set_defaults(func=_cmd_psf)

    fs = sub.add_parser(
        "fab-study", help="sweep fab perturbations: efficiency, Strehl, focal/centroid shift, crosstalk",
        description="For every combination of --bias-nm, --jitter-nm, --corner-nm (and --seeds jitter draws), "
        "rebuild the as-fabricated pupil and report per channel: focusing efficiency (power in the designed "
        "quadrant / incident), Strehl ratio at best focus, focal shift, centroid shift, crosstalk into the other "
        "quadrants. Writes OUT/fab-study.csv, .json and .png.")
    _forward_args(fs)
    fs.add_argument("--bias-nm", type=float, nargs="+", default=[-10.0, 0.0, 10.0], help="width biases (nm)")
    fs.add_argument("--jitter-nm", type=float, nargs="+", default=[0.0], help="jitter sigmas (nm)")
    fs.add_argument("--corner-nm", type=float, nargs="+", default=[0.0], help="corner radii (nm)")
    fs.add_argument("--seeds", type=int, default=1, help="jitter draws per case")
    fs.add_argument("--seed", type=int, default=0, help="first jitter seed")
    fs.add_argument("-o", "--output", help="output folder (default: fab-study/ beside the layout)")
    fs.add_argument("--json", action="store_true", help="print the rows as JSON")
    fs.set_defaults(func=_cmd_fab_study)

    tu = sub.add_parser(
        "turbulence", help="turbulence model: show (path, r0, sampling) | validate (Figs. S5, S6)",
        description="Stage 5. `turbulence show` solves the path (Rytov -> Cn^2 -> r0 -> per-screen r0) and checks "
        "the split-step sampling constraints (exit 2 when infeasible). `turbulence validate` compares screens and "
        "received fields with theory: structure function, log-amplitude variance vs nominal Rytov, coherence "
        "factor, long-exposure MTF, and power in bucket after phase-only / complex-field / no correction.")
    tu.add_argument("action", choices=["show", "validate"])
    tu.add_argument("recipe", nargs="?", help="scenario recipe (default: sensing/turbulence.toml)")
    tu.add_argument("--rytov", type=float, nargs="+", help="Rytov numbers (validate default: 0.1 0.3 0.5 0.7)")
    tu.add_argument("--samples", type=int, default=40, help="samples per Rytov number (default 40)")
    tu.add_argument("--seed", type=int, default=0, help="master seed")
    tu.add_argument("-o", "--output", default="turbulence-out", help="output folder for validate")
    tu.add_argument("--json", action="store_true", help="print the summary as JSON")
    tu.set_defaults(func=_cmd_turbulence)

    lib = sub.add_parser("library", help="unit-cell library: build (RCWA sweep), show, plot, export",
                         description="Stage 1: the RCWA unit-cell library of rectangular Si pillars.")
    lsub = lib.add_subparsers(dest="library_command", metavar="ACTION")
    lsub.required = True
    b = lsub.add_parser("build", help="run the RCWA sweep of a recipe (parallel, resumable)",
                        description="Certify RCWA convergence on a few cells, then sweep (wx, wy) in "
                        "parallel worker processes. Finished chunks are kept in OUTPUT.partial/; a killed "
                        "build resumes where it stopped. The library is written atomically.")
    b.add_argument("recipe", help="library recipe (TOML), e.g. library/paper.toml")
    b.add_argument("-o", "--output", help="library file (default: the recipe path with .npz)")
    b.add_argument("-j", "--workers", type=int, default=min(2, os.cpu_count() or 1),
                   help="worker processes, one thread each (default: 2)")
    b.add_argument("--allow-unconverged", action="store_true",
                   help="build even if the convergence check exceeds the tolerance")
    b.add_argument("--json", action="store_true", help="print the build report as JSON")
    b.set_defaults(func=_cmd_library_build)

    s = lsub.add_parser("show", help="print a summary of a library",
                        description="Summary: grid, stack, solver, convergence, coverage, fraction above "
                        "the transmission threshold.")
    s.add_argument("library", nargs="?", help="library file (default: the committed library/paper.npz)")
    s.add_argument("--threshold", type=float, default=0.7, help="0th-order transmission threshold (default 0.7)")
    s.add_argument("--json", action="store_true", help="print as JSON")
    s.set_defaults(func=_cmd_library_show)

    pl = lsub.add_parser("plot", help="draw the Fig. S1 equivalent (phase, T0, T total maps)")
    pl.add_argument("library", nargs="?", help="library file (default: the committed library/paper.npz)")
    pl.add_argument("-o", "--output", help="PNG path (default: beside the library)")
    pl.set_defaults(func=_cmd_library_plot)

    ex = lsub.add_parser("export", help="write the library as CSV for other tools")
    ex.add_argument("library", nargs="?", help="library file (default: the committed library/paper.npz)")
    ex.add_argument("--csv", required=True, help="CSV output path")
    ex.set_defaults(func=_cmd_library_export)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    a = parser.parse_args(argv)
    try:
        return int(a.func(a) or 0)
    except InputError as exc:
        print(f"metadesign: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("metadesign: interrupted; finished work is kept, rerun the same command to resume",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

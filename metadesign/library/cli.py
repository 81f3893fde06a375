"""``metadesign library build|show|plot|export`` (stage 1 CLI)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..cliutil import emit, integer, log_to, num, out_dir, out_file, progress_bar, workers_arg
from ..paths import default_library_path

__all__ = ["register"]


def _cmd_build(a: argparse.Namespace) -> int:
    from .build import build_library
    from .recipe import load_recipe

    recipe = load_recipe(a.recipe)
    out = out_file(Path(a.output) if a.output else Path(a.recipe).with_suffix(".npz"), suffixes=(".npz",))
    lib, rep = build_library(
        recipe, out, workers=a.workers, allow_unconverged=a.allow_unconverged,
        progress=progress_bar("library"), log=log_to(a.json), scheduler=a.scheduler,
    )
    s = lib.summary()
    rep["summary"] = s
    text = (
        f"wrote {out}: {rep['cells']} cells ({rep['cells_solved']} solved), nG {s['solver']['n_harmonics']}, "
        f"convergence {rep['convergence']['max_phase_change_rad']:.4f} rad, "
        f"{rep['sweep_seconds']:.1f} s sweep on {a.workers} worker(s); "
        f"{100 * s['fraction_above_threshold']:.1f} % of cells have T0 >= 70 % in both polarisations"
    )
    emit(rep, a.json, text)
    return 0


def summary_text(s: dict) -> str:
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


def _cmd_show(a: argparse.Namespace) -> int:
    from .store import load_library

    lib = load_library(_lib_arg(a))
    s = lib.summary(a.threshold)
    emit(s, a.json, summary_text(s))
    return 0


def _cmd_plot(a: argparse.Namespace) -> int:
    from .plot import plot_library
    from .store import load_library

    path = _lib_arg(a)
    out = out_file(Path(a.output) if a.output else path.with_name(path.stem + "-fig-s1.png"), suffixes=(".png",))
    lib = load_library(path)
    plot_library(lib, out)
    print(f"wrote {out}")
    return 0


def _cmd_export(a: argparse.Namespace) -> int:
    from .store import export_csv, load_library

    out = out_file(a.csv, "--csv")
    lib = load_library(_lib_arg(a))
    n = export_csv(lib, out)
    print(f"wrote {out}: {n} rows")
    return 0


def _cmd_lpa(a: argparse.Namespace) -> int:
    import json

    import numpy as np

    from ..io import atomic_write_text
    from ..sensing.model import AsFabricated
    from .lpa import lpa_check, lpa_downstream

    src = Path(a.design)
    out = out_dir(a.output or (src.parent if src.is_file() else src) / "lpa-check")
    if (a.dataset is None) != (a.model is None):
        from ..validation import ValidationError

        raise ValidationError("--dataset and --model go together (the downstream NPiB needs both)")
    log = log_to(a.json)
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
    out.mkdir(exist_ok=True)
    atomic_write_text(out / "lpa.json", json.dumps(rep, indent=1))
    from .plot import plot_lpa

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


def register(sub) -> None:
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
    workers_arg(b)
    b.add_argument("--scheduler", metavar="ADDRESS",
                   help="solve the chunks on a Dask distributed scheduler (e.g. tcp://host:8786) instead of -j")
    b.add_argument("--allow-unconverged", action="store_true",
                   help="build even if the convergence check exceeds the tolerance")
    b.add_argument("--json", action="store_true", help="print the build report as JSON")
    b.set_defaults(func=_cmd_build)

    s = lsub.add_parser("show", help="print a summary of a library",
                        description="Summary: grid, stack, solver, convergence, coverage, fraction above "
                        "the transmission threshold.")
    s.add_argument("library", nargs="?", help="library file (default: the committed library/paper.npz)")
    s.add_argument("--threshold", type=num(0, 1, open_lo=True), default=0.7,
                   help="0th-order transmission threshold in (0, 1] (default 0.7)")
    s.add_argument("--json", action="store_true", help="print as JSON")
    s.set_defaults(func=_cmd_show)

    pl = lsub.add_parser("plot", help="draw the Fig. S1 equivalent (phase, T0, T total maps)")
    pl.add_argument("library", nargs="?", help="library file (default: the committed library/paper.npz)")
    pl.add_argument("-o", "--output", help="PNG path (default: beside the library)")
    pl.set_defaults(func=_cmd_plot)

    ex = lsub.add_parser("export", help="write the library as CSV for other tools")
    ex.add_argument("library", nargs="?", help="library file (default: the committed library/paper.npz)")
    ex.add_argument("--csv", required=True, help="CSV output path")
    ex.set_defaults(func=_cmd_export)

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
    lp.add_argument("--samples", type=integer(1, 100000), default=64, help="test samples downstream (64)")
    lp.add_argument("--noise", type=num(0, 100), default=5.0, help="sensor noise downstream, %% of peak (5)")
    lp.add_argument("-o", "--output", help="output folder (default: lpa-check/ beside the design)")
    workers_arg(lp)
    lp.add_argument("--json", action="store_true", help="print the report as JSON")
    lp.set_defaults(func=_cmd_lpa)

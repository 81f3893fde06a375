"""``metadesign library build|show|plot|export`` (stage 1 CLI)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..cliutil import emit, log_to, num, out_file, progress_bar, workers_arg
from ..execution import scratch_path
from ..paths import default_library_path
from ..outputs import product

__all__ = ["register"]


def _cmd_build(a: argparse.Namespace) -> int:
    from .build import build_library
    from .recipe import load_recipe

    recipe = load_recipe(a.recipe)
    out = out_file(Path(a.output) if a.output else Path(a.recipe).with_suffix(".npz"), suffixes=(".npz",))
    with product(out, "unit-cell-library", {"recipe": a.recipe}, scratch=(scratch_path(out),)):
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
    with product(out, "figure", {"library": path}):
        plot_library(lib, out)
    print(f"wrote {out}")
    return 0


def _cmd_export(a: argparse.Namespace) -> int:
    from .store import export_csv, load_library

    out = out_file(a.csv, "-o/--output")
    lib = load_library(_lib_arg(a))
    with product(out, "library-csv", {"library": _lib_arg(a)}):
        n = export_csv(lib, out)
    print(f"wrote {out}: {n} rows")
    return 0


def register(sub) -> dict:
    """Add the stage-1 commands; returns the ``library`` action group (studies add theirs to it)."""
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
    ex.add_argument("-o", "--output", "--csv", dest="csv", required=True, help="CSV output path")
    ex.set_defaults(func=_cmd_export)
    return {"library": lsub}

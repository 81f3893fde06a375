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
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from . import __version__  # noqa: E402
from .config import InputError  # noqa: E402
from .paths import default_library_path, repo_root  # noqa: E402

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


# ------------------------------------------------------------------- demo


def _cmd_demo(a: argparse.Namespace) -> int:
    from .demo import run_demo

    summary = run_demo(Path(a.output), log=_log(a.json))
    _emit(summary, a.json, summary["text"])
    return 0


# ------------------------------------------------------------------ parser


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

"""``metadesign design build|plot|show`` (stage 2 CLI).  ``design RECIPE`` is
kept as the spelling of ``design build RECIPE``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..cliutil import emit, integer, out_dir, out_file, progress_bar
from ..outputs import product

__all__ = ["register", "SUBCOMMANDS", "DEFAULT"]

SUBCOMMANDS = ("build", "plot", "show", "compensate")
DEFAULT = "build"


def design_text(d, out) -> str:
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


def _cmd_build(a: argparse.Namespace) -> int:
    from .recipe import load_design_recipe
    from .store import run_design

    recipe = load_design_recipe(a.recipe)
    out = out_dir(a.output) if a.output else out_dir(recipe.default_output())
    with product(out, "design", {"recipe": a.recipe, "design.library": recipe.library_path}):
        d, out = run_design(recipe, out, progress=progress_bar("design", unit="row"))
    emit(d.metrics | {"output": str(out), "seconds": d.seconds}, a.json, design_text(d, out))
    return 0


def _cmd_show(a: argparse.Namespace) -> int:
    from .discretize import distinct_supercells
    from .store import load_design

    d = load_design(a.design)
    sc = distinct_supercells(d.index_map, d.spec.supercell)
    cov = sc["most_frequent_covering"]
    emit({**d.metrics, "distinct_supercells": sc}, a.json, design_text(d, a.design) + "\n" + (
        f"supercells     {sc['supercells']:,} ({d.spec.supercell}x{d.spec.supercell}), {sc['distinct']:,} distinct; the "
        f"most frequent {cov['0.5']:,} / {cov['0.9']:,} / {cov['0.99']:,} cover 50 / 90 / 99 %"))
    return 0


def _cmd_plot(a: argparse.Namespace) -> int:
    from ..validation import ValidationError
    from .plot import plot_design
    from .store import design_file, design_library, load_design

    base = Path(a.design)
    out = out_file(Path(a.output) if a.output else (base if base.is_dir() else base.parent) / "fig-s2.png",
                   suffixes=(".png",))
    d = load_design(a.design)
    lib = None
    try:
        lib = design_library(d)
    except ValidationError:
        pass  # coverage dots need the library; the rest does not
    with product(out, "figure", {"design": design_file(base)}):
        plot_design(d, out, lib)
    print(f"wrote {out}")
    return 0


def _cmd_compensate(a: argparse.Namespace) -> int:
    from ..library.coupling_net import find_coupling
    from .compensate import compensate_design
    from .store import design_file, design_library, load_design, save_design

    src = Path(a.design)
    d = load_design(src)
    if d.meta.get("coupling_compensated"):
        from ..validation import ValidationError

        raise ValidationError(f"{src}: already compensated (start from the nearest-atom design)")
    out = out_dir(a.output or (src if src.is_dir() else src.parent).with_name(
        (src if src.is_dir() else src.parent).name + "-compensated"))
    lib = design_library(d)
    model, card, mpath = find_coupling(lib, a.coupling_model)
    if model.cfg.interaction != "pair":
        from ..validation import ValidationError

        raise ValidationError(f"--coupling-model {mpath}: interaction {model.cfg.interaction!r}; the compensating "
                              "discretizer scores candidates from pair tables and needs a 'pair' model")
    with product(out, "design", {"design": design_file(src), "--coupling-model": mpath}):
        d2, rep = compensate_design(d, model, a.neighbours, a.sweeps,
                                    progress=progress_bar("compensate", unit="row"))
        d2.meta["coupling_model"] = {"path": str(mpath), "sha256": card["weights_sha256"]}
        save_design(out, d2)
    rep["output"] = str(out)
    b, f = rep["residual_rms_before"], rep["residual_rms_after"]
    emit(rep, a.json, f"wrote {out}/design.npz: {rep['supercells']:,} supercells re-chosen under the coupling "
                      f"model ({mpath.name}) in {rep['seconds']:.1f} s; {100 * rep['pillars_changed_fraction']:.1f} % "
                      f"of pillars changed; supercell residual |t - target| RMS x {b[0]:.4f} -> {f[0]:.4f}, "
                      f"y {b[1]:.4f} -> {f[1]:.4f}")
    return 0


def register(sub) -> None:
    des = sub.add_parser(
        "design", help="stage 2: design build RECIPE | design plot DESIGN | design show DESIGN",
        description="Stage 2. `design build RECIPE [-o OUT]` (or `design RECIPE`) computes the Eq. 1 phases of "
        "every cell, selects the atoms (16x16 binning of the library's (phase_x, phase_y) coverage over cells "
        "with T0 >= threshold) and maps every cell to its nearest atom; writes OUT/design.npz and "
        "OUT/metrics.json (default OUT: a folder named after the recipe, beside it). `design plot DESIGN` draws "
        "the Fig. S2 equivalent; `design show DESIGN` prints the metrics.")
    dsub = des.add_subparsers(dest="design_command", metavar="ACTION")
    dsub.required = True
    b = dsub.add_parser("build", help="design a metasurface from a recipe (TOML)")
    b.add_argument("recipe", help="design recipe (TOML), e.g. layouts/paper-5mm.toml")
    b.add_argument("-o", "--output", help="output folder (default: a folder named after the recipe, beside it)")
    b.add_argument("--json", action="store_true", help="print the metrics as JSON")
    b.set_defaults(func=_cmd_build)
    s = dsub.add_parser("show", help="print a design's metrics")
    s.add_argument("design", help="design folder or design.npz")
    s.add_argument("--json", action="store_true", help="print the metrics as JSON")
    s.set_defaults(func=_cmd_show)
    p = dsub.add_parser("plot", help="draw the Fig. S2 equivalent")
    p.add_argument("design", help="design folder or design.npz")
    p.add_argument("-o", "--output", help="PNG path (default: DESIGN/fig-s2.png)")
    p.set_defaults(func=_cmd_plot)
    c = dsub.add_parser(
        "compensate", help="re-choose every supercell's atoms so its coupled 0th order matches the lens fields",
        description="The supercell-aware discretizer: starting from DESIGN's nearest-atom choice, choose each "
        "2 x 2 supercell's four atoms jointly (coordinate descent over each atom's nearest atoms in phase) so "
        "that the coupling model's propagating order matches the sum of the four lens fields in both "
        "polarisations. Atoms stay in the design's table (its design rules). Writes OUT/design.npz; lay it out "
        "with `metadesign layout OUT`.")
    c.add_argument("design", help="design folder or design.npz (nearest-atom)")
    c.add_argument("--coupling-model", help="coupling model (default: the one fitted against the design's library)")
    c.add_argument("--neighbours", type=integer(1, 256), default=9, help="candidate atoms per pillar (9)")
    c.add_argument("--sweeps", type=integer(1, 100), default=2, help="coordinate-descent sweeps (2)")
    c.add_argument("-o", "--output", help="output folder (default: DESIGN-compensated beside it)")
    c.add_argument("--json", action="store_true", help="print the report as JSON")
    c.set_defaults(func=_cmd_compensate)

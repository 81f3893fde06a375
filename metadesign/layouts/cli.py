"""``metadesign layout write|verify|preview`` (stage 3 CLI).  ``layout DESIGN``
is kept as the spelling of ``layout write DESIGN``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..cliutil import emit, integer, out_dir, out_file, progress_bar, workers_arg
from ..config import InputError
from ..execution import Execution
from ..outputs import product
from .rules import DESIGN_RULES, DesignRules

__all__ = ["register", "SUBCOMMANDS", "DEFAULT", "MAX_PREVIEW_CELLS"]

SUBCOMMANDS = ("write", "verify", "preview", "tiled")
DEFAULT = "write"
#: a preview draws one patch per pillar: beyond this it is a picture of noise (and minutes of matplotlib)
MAX_PREVIEW_CELLS = 256


def _cmd_write(a: argparse.Namespace) -> int:
    from ..design.store import design_file, load_design
    from . import write_layout

    base = Path(a.design)
    folder = base if base.is_dir() else base.parent
    stem = Path(a.output) if a.output else folder / "layout"
    if stem.is_dir():
        raise InputError(f"-o/--output {stem}: is a folder, expected a layout file path (e.g. {stem}/layout.oas)")
    if stem.suffix in (".oas", ".gds"):
        stem = stem.with_suffix("")
    elif stem.suffix:
        raise InputError(f"-o/--output {stem}: expected a layout path ending in .oas or .gds (or one without a "
                         "suffix: --format adds it)")
    fmts = ["oas", "gds"] if a.format == "both" else [a.format]
    for fmt in fmts:
        out_file(stem.with_suffix("." + fmt))
    d = load_design(a.design)
    opts = _options(a)
    reports = []
    src = design_file(base)
    for fmt in fmts:
        if fmt == "gds" and d.index_map.size > 1_000_000:
            print(f"metadesign: warning: GDSII cannot store irregular repetitions: {d.index_map.size:,} pillars "
                  "expand into one SREF each (expect a file of GB size and minutes)", file=sys.stderr)
        target = stem.with_suffix("." + fmt)
        with product(target, "layout", {"design": src}, also=(target.with_name(target.name + ".json"),)):
            reports.append(write_layout(d, target, fmt, opts))
    text = "\n".join(
        f"wrote {r['file']}: {r['pillars']:,} pillars, {r['atoms']} atoms, {r['bytes'] / 1e6:.2f} MB in "
        f"{r['seconds']:.1f} s; widths snapped to {r['snapping']['grid_nm']} nm (max error "
        f"{r['snapping']['max_error_nm']:.3f} nm, {r['snapping']['odd_width_atoms']} atoms with an odd-nm width "
        "centred 0.5 nm low)" for r in reports)
    emit({"layouts": reports}, a.json, text)
    return 0


def _text_tiled(r) -> str:
    """The text report of the tiled method (KLayout's count of every pillar, sampled tiles)."""
    rep, d, rules = r.details, r.drc, r.rules
    viol = sum(w["width_violations"] + w["space_violations"] for w in d["windows"])
    lines = [f"verify {r.file}: {'PASS' if r.passed else 'FAIL'} (tiled: {rep['tiles']:,} tiles)",
             f"  KLayout count of every pillar: {rep['pillars_klayout']:,} (design {rep['pillars_design']:,}), "
             f"per atom {'equal' if not any('per-atom' in p for p in rep['problems']) else 'DIFFERENT'} "
             f"(read {rep['read_seconds']:.1f} s)",
             f"  exact read-back of {len(rep['sampled_tiles'])} tiles drawn with seed {rep['seed']}: "
             f"{rep['sampled_pillars']:,} pillars ({100 * rep['sampled_fraction']:.2f} % of the device), "
             f"{rep['mismatched_cells']} cells differ",
             f"  design rules (min feature {rules.min_feature_nm} nm, min gap {rules.min_gap_nm} nm): atom table min "
             f"feature {d['from_atom_table']['min_feature_nm']} nm; KLayout on a {rules.window_cells}x"
             f"{rules.window_cells} window of each sampled tile: {viol} violations -> "
             f"{'pass' if d['passed'] else 'FAIL'}"]
    lines += [f"    - {p}" for p in rep["problems"]]
    return "\n".join(lines)


def _text_stream(r) -> str:
    """The text report of the stream method (every pillar, record, signature and neighbour pair)."""
    rep, d, rules = r.details, r.drc, r.rules
    sig = rep["signature"]
    lines = [f"verify {r.file}: {'PASS' if r.passed else 'FAIL'} (streamed: {rep['bytes'] / 1e6:,.1f} MB in "
             f"{rep['seconds']:.1f} s on {rep['workers']} worker{'s' if rep['workers'] > 1 else ''})",
             f"  every pillar against the design: {rep['pillars']:,} (design {rep['pillars_design']:,}) in "
             f"{rep['tiles']:,} tiles; {rep['mismatched_cells']} cells differ, {rep['duplicates']} duplicates, "
             f"{rep['off_lattice']} off the lattice",
             f"  file: records well-formed {'yes' if not any('malformed' in p for p in rep['problems']) else 'NO'}, "
             f"{sig['scheme'] or 'no'} signature {'matches' if sig['ok'] else 'DOES NOT MATCH' if sig['ok'] is False else '-'}",
             f"  design rules (min feature {rules.min_feature_nm} nm, min gap {rules.min_gap_nm} nm) on every placed "
             f"pillar and each of {d['pairs_checked']:,} neighbour pairs: min feature {d['min_feature_nm']} nm, min "
             f"gap {d['min_gap_nm']} nm; {d['width_violations']} width, {d['space_violations']} space violations -> "
             f"{'pass' if d['passed'] else 'FAIL'}"]
    lines += [f"    - {p}" for p in rep["problems"]]
    return "\n".join(lines)


def _text_readback(r) -> str:
    """The text report of the read-back method (gdstk, and KLayout when asked)."""
    rep, rules = r.details, r.rules
    g = rep["gdstk"]
    lines = [f"verify {r.file}: {'PASS' if r.passed else 'FAIL'}",
             f"  gdstk read-back: {g['pillars']:,} pillars, exact {g['exact']} ({g['read_seconds']:.1f} s)"
             + "".join(f"\n    - {p}" for p in g["problems"])]
    if "klayout" in rep:
        k = rep["klayout"]
        lines.append(f"  KLayout read-back: {k['pillars']:,} pillars, exact {k['exact']}, per-atom counts "
                     f"{'agree' if k['counts_per_atom'] == g['counts_per_atom'] else 'DIFFER'} "
                     f"({k['read_seconds']:.1f} s)" + "".join(f"\n    - {p}" for p in k["problems"]))
    t, w = r.drc["from_atom_table"], r.drc["geometric_window"]
    lines.append(f"  design rules (min feature {rules.min_feature_nm} nm, min gap {rules.min_gap_nm} nm): atom "
                 f"table min feature {t['min_feature_nm']} nm, min gap x {t['min_gap_x_nm']} / y {t['min_gap_y_nm']} "
                 f"nm; KLayout window {w['window_cells']}x{w['window_cells']} cells: {w['width_violations']} width, "
                 f"{w['space_violations']} space violations -> {'pass' if r.drc['passed'] else 'FAIL'}")
    return "\n".join(lines)


def _rules(a: argparse.Namespace) -> DesignRules:
    """The design rules of ``layout verify``'s options."""
    return DesignRules(a.min_feature_nm, a.min_gap_nm, a.drc_window_cells)


#: the progress bar of each method that reports progress
_VERIFY_BARS = {"stream": ("verify: stripes of tiles", "stripe"), "tiled": ("verify: design stripes", "row")}


def _cmd_verify(a: argparse.Namespace) -> int:
    from .verification import VerifyOptions, choose_method, verify

    path = Path(a.layout)
    method = "stream" if a.stream else "tiled" if a.sample_tiles is not None else "readback" if a.all else "auto"
    options = VerifyOptions(a.sample_tiles, a.seed, a.tile, a.klayout)
    choice = choose_method(path, method, options)  # one-line errors for a bad path, before any work
    bar = _VERIFY_BARS.get(choice.method)
    run = Execution(workers=a.workers, scheduler=a.scheduler,
                    progress=progress_bar(*bar) if bar and not a.json else None,
                    log=(lambda line: None) if a.json else (lambda line: print(line, flush=True)))
    rep = verify(path, a.design, choice, _rules(a), options, run)
    text = {"readback": _text_readback, "tiled": _text_tiled, "stream": _text_stream}[rep.method](rep)
    emit(rep.to_dict(), a.json, text)
    return 0 if rep.passed else 1


def _options(a: argparse.Namespace):
    from . import LayoutOptions

    return LayoutOptions(layer=a.layer, datatype=a.datatype, grid_nm=a.grid_nm,
                         outline_layer=None if a.no_outline else a.outline_layer,
                         label_layer=a.label_layer, label=a.label)


def _cmd_tiled(a: argparse.Namespace) -> int:
    from ..design.recipe import load_design_recipe
    from .tiled import build_tiled, tiled_need

    recipe = load_design_recipe(a.recipe)
    out = out_dir(a.output) if a.output else out_dir(recipe.default_output())
    opts = _options(a)
    with product(out, "design", {"recipe": a.recipe, "design.library": recipe.library_path},
                 need=tiled_need(recipe, a.tile, a.workers)):
        run = Execution(workers=a.workers, scheduler=a.scheduler,
                        progress=None if a.json else progress_bar("tiled design + layout", unit="row"))
        rep = build_tiled(recipe, out, a.tile, a.hierarchy, opts, run)
    m = rep["metrics"]
    emit(rep, a.json, "\n".join([
        f"wrote {rep['design']} and {rep['file']}: {rep['pillars']:,} pillars in {rep['tiles']:,} tiles of "
        f"{rep['tile_cells']} x {rep['tile_cells']} cells ({rep['hierarchy']}), {rep['bytes'] / 1e6:.1f} MB, "
        f"{rep['seconds']:.1f} s ({rep['pillars_per_second'] / 1e6:.2f} M pillars/s)",
        f"  phase RMSE x-pol {m['rmse_rad'][0]:.4f}  y-pol {m['rmse_rad'][1]:.4f} rad; mean T0 "
        f"{m['mean_T0'][0]:.4f} / {m['mean_T0'][1]:.4f}; {m['n_atoms_used']} of {m['n_atoms']} atoms used",
        f"  check it: metadesign layout verify {rep['file']} (KLayout count of every pillar, sampled tiles)"]))
    return 0


def _cmd_preview(a: argparse.Namespace) -> int:
    from . import read_layout
    from .preview import preview_layout

    path = Path(a.layout)
    if a.window and not 1 <= a.window[2] <= MAX_PREVIEW_CELLS:
        raise InputError(f"--window: CELLS expected an integer in [1, {MAX_PREVIEW_CELLS}], got {a.window[2]}")
    out = out_file(Path(a.output) if a.output else path.with_name(path.stem + "-preview.png"), suffixes=(".png",))
    lc = read_layout(path)
    n = lc.index_map.shape[0]
    if a.window and (a.window[0] >= n or a.window[1] >= n):
        raise InputError(f"--window: IX0 and IY0 must be < {n} (cells per side of this layout), got "
                         f"{a.window[0]} {a.window[1]}")
    with product(out, "figure", {"layout": path}):
        preview_layout(lc, out, tuple(a.window) if a.window else None)
    print(f"wrote {out}")
    return 0


def _layout_option_args(p) -> None:
    """The layer, snapping, outline and label options of every layout writer (see :func:`_options`)."""
    p.add_argument("--layer", type=integer(0, 65535), default=1, help="pillar layer (default 1)")
    p.add_argument("--datatype", type=integer(0, 65535), default=0, help="pillar datatype (default 0)")
    p.add_argument("--grid-nm", type=integer(1, 100), default=1, help="width snapping grid in nm (default 1)")
    p.add_argument("--outline-layer", type=integer(0, 65535), default=10, help="aperture outline layer (default 10)")
    p.add_argument("--no-outline", action="store_true", help="no aperture outline")
    p.add_argument("--label-layer", type=integer(0, 65535), default=11, help="text/provenance layer (default 11)")
    p.add_argument("--label", help="label text written beside the aperture (default: the design name)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def register(sub) -> None:
    lay = sub.add_parser(
        "layout", help="stage 3: layout write DESIGN | layout verify LAYOUT | layout preview LAYOUT",
        description="Stage 3. `layout write DESIGN` (or `layout DESIGN`) writes the design as OASIS (default) "
        "and/or GDS with gdstk (one cell per atom, one repetition per atom; 1 nm database unit), with provenance "
        "in the file and a JSON side-car. `layout verify LAYOUT` reads every pillar back and compares it exactly "
        "with the design (add --klayout for KLayout's independent reader), and runs the design-rule checks. "
        "`layout preview LAYOUT` renders a pillar window and a thumbnail.")
    lsub = lay.add_subparsers(dest="layout_command", metavar="ACTION")
    lsub.required = True
    w = lsub.add_parser("write", help="write the OASIS/GDS layout of a design")
    w.add_argument("design", help="design folder or design.npz")
    w.add_argument("-o", "--output", help="layout path without suffix (default DESIGN/layout)")
    w.add_argument("--format", default="oas", choices=["oas", "gds", "both"], help="oas (default), gds or both")
    _layout_option_args(w)
    w.set_defaults(func=_cmd_write)

    t = lsub.add_parser(
        "tiled", help="design + OASIS layout in one streamed pass, tile by tile (centimetre apertures)",
        description="Design RECIPE and write OUT/design.npz and OUT/layout.oas in one pass over stripes of "
        "TILE rows, so memory is set by the tile, not the aperture (a 2.5 cm, 1.28e9-pillar device in a few GB). "
        "The design file has the same bytes as `design build`'s; the layout holds, per tile, one placement per "
        "atom with a lattice repetition. Stripes run on -j local workers or a Dask --scheduler; the bytes do "
        "not depend on either.")
    t.add_argument("recipe", help="design recipe (TOML), e.g. layouts/wide-25mm.toml")
    t.add_argument("-o", "--output", help="output folder (default: a folder named after the recipe, beside it)")
    t.add_argument("--tile", type=integer(16, 1 << 20), default=1024,
                   help="tile side in cells, a multiple of the recipe's tile_rows (default 1024)")
    t.add_argument("--hierarchy", choices=("tiles", "flat"), default="tiles",
                   help="tiles: one cell per tile placed by the top cell (default); flat: all in the top cell")
    workers_arg(t)
    t.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786) instead of local workers")
    _layout_option_args(t)
    t.set_defaults(func=_cmd_tiled)

    v = lsub.add_parser("verify", help="read every pillar back, compare with the design, design rules")
    v.add_argument("layout", help="layout file (.oas/.gds)")
    v.add_argument("--design", help="the design to compare with (default: design.npz beside the layout)")
    v.add_argument("--klayout", action="store_true", help="also read the file with KLayout and compare")
    v.add_argument("--min-feature-nm", type=integer(1, 100000), default=DESIGN_RULES.min_feature_nm,
                   help=f"minimum pillar width rule ({DESIGN_RULES.min_feature_nm})")
    v.add_argument("--min-gap-nm", type=integer(1, 100000), default=DESIGN_RULES.min_gap_nm,
                   help=f"minimum gap rule ({DESIGN_RULES.min_gap_nm})")
    v.add_argument("--drc-window-cells", type=integer(2, 4096), default=64,
                   help="geometric DRC window in cells per side, 2..4096 (default 64)")
    v.add_argument("--sample-tiles", type=integer(0, 10**6),
                   help="tiled layouts: KLayout counts every pillar, and this many tiles (seeded) are compared "
                   "pillar by pillar (default 8; the default mode for a tiled layout)")
    v.add_argument("--seed", type=integer(0, 2**31 - 1), default=0, help="seed of the sampled tiles (0)")
    v.add_argument("--stream", action="store_true",
                   help="tiled layouts: read the file once in bounded memory (no KLayout): every pillar compared "
                   "with the design, every record and the CRC checked, design rules on every neighbour pair")
    v.add_argument("--tile", type=integer(1, 10**7),
                   help="--stream: cells per tile side (default: the layout's side-car; checked against the file)")
    workers_arg(v, 1, "--stream: processes reading stripes of tiles")
    v.add_argument("--scheduler", help="--stream: a Dask scheduler (tcp://host:8786) instead of -j")
    v.add_argument("--all", action="store_true",
                   help="tiled layouts: read every pillar back with gdstk instead (memory: the whole layout)")
    v.add_argument("--json", action="store_true", help="print the report as JSON")
    v.set_defaults(func=_cmd_verify)

    p = lsub.add_parser("preview", help="render a pillar window and a thumbnail of the aperture")
    p.add_argument("layout", help="layout file (.oas/.gds)")
    p.add_argument("-o", "--output", help="preview PNG (default: beside the layout)")
    p.add_argument("--window", type=integer(0, 10**7), nargs=3, metavar=("IX0", "IY0", "CELLS"),
                   help=f"window of cells to draw (default: 16 x 16 at the centre; CELLS <= {MAX_PREVIEW_CELLS})")
    p.set_defaults(func=_cmd_preview)

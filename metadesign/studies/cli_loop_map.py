"""The ``loop-map`` command: the closed loop over loop rate (or latency) x Greenwood frequency x Rytov number,
each sensor's region, and the issue's verdict (issue #50, section 4)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..cliutil import emit, log_to, out_dir, progress_bar, workers_arg
from ..execution import Execution, scratch_path
from ..outputs import product
from .cli_loop import loop_inputs

__all__ = ["register"]


def _summary(rep: dict, out: Path, name: str) -> str:
    from .loop_map import LETTERS  # one letter per method
    from .loop_study import LABELS

    mp, axis = rep["map"], rep["axis"]
    xs = mp["rates_hz"] if axis == "rate_hz" else mp["latency_ms"]
    unit = "Hz" if axis == "rate_hz" else "ms"
    methods = rep["loop"]["methods"]
    lines = [f"loop map {name} -> {out}: {'rate' if axis == 'rate_hz' else 'latency'} "
             f"{', '.join(format(x, 'g') for x in xs)} {unit} x f_G {', '.join(format(g, 'g') for g in mp['greenwood_hz'])}"
             f" Hz (plane wave) x Rytov {', '.join(format(r, 'g') for r in mp['rytov'])}; {mp['steps']} steps x "
             f"{rep['loop']['seeds']} seed(s) per run"]
    c = rep["criterion"]
    lines.append(f"  region: mean NPiB >= {c['npib_vs_ideal']:g} x the ideal loop's and P(fade {c['threshold_db']:g} "
                 f"dB) <= {c['fade_probability']:g}; " + ", ".join(f"{LETTERS[m]} {LABELS[m]}" for m in methods))
    for ry in mp["rytov"]:
        pts = {(p["greenwood_hz"], p[axis]): p for p in rep["points"] if p["rytov"] == ry}
        lines.append(f"  Rytov {ry:g}   f_G \\ {unit:<3}" + "".join(f"{format(x, 'g'):>{len(methods) + 12}}" for x in xs))
        for g in mp["greenwood_hz"]:
            row = []
            for x in xs:
                p = pts[(g, x)]
                marks = "".join(LETTERS[m] if p["methods"][m]["in_region"] else "." for m in methods)
                best = p.get("best_metasurface")
                ratio = f"{p['methods'][best]['vs_ideal']:.2f}" if best else ""
                row.append(f"{marks} {ratio:>5}".rjust(len(methods) + 12))
            lines.append(f"  {'':<11}{format(g, 'g'):>6} Hz" + "".join(row))
    if any(p.get("best_metasurface") for p in rep["points"]):
        lines.append("  (each cell: the methods in their region, then the best metasurface loop's NPiB / the ideal's)")
    gain = rep.get("gain", {})
    if gain.get("rule") == "optimise":
        lines.append(f"  gains (optimised per point and closed loop: grid then refinement, {gain['steps']} steps of "
                     "the first seed a trial):")
        for p in rep["points"]:
            where = f"Rytov {p['rytov']:g}, f_G {p['greenwood_hz']:g} Hz, {format(p[axis], 'g')} {unit}"
            lines.append(f"    {where:<34}" + "  ".join(f"{LETTERS[m]} {p['methods'][m]['gain']:.3f}" for m in methods
                                                   if p["methods"][m].get("gain") is not None))
    if rep["loop"].get("sh_lenslets") == "auto" and rep.get("shack_hartmann"):
        lines.append("  Shack-Hartmann lenslets (auto, ceil(D / r0) per Rytov number): " + ", ".join(
            f"Rytov {s['rytov']:g}: {s['lenslets']} (d/r0 {s['d_over_r0']:.2f})" for s in rep["shack_hartmann"]))
    lines.append("  " + rep["verdict"]["statement"])
    lines.append(f"  figures: {', '.join(Path(p).name for p in rep['figures'])}")
    return "\n".join(lines)


def _cmd_loop_map(a: argparse.Namespace) -> int:
    from ..paths import recipe_path
    from .loop_map import load_map_recipe, run_loop_map

    path = recipe_path(a.recipe, "sensing")  # a path, or a packaged recipe's name: `loop-map loop-map`
    mrec = load_map_recipe(path)
    rec = mrec.loop
    out = out_dir(a.output or Path.cwd() / f"{path.stem}-out")
    inputs = loop_inputs(path, rec)
    run = Execution(workers=a.workers, scheduler=a.scheduler, log=log_to(a.json),
                    progress=None if a.json else progress_bar("loop map", unit="step"))
    with product(out, "loop-map", inputs, scratch=(scratch_path(out),)):
        rep = run_loop_map(mrec, out, run)
    emit(rep, a.json, _summary(rep, out, mrec.name))
    return 0


def register(sub, groups: dict) -> None:
    p = sub.add_parser(
        "loop-map", help="the closed loop over rate (or latency) x f_G x Rytov: each sensor's region, the verdict",
        description="Runs every method of a loop recipe with a [map] section at each point of a grid of loop rates "
        "(rates_hz) or declared latencies of the metasurface loops (latency_ms), target plane-wave Greenwood "
        "frequencies (greenwood_hz: the recipe's wind scaled to each) and Rytov numbers (rytov), and reports per "
        "point and method the mean NPiB, the fade probability at [loop] threshold_db and the NPiB relative to the "
        "ideal-phase loop; each method's region (NPiB >= 0.8 x the ideal loop's, P(fade) <= 1e-2); and the "
        "verdict at Rytov 0.5, f_G 100 Hz, 2 kHz with the measured latencies (the best metasurface loop against "
        "the ideal-phase and Shack-Hartmann loops, and the largest latency that would meet each goal, from a "
        "scan of declared latencies). [loop] gain = \"optimise\": each closed loop's gain chosen at each point by "
        "the loop study's search (a grid, then a refinement, on the first gain_steps frames of the first seed), "
        "recorded per point and written in the figure; sh_lenslets = \"auto\": the Shack-Hartmann's count "
        "ceil(D / r0) at each Rytov number. Every run is one task of one set on -j local workers or a Dask "
        "--scheduler, kept in OUT.partial as it finishes (a killed map resumes; the bytes do not depend on the worker "
        "count). Writes OUT/map.json and OUT/map.png.")
    p.add_argument("recipe", help="loop-map recipe (TOML), or a packaged one's name (loop-map)")
    p.add_argument("-o", "--output", help="output folder (default: RECIPE-out in the working directory)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    workers_arg(p, 1)
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler address (tcp://host:8786) instead of local workers")
    p.set_defaults(func=_cmd_loop_map)

"""The ``loop`` command: the sensor in a closed adaptive-optics loop over moving turbulence (issue #50)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..cliutil import emit, log_to, out_dir, progress_bar, workers_arg
from ..execution import Execution, scratch_path
from ..outputs import product

#: the steps a fade probability of 1e-3 needs (100 frames in a fade at that probability; issue #50)
FADE_STEPS = 100_000

__all__ = ["register", "loop_inputs"]


def loop_inputs(path: Path, rec) -> dict:
    """The files a loop study (or a map of them) reads: the product layer's declared inputs."""
    return {"recipe": path, "design": rec.design, "sensor": rec.sensor, "turbulence": rec.turbulence,
            "model": rec.model, "realtime": rec.realtime, "influence": rec.influence}


def _cmd_loop(a: argparse.Namespace) -> int:
    from ..paths import recipe_path
    from .loop_recipe import load_loop_recipe
    from .loop_study import LABELS, run_loop_study

    path = recipe_path(a.recipe, "sensing")  # a path, or a packaged recipe's name: `loop loop-demo`
    rec = load_loop_recipe(path)
    out = out_dir(a.output or Path.cwd() / f"{path.stem}-out")
    inputs = loop_inputs(path, rec)
    run = Execution(workers=a.workers, scheduler=a.scheduler, log=log_to(a.json),
                    progress=None if a.json else progress_bar("loop", unit="step"))
    with product(out, "loop", inputs, scratch=(scratch_path(out),)):
        rep = run_loop_study(rec, out, run)
    v = rep["verdict"]
    lines = [f"loop {rec.name} -> {out}: {rep['loop']['rate_hz']:g} Hz, Rytov {rep['turbulence']['rytov']:g}, "
             f"f_G {rep['turbulence']['greenwood_hz']:.0f} Hz"]
    if v.get("best_metasurface"):
        parts = [f"best metasurface loop: {LABELS[v['best_metasurface']]}"]
        if v.get("vs_ideal") is not None:
            parts.append(f"{v['vs_ideal']:.2f} of the ideal-phase loop")
        if v.get("vs_shack_hartmann") is not None:
            parts.append(f"{v['vs_shack_hartmann']:.2f}x the Shack-Hartmann loop")
        lines.append("  " + ", ".join(parts))
    th = rep["loop"]["threshold_db"]
    lines.append(f"  {'method':<34} {'NPiB':>6} {'P(fade ' + format(th, 'g') + ' dB)':>16} {'fades/s':>8} "
                 f"{'delay':>6} {'latency ms':>10} {'gain':>6}")
    for m, r in rep["methods"].items():
        f = r["fades"]
        gain = format(r["gain"], "6.3f") if "gain" in r else format("", "6")
        lines.append(f"  {r['label']:<34} {r['npib_mean']:6.3f} {f['probability']:16.3g} {f['fades_per_s']:8.1f} "
                     f"{r['delay_frames']:6.2f} {r['latency_ms']:10.2f} {gain}")
    if "gain_search" in rep:
        lines.append(f"  gain search: {rep['gain_search']['objective']} (grid 0.1..0.9, then +-0.075 around its best)")
        for m, r in rep["methods"].items():
            if "gain_search" in r:
                g = r["gain_search"]
                trials = " ".join(f"{x:g}:{v:.3f}" for x, v in zip(g["gains"], g["npib_mean"]))
                lines.append(f"    {r['label']:<32} {g['gain']:.3f}  [{trials}]")
    cost = {r["label"]: r["core_s_per_link_s"] for r in rep["methods"].values() if "core_s_per_link_s" in r}
    if cost:
        total = sum(cost.values())
        lines.append(f"  cost per second of link time (core-s): {', '.join(f'{k} {v:.0f}' for k, v in cost.items())}; "
                     f"{FADE_STEPS:,} steps of every method (fades to 1e-3): "
                     f"{total * FADE_STEPS / rep['loop']['rate_hz'] / 3600:.1f} core-h")
    if rep["loop"]["seeds"] > 1:
        lines.append(f"  pooled over {rep['loop']['seeds']} seeds x {rep['loop']['steps']} steps")
    lines.append(f"  figures: {', '.join(Path(p).name for p in rep['figures'])}")
    emit(rep, a.json, "\n".join(lines))
    return 0


def register(sub, groups: dict) -> None:
    p = sub.add_parser(
        "loop", help="the sensor in a closed AO loop over moving turbulence: PiB in time, fades, rejection",
        description="Runs every method of a loop recipe (the metasurface sensor with its reconstructions, a "
        "Shack-Hartmann, the ideal phase sensor; the references: the zero-delay DM-fitted oracle, the phase "
        "conjugate, the open loop) on the same frozen-flow turbulence at the recipe's rate, with each method's "
        "delay (its reconstruction's latency measured on this machine unless declared), and reports the power in "
        "the bucket in time, its CDF and fades, the modal spectra and the measured rejection against theory, "
        "pooled over the recipe's seeds. Each run (one seed x one method) is a task on -j local workers or a Dask "
        "--scheduler, kept in OUT.partial as it finishes (a killed run resumes; the bytes do not depend on the "
        "worker count). Writes OUT/loop.json and OUT/loop.png.")
    p.add_argument("recipe", help="loop recipe (TOML), or a packaged one's name (loop-demo)")
    p.add_argument("-o", "--output", help="output folder (default: RECIPE-out in the working directory)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    workers_arg(p, 1)
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler address (tcp://host:8786) instead of local workers")
    p.set_defaults(func=_cmd_loop)

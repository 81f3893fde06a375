"""The ``polcam`` command: which polarisation camera to buy (issue #52)."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from ..cliutil import emit, integer, limit_arg, log_to, out_dir, progress_bar
from ..outputs import product, zarr_input

__all__ = ["register"]


def _lines(summ: dict, out: Path, files) -> list[str]:
    nets = summ["networks"]
    names = {"unet": "U-Net", "refine": "refined"}
    retrained = (f"the model trained on {Path(summ['retraining']['trained_on']).name}" if summ["retraining"]["run"]
                 else "no retraining")
    lines = [(f"polcam {summ['name']}: {summ['n']} {summ['split']} samples, {summ['noise_percent']:g} % noise, "
              f"{retrained} ({summ['seconds']:.0f} s) -> {out}"),
             f"  {'camera':<44} {'frames':>8} " + " ".join(f"{names.get(k, k) + ' CF':>11} {'delta':>7}" for k in nets)]
    for c in summ["cameras"].values():
        lines.append(f"  {c['label'][:44]:<44} {c['frame_pitch_um']:6.3g}um " + " ".join(
            f"{c[k]['captured_fraction']:11.3f} {c[k]['delta_vs_ideal']:+7.3f}" for k in nets))
    lines.append(f"  the ideal camera's row is the dataset's tensors; the beacons re-rendered match them to "
                 f"{summ['ideal_render_check']:.1e} of the peak")
    lines.append(f"  buy: {summ['verdict']['text']}")
    if not summ["retraining"]["run"]:
        lines.append("  retraining on the camera's frames: " + summ["retraining"]["why"])
    lines.append(f"  files: {', '.join(Path(f).name for f in files)}")
    return lines


def _cmd_polcam(a: argparse.Namespace) -> int:
    from ..paths import recipe_path
    from .polcam import load_polcam_recipe, run_polcam, summarise, write_polcam

    path = recipe_path(a.recipe, "sensing")  # a path, or a packaged recipe's name: `polcam polcam-demo`
    rec = load_polcam_recipe(path)
    if a.samples is not None:
        rec = replace(rec, limit=a.samples)
    if a.model is not None:
        rec = replace(rec, model=Path(a.model))
    out = out_dir(a.output or Path.cwd() / f"{path.stem}")
    log = log_to(a.json)
    with product(out, "polcam", {"recipe": path, "dataset": zarr_input(rec.dataset), "model": rec.model}):
        res = run_polcam(rec, progress=None if a.json else progress_bar("polcam", unit="sample"), log=log)
        summ = summarise(res)
        files = write_polcam(summ, out)
    emit(summ | {"files": [str(f) for f in files]}, a.json, "\n".join(_lines(summ, out, files)))
    return 0


def register(sub, groups: dict) -> None:
    p = sub.add_parser(
        "polcam", help="which polarisation camera to buy: captured fraction vs extinction ratio and mosaic pitch",
        description="Renders the samples of a dataset split through division-of-focal-plane polarisation cameras "
        "(a 2 x 2 micro-polariser mosaic, metadesign.sensing.mosaic: the recipe's grid of extinction ratios x "
        "mosaic pitches and its variants), with the evaluation's sensor noise, and scores the model (a refiner: its "
        "U-Net and its refinement) without retraining against the ideal camera (the dataset's own frames). Writes "
        "OUT/polcam.json and OUT/polcam.png; says which camera keeps the captured fraction within the recipe's "
        "tolerance of the ideal camera.")
    p.add_argument("recipe", help="polcam recipe (TOML), or a packaged one's name (polcam-demo)")
    p.add_argument("-o", "--output", help="output folder (default: RECIPE's name in the working directory)")
    limit_arg(p, "at most this many samples of the split (default: the recipe's limit)", type=integer(1, 10**8))
    p.add_argument("--model", help="a U-Net or refiner in place of the recipe's (e.g. one retrained on the "
                                   "camera's frames)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_cmd_polcam)

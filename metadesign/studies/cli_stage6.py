"""The stage-6 study commands: ``transfer``, ``tolerance``, ``table-s2``, ``codesign`` and
``dataset synth-captures``."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from ..cliutil import emit, integer, limit_arg, log_to, num, out_dir, out_file, progress_bar, workers_arg
from ..outputs import path_fields, product, zarr_input

__all__ = ["register"]


def _cmd_table_s2(a: argparse.Namespace) -> int:
    from .table_s2 import run_table_s2

    out = out_dir(a.output or Path(a.recipe).with_suffix("").with_name(Path(a.recipe).stem + "-out"))
    with product(out, "table-s2", {"recipe": a.recipe}):
        rep = run_table_s2(a.recipe, out, workers=a.workers, log=log_to(a.json))
    lines = [f"Table S2 ({rep['samples']} samples at Rytov {rep['rytov']}, {rep['epochs']} epochs) -> {out}",
             "  model split  PiB ratio (mean of NPiB_unet / NPiB_pc)  ratio of means   NPiB U-Net / none / conjugate"]
    for r in rep["rows"]:
        lines.append(f"  {r['model']:<5} {r['split']:<5}  {100 * r['pib_ratio']:6.1f} %                        "
                     f"{100 * r['pib_ratio_of_means']:6.1f} %          {r['npib_unet']:.3f} / {r['npib_none']:.3f} / "
                     f"{r['npib_phase_conjugate']:.3f}")
    lines.append("  paper: E2E 96.3 % / 96.0 %, MSE 94.6 % / 71.5 % (train / test)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_tolerance(a: argparse.Namespace) -> int:
    from .tolerance import load_tolerance_recipe, run_tolerance

    rec = load_tolerance_recipe(a.recipe)
    out = out_dir(a.output or Path(a.recipe).with_suffix("").with_name(Path(a.recipe).stem + "-out"))
    with product(out, "tolerance", {"recipe": a.recipe, **path_fields(rec)}):
        rep = run_tolerance(rec, out, workers=a.workers, log=log_to(a.json))
    lines = [f"fab tolerance of {rec.model.name} at {rep['noise_percent']:g} % noise -> {out} ({Path(rep['figure']).name})",
             "  case              NPiB U-Net  captured  gain(median) | fine-tuned U-Net  captured | conjugate  none"]
    for r in rep["rows"]:
        b, f = r["before"], r.get("after")
        lines.append(f"  {r['case']:<16}  {b['npib_unet']:.3f}       {b['captured_fraction']:5.2f}     "
                     f"{b['gain_median']:6.1f}     | " + (f"{f['npib_unet']:.3f}             {f['captured_fraction']:5.2f}"
                                                           if f else "  -                  -  ")
                     + f"     | {b['npib_phase_conjugate']:.3f}      {b['npib_none']:.3f}")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_codesign(a: argparse.Namespace) -> int:
    from .codesign import FisherSettings, read_diversity, run_codesign_report

    read_diversity(a.run)  # a bad run is one line before anything is written
    out = out_dir(a.output)
    run_file = Path(a.run) / "diversity.json" if Path(a.run).is_dir() else Path(a.run)
    inputs = {"run": run_file, "--dataset": zarr_input(a.dataset), "--base": a.base}
    recipe = out_file(a.recipe, "--recipe", suffixes=(".toml",)) if a.recipe else None
    with product(out, "codesign", inputs), \
            (product(recipe, "design-recipe", {**inputs, "-o": out}) if recipe else contextlib.nullcontext()):
        fisher = FisherSettings(a.modes, a.fisher_samples, a.photons, a.read_noise_e, a.random)
        rep = run_codesign_report(a.run, a.dataset, a.base, out, fisher, recipe=recipe, log=log_to(a.json))
    m = rep["fisher"]["mean_crb_rad2"]
    lines = [f"co-designed sensor -> {out}: design recipe {Path(rep['design_recipe']).name}, "
             + ", ".join(Path(f).name for f in rep["figures"]),
             f"  mean Cramer-Rao bound over Noll 2..{1 + a.modes} at {a.photons:.0e} photons (rms rad): "
             + ", ".join(f"{k} {v ** 0.5:.3g}" for k, v in m.items())]
    emit(rep, a.json, "\n".join(lines))
    return 0


def _cmd_synth(a: argparse.Namespace) -> int:
    from ..sensing.camera import Alignment, CameraSpec
    from .captures import CaptureSession, synth_captures

    out = out_dir(a.output)
    al = Alignment(a.shift[0], a.shift[1], a.rotation_deg, a.scale)
    cam = CameraSpec(peak_counts=a.peak_counts, photons_at_peak=a.photons, read_noise_e=a.read_noise_e,
                     dark_counts=a.dark_counts, hot_pixels=a.hot_pixels, seed=a.seed)
    session = CaptureSession(samples=a.samples, split=a.split, fmt=a.format, saturate=a.saturate, seed=a.seed)
    rep = synth_captures(a.phases, a.device, out, al, cam, session, progress=progress_bar("captures", unit="frame"))
    emit(rep, a.json, f"wrote {out}: {rep['samples']} samples ({rep['format']}), {rep['flats']} flat and "
         f"{rep['darks']} dark captures, {rep['saturated']} over-exposed; manifest {out / 'manifest.csv'}")
    return 0


def _cmd_transfer(a: argparse.Namespace) -> int:
    from .transfer import load_transfer_recipe, run_transfer

    rec = load_transfer_recipe(a.recipe)
    out = out_dir(a.output or Path(a.recipe).with_name(Path(a.recipe).stem + "-out"))
    with product(out, "transfer", {"recipe": a.recipe, **path_fields(rec)}):
        rep = run_transfer(rec, out, workers=a.workers, log=log_to(a.json),
                           progress=None if a.json else progress_bar("captures", unit="frame"))
    r = rep["rows"]
    tr, fi = rep["truth_alignment"], rep["fitted_alignment"]
    lines = [f"transfer to captured frames -> {out} ({Path(rep['figure']).name}); relay true "
             f"({tr['shift_x_px']:+.2f}, {tr['shift_y_px']:+.2f}) px {tr['rotation_deg']:+.3f} deg x{tr['scale']:.4f}, "
             f"fitted ({fi['shift_x_px']:+.2f}, {fi['shift_y_px']:+.2f}) px {fi['rotation_deg']:+.3f} deg x{fi['scale']:.4f}",
             "  model                 NPiB mean  median  captured"]
    for k in ("unadapted", "scratch", "finetuned"):
        if k in r:
            lines.append(f"  {k:<20}  {r[k]['npib_unet']:.3f}      {r[k]['npib_unet_median']:.3f}   "
                         f"{r[k]['captured_fraction']:.2f}")
    lines.append(f"  uncorrected {r['unadapted']['npib_none']:.3f}, phase conjugate "
                 f"{r['unadapted']['npib_phase_conjugate']:.3f} ({r['unadapted']['n']} test captures)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _add_transfer(sub) -> None:
    tf = sub.add_parser(
        "transfer", help="stage 6: fab-to-lab transfer learning on (synthetic) captured frames",
        description="Render the lab device (the design as made) and SLM screens, synthesise camera captures "
        "through a misaligned relay, import them against the nominal dataset, and compare the synthetic model "
        "unadapted, fine-tuned from it (--init) and trained from scratch on the same captures.")
    tf.add_argument("recipe", help="transfer recipe (TOML), e.g. sensing/transfer-demo.toml")
    tf.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe)")
    workers_arg(tf)
    tf.add_argument("--json", action="store_true", help="print the summary as JSON")
    tf.set_defaults(func=_cmd_transfer)


def _add_tolerance(sub) -> None:
    tol = sub.add_parser(
        "tolerance", help="stage 6: reconstruction-level fab tolerance (NPiB vs bias/jitter/corner, fine-tune recovery)",
        description="For each fabrication case of the recipe (one-at-a-time sweeps of width bias, jitter and "
        "corner rounding around the nominal device): render a dataset through the perturbed layout (same "
        "turbulence samples in every case), evaluate the nominal model on its test split, fine-tune it on the "
        "case's small training split (train --init) and evaluate again. Resumable; writes OUT/tolerance.csv, "
        ".json and .png.")
    tol.add_argument("recipe", help="tolerance recipe (TOML), e.g. sensing/tolerance-demo.toml")
    tol.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe)")
    workers_arg(tol)
    tol.add_argument("--json", action="store_true", help="print the table as JSON")
    tol.set_defaults(func=_cmd_tolerance)


def _add_table_s2(sub) -> None:
    t2 = sub.add_parser("table-s2", help="stage 6: reproduce Table S2 (E2E vs MSE loss: train and test PiB ratio)",
                        description="Build the recipe's dataset, train the same U-Net with the end-to-end PiB loss "
                        "and with the MSE phase loss, and evaluate both on their train and test splits.")
    t2.add_argument("recipe", help="Table S2 recipe (TOML), e.g. sensing/table-s2.toml")
    t2.add_argument("-o", "--output", help="output folder (default: RECIPE-out beside the recipe)")
    workers_arg(t2)
    t2.add_argument("--json", action="store_true", help="print the table as JSON")
    t2.set_defaults(func=_cmd_table_s2)


def _add_codesign(sub) -> None:
    cd = sub.add_parser(
        "codesign", help="stage 6: the co-designed sensor as a device recipe, its diversity and Fisher information",
        description="From a co-design run (metadesign train with a [codesign] section: diversity.json beside "
        "the U-Net): the design recipe of the device with the learned diversity (OUT/design.toml: --base with "
        "each lens's learned focal length and Zernike terms; build, lay out and simulate it like any design), "
        "the diversity and the PSFs of a flat wavefront beside the paper's (diversity.png), and the Cramer-Rao "
        "bounds of the first Zernike modes for the paper's, the learned and random diversities (fisher.png, "
        "codesign.json).")
    cd.add_argument("run", help="co-design training run folder (or its diversity.json)")
    cd.add_argument("--dataset", required=True, help="the dataset it was trained on (its device and received fields)")
    cd.add_argument("--base", required=True, help="the base design recipe (TOML), e.g. layouts/paper-5mm.toml")
    cd.add_argument("--modes", type=integer(1, 64), default=20, help="Zernike modes Noll 2..N+1 (default 20)")
    cd.add_argument("--fisher-samples", type=integer(0, 1000), default=4,
                    help="received fields of the test split the information is averaged over, besides a flat one")
    cd.add_argument("--photons", type=num(1.0, 1e15), default=1e6, help="photo-electrons per frame (default 1e6)")
    cd.add_argument("--read-noise-e", type=num(0.0, 1e6), default=0.0, help="read noise per pixel (e-)")
    cd.add_argument("--random", type=integer(0, 100), default=2, help="random diversities to compare (default 2)")
    cd.add_argument("-o", "--output", required=True, help="output folder")
    cd.add_argument("--recipe", help="also write the design recipe here (e.g. layouts/codesign-demo.toml: its "
                    "library named relative to it, ready to commit beside the other design recipes)")
    cd.add_argument("--json", action="store_true", help="print the summary as JSON")
    cd.set_defaults(func=_cmd_codesign)


def _add_synth_captures(sub) -> None:
    sy = sub.add_parser(
        "synth-captures", help="synthetic camera captures from a dataset's phases through a (perturbed) device",
        description="The SLM shows the received phases of PHASES' samples; frames are rendered through DEVICE's "
        "coarse pupil onto a misaligned camera with shot and read noise, dark offset and hot pixels (16-bit PNG, "
        "TIFF or .npy), with flat and dark captures and a manifest: input for `dataset import`.")
    sy.add_argument("phases", help="dataset whose received phases the SLM shows (also the sensor geometry)")
    sy.add_argument("--device", required=True, help="dataset of the device to render (older datasets: or their device-pupil.npz)")
    sy.add_argument("-o", "--output", required=True, help="capture folder to write")
    sy.add_argument("--split", choices=("train", "val", "test", "all"), default="all", help="samples of PHASES")
    limit_arg(sy, "at most this many samples of the split", type=integer(1, 10_000_000))
    sy.add_argument("--shift", nargs=2, type=num(-200, 200), default=(0.0, 0.0), metavar=("DX", "DY"),
                    help="relay shift, camera pixels")
    sy.add_argument("--rotation-deg", type=num(-10, 10), default=0.0)
    sy.add_argument("--scale", type=num(0.8, 1.25), default=1.0, help="relay magnification / nominal")
    sy.add_argument("--format", choices=("png", "tiff", "fits", "npy"), default="png")
    sy.add_argument("--peak-counts", type=num(1, 65535), default=40000.0)
    sy.add_argument("--photons", type=num(0, 1e9), default=20000.0, help="photo-electrons at the peak (0: none)")
    sy.add_argument("--read-noise-e", type=num(0, 1e4), default=5.0)
    sy.add_argument("--dark-counts", type=num(0, 65535), default=100.0)
    sy.add_argument("--hot-pixels", type=integer(0, 100000), default=20)
    sy.add_argument("--saturate", type=integer(0, 10_000_000), default=0,
                    help="over-expose the last N samples (2x: clipped at full scale)")
    sy.add_argument("--seed", type=integer(0, 2**63 - 1), default=0)
    sy.add_argument("--json", action="store_true", help="print the report as JSON")
    sy.set_defaults(func=_cmd_synth)


def register(sub, groups: dict) -> None:
    """Add ``transfer``, ``tolerance``, ``table-s2`` and ``codesign`` to ``sub``, ``synth-captures`` to the ``dataset`` group."""
    _add_transfer(sub)
    _add_tolerance(sub)
    _add_table_s2(sub)
    _add_codesign(sub)
    _add_synth_captures(groups["dataset"])

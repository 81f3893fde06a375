"""The stage-6 commands: ``dataset build|operators|show|verify|plot|import``, ``train``, ``evaluate``,
``export``.  (The studies on top of stage 6, ``compare``, ``retrieve``, ``tolerance``, ``transfer``,
``table-s2`` and ``dataset synth-captures``, are :mod:`metadesign.studies.cli`.)"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..execution import Execution
from ..cliutil import emit, integer, limit_arg, log_to, num, out_dir, out_file, progress_bar, workers_arg
from ..outputs import product, zarr_input
from ..sensing.orientation import ORIENTATIONS

__all__ = ["register"]


def _cmd_build(a: argparse.Namespace) -> int:
    from .dataset_build import build_dataset
    from .dataset_recipe import load_dataset_recipe

    rec = load_dataset_recipe(a.recipe)
    if a.samples is not None:
        rec = rec.with_samples(a.samples)
    out = out_dir(a.output or rec.default_output())
    rep = build_dataset(rec, out, a.overwrite, Execution(workers=a.workers, scheduler=a.scheduler,
                                                         progress=progress_bar("dataset", unit="sample"),
                                                         log=log_to(a.json)))
    ps = rep["per_sample_seconds"]
    text = (f"wrote {out}: {rep['samples']} samples (8 x {rep['tensor'][1]}^2), split "
            + "/".join(str(v) for v in rep["split_counts"].values())
            + f", {rep['bytes_per_sample'] / 1e3:.1f} kB per sample on disk; {rep['computed_samples']} computed "
            f"({rep['resumed_shards']} shards resumed) in {rep['sweep_seconds']:.1f} s on "
            f"{rep['workers']} worker(s)")
    if ps:
        text += "\n  per sample: " + ", ".join(f"{k} {1e3 * v:.1f} ms" for k, v in ps.items())
    emit(rep, a.json, text)
    return 0


def _cmd_operators(a: argparse.Namespace) -> int:
    from .operators import build_operators

    rep = build_operators(a.dataset, a.splits, a.overwrite, Execution(workers=a.workers, scheduler=a.scheduler,
                                                                       progress=progress_bar("operators", unit="sample"),
                                                                       log=log_to(a.json)))
    text = (f"{rep['output']}: bucket operators of {'/'.join(rep['splits'])} ({rep['samples']} samples, "
            f"{rep['bucket_pixels']} x {rep['aperture_pixels']} complex64, {rep['bytes_per_operator'] / 1e3:.0f} kB "
            f"each, {rep['bytes_on_disk'] / 1e9:.2f} GB on disk); {rep['computed_samples']} computed "
            f"({rep['resumed_shards']} shards resumed) in {rep['seconds']:.1f} s on {rep['workers']} worker(s)")
    if rep["per_sample_seconds"]:
        text += f", {1e3 * rep['per_sample_seconds']['operator']:.0f} ms per sample per worker"
    emit(rep, a.json, text)
    return 0


def _crop_line(info) -> str:
    c0, a = info.crop()
    try:
        sc = info.scenario()
        return (f"received crop  {a} x {a} samples of the {sc.n_grid}^2 turbulence grid from index {c0} "
                f"(pitch {sc.dx * 1e3:.4g} mm: {a * sc.dx * 1e3:.4g} mm square; receiver aperture "
                f"{sc.receiver_aperture * 1e3:.4g} mm)")
    except Exception:  # the summary of a damaged store still prints
        return f"received crop  {a} x {a} samples from index {c0}"


def _cmd_show(a: argparse.Namespace) -> int:
    from .dataset_store import open_dataset

    info = open_dataset(a.dataset)
    s = info.summary()
    at = info.attrs
    text = "\n".join([
        f"dataset        {at.get('name')} ({s['path']}), format {at.get('format')}, metadesign {s['version']}",
        f"samples        {s['samples']}: train {s['split_counts']['train']}, val {s['split_counts']['val']}, "
        f"test {s['split_counts']['test']}; tensor {' x '.join(map(str, s['tensor']))}",
        ("Rytov          unknown (captures imported without a rytov column)" if s["rytov_nominal"] is None else
         f"Rytov          nominal {s['rytov_nominal'][0]:.3f}..{s['rytov_nominal'][1]:.3f}, measured "
         f"{s['rytov_measured'][0]:.3f}..{s['rytov_measured'][1]:.3f} (mean {s['rytov_measured_mean']:.3f})"
         + (f"; unknown for {s['rytov_unknown']} samples" if s["rytov_unknown"] else "")),
        _crop_line(info),
        (f"device         layout {str(s['layout_sha256'])[:12]}, library {str(s['library_sha256'])[:12]}, "
         f"perturbation {at['provenance'].get('perturbation')}") if at.get("propagation") != "slm" else
        (f"captures       {at['provenance'].get('captures')} (propagation slm), relay "
         + ", ".join(f"{k} {v:+.3g}" for k, v in at['provenance'].get('calibration', {}).get('alignment', {}).items())
         + f"; {len(at['provenance'].get('saturated') or [])} saturated ({at['provenance'].get('saturated_policy')})"),
        f"storage        {s['bytes_on_disk'] / 1e6:.1f} MB, {s['bytes_per_sample'] / 1e3:.1f} kB per sample; "
        f"root seed {s['root_seed']}",
        "PiB operators  " + ("none (metadesign dataset operators DATASET adds them)" if not at.get("pib_operator") else
                             f"{'/'.join(at['pib_operator']['splits'])}, {at['pib_operator']['bucket_pixels']} x "
                             f"{at['pib_operator']['aperture_pixels']} each"
                             + ("" if at["pib_operator"].get("complete") else " (unfinished: rerun to complete)")),
    ])
    emit(s | {"attributes": at}, a.json, text)
    return 0


def _cmd_verify(a: argparse.Namespace) -> int:
    from .dataset_store import verify_dataset

    rep = verify_dataset(a.dataset, progress=None if a.json else progress_bar("verify", unit="sample"))
    bad = rep["damaged_shards"]
    lines = [f"{rep['path']}: {rep['samples']} samples in {rep['shards']} shards, arrays {', '.join(rep['arrays'])}: "
             + ("every sample reads back and checks out" if not bad else f"{len(bad)} damaged shard(s)")]
    lines += [f"  shard {b['shard']} (samples {b['samples'][0]}..{b['samples'][1]}): {b['problem']}" for b in bad]
    if bad:
        lines.append("  remedy: rebuild it (`metadesign dataset build RECIPE -o DIR --overwrite`: the same recipe gives "
                     "the same bytes), or restore it from a copy")
    emit(rep, a.json, "\n".join(lines))
    return 0 if rep["ok"] else 1


def _cmd_plot(a: argparse.Namespace) -> int:
    from .dataset_store import open_dataset
    from .plot import plot_dataset

    out = out_file(a.output or Path(a.dataset) / "fig-dataset.png", suffixes=(".png",))
    info = open_dataset(a.dataset)
    with product(out, "figure", {"dataset": zarr_input(a.dataset)}):
        plot_dataset(info, out, a.samples)
    print(f"wrote {out}")
    return 0


def _cmd_train(a: argparse.Namespace) -> int:
    import dataclasses
    import os

    from .train import load_train_recipe, train

    rec = load_train_recipe(a.recipe)
    run = Path(a.output) if a.output else Path(a.recipe).with_suffix("").parent / (rec.name + "-run")
    if not a.resume:
        out_dir(run)
    if a.init is not None and not Path(a.init).exists():
        from ..validation import ValidationError

        raise ValidationError(f"--init {a.init}: no such model")
    rank = int(os.environ.get("RANK", "0"))
    if a.max_steps is not None:
        rec = dataclasses.replace(rec, max_steps=a.max_steps)
    rep = train(rec, run, dataset=a.dataset, resume=a.resume, init=a.init, log=log_to(a.json or rank != 0),
                progress=not a.json)
    if rank == 0:
        h = rep["history"][-1] if rep["history"] else {}
        text = (f"trained {rep['run']}: {rep['epochs_done']} epochs on {rep['world_size']} process(es) ({rep['device']}); "
                f"best validation NPiB {rep['best_val_npib']:.3f}; last: U-Net {h.get('val_npib', float('nan')):.3f}, "
                f"uncorrected {h.get('val_npib_none', float('nan')):.3f}, phase conjugate "
                f"{h.get('val_npib_phase_conjugate', float('nan')):.3f}; model {rep['run']}/model.safetensors")
        emit(rep, a.json, text)
    return 0


def _cmd_evaluate(a: argparse.Namespace) -> int:
    import json as _json

    from ..io import atomic_write_text
    from .evaluate import evaluate_model, noise_levels_of, plot_fig3, summarise, write_results

    out = out_dir(a.output or Path(a.dataset) / "evaluation")
    from ..cliutil import json_safe

    with product(out, "evaluation", {"model": a.model, "dataset": zarr_input(a.dataset)}):
        res = evaluate_model(a.model, a.dataset, a.split, noise_levels_of(a.noise, a.photons), limit=a.limit,
                             progress=progress_bar("evaluate", unit="sample"))
        files = write_results(res, out)
        figs = plot_fig3(res, out)
        keys = list(res["rows"])
        summary = {"n": res["n"], "split": a.split, "noise": keys[0], **summarise(res["rows"][keys[0]])}
        if len(keys) > 1:
            summary["by_noise"] = {k: summarise(res["rows"][k]) for k in keys}
        summary["files"] = [str(f) for f in files + figs]
        atomic_write_text(out / "summary.json", _json.dumps(json_safe(summary), indent=2, sort_keys=True))
    s = summary
    net = "refined" if "start" in s else "U-Net"  # a refiner's rows: the refined estimate, and its U-Net alone
    lines = [f"evaluated {a.model} on {res['n']} {a.split} samples of {a.dataset} (noise {keys[0]}) -> {out}",
             "  mean NPiB: uncorrected {none:.3f}, {net} {unet:.3f}, phase conjugate {phase_conjugate:.3f}, "
             "complex conjugate {complex_conjugate:.3f}".format(net=net, **s["npib"])
             + (f"; its U-Net alone {s['start']['npib']:.3f} (captured {s['start']['captured_fraction']:.3f})"
                if "start" in s else ""),
             f"  captured fraction {s['captured_fraction']:.3f}; gain {net} / uncorrected: mean {s['gain']['mean']:.1f}x, "
             f"median {s['gain']['median']:.1f}x, ratio of means {s['gain']['ratio_of_means']:.1f}x; residual RMS "
             f"{s['residual_rms_rad']:.2f} rad (+ tip/tilt {s['residual_tiptilt_rms_rad']:.2f} rad)"]
    if "vortex_free" in s:
        lines.append(f"  branch points {s['vortex_free']['branch_points_mean']:.1f} per sample; the phase conjugate "
                     f"without them captures {s['vortex_free']['captured_fraction']:.3f} (a vortex-free estimate's ceiling)")
    for k, b in s["by_rytov"].items():
        lines.append(f"  Rytov {k:>9}: n {b['n']:4d}, NPiB none {b['npib']['none']:.3f}, {net} {b['npib']['unet']:.3f}, "
                     f"conjugate {b['npib']['phase_conjugate']:.3f}, captured {b['captured_fraction']:.2f}"
                     + (f", vortex-free {b['vortex_free']['captured_fraction']:.2f}" if "vortex_free" in b else ""))
    for k, b in s.get("by_noise", {}).items():
        lines.append(f"  noise {k:>14}: {net} NPiB {b['npib']['unet']:.3f} (median {b['npib_median']['unet']:.3f}), "
                     f"captured {b['captured_fraction']:.2f}, residual {b['residual_rms_rad']:.2f} rad"
                     + (f"; U-Net alone captured {b['start']['captured_fraction']:.2f}" if "start" in b else ""))
    emit(summary, a.json, "\n".join(lines))
    return 0


def _cmd_export(a: argparse.Namespace) -> int:
    from .export import export_onnx

    out = out_file(a.onnx, "-o/--output", suffixes=(".onnx",))
    with product(out, "onnx", {"model": a.model, "--dataset": zarr_input(a.dataset) if a.dataset else None}):
        rep = export_onnx(a.model, out, a.opset, a.dataset, log=log_to(a.json))
    emit(rep, a.json, f"wrote {out} ({rep['bytes'] / 1e6:.1f} MB, opset {rep['opset']}, dynamic batch): onnxruntime "
         f"matches torch within {rep['max_abs_diff']:.1e} rad on random inputs; contract of {rep['device']['design']} "
         f"from {rep['device_source']}")
    return 0


def _cmd_import(a: argparse.Namespace) -> int:
    from .captures import ImportOptions, import_captures

    out = out_dir(a.output)
    if a.split is not None and (len(a.split) != 3 or abs(sum(a.split) - 1) > 1e-6):
        from ..validation import ValidationError

        raise ValidationError(f"--split: expected three fractions [train val test] summing to 1, got {a.split}")
    opt = ImportOptions(fit=a.fit, hot_sigma=a.hot_sigma, saturation=a.saturation, saturated=a.saturated,
                        phase_per_count=a.phase_per_count, split=tuple(a.split or (0.9, 0.05, 0.05)), seed=a.seed,
                        overwrite=a.overwrite, orientation=a.orientation)
    rep = import_captures(a.folder, out, a.calibration, a.reference, a.dark, opt,
                          Execution(progress=progress_bar("import", unit="sample"), log=log_to(a.json)), a.mosaic)
    al = rep["calibration"]["alignment"]
    text = (f"wrote {out}: {rep['samples']} of {rep['listed']} samples (8 x {rep['tensor'][1]}^2), split "
            + "/".join(str(v) for v in rep["split_counts"].values())
            + f"; orientation {rep['orientation']['best']} (chi2 {rep['orientation']['chi2']:.2g})"
            + f"; relay shift ({al['shift_x_px']:+.2f}, {al['shift_y_px']:+.2f}) px, rotation "
            f"{al['rotation_deg']:+.3f} deg, x{al['scale']:.4f} (spot residual max "
            f"{max(rep['calibration']['residuals_px']):.2f} px); hot pixels {rep['calibration']['hot_pixels']}; "
            f"saturated {rep['saturated']} ({rep['saturated_policy']})"
            + (": " + ", ".join(rep["saturated_samples"]) if rep["saturated"] else "")
            + f"; {rep['seconds']:.1f} s")
    emit(rep, a.json, text)
    return 0


def register(sub) -> dict:
    """Add the stage-6 commands; returns the ``dataset`` action group (studies add theirs to it)."""
    _register_export(sub)
    _register_evaluate(sub)
    _register_train(sub)
    dsub = _register_dataset(sub)
    _register_build(dsub)
    _register_operators(dsub)
    _register_inspect(dsub)
    _register_import(dsub)
    return {"dataset": dsub}


def _register_export(sub) -> None:
    """``export``: a model as ONNX."""
    ex = sub.add_parser("export", help="stage 6: export a model for deployment (ONNX, dynamic batch)",
                        description="Export the U-Net (or refiner) as ONNX with a dynamic batch axis, checked "
                        "against torch in onnxruntime, with the complete deployment contract as its metadata: camera "
                        "geometry, relay, orientation, per-channel polarisation and focal length, wavelength, device "
                        "identity and the flat-frame calibration signature (examples/deploy_onnx.py checks frames "
                        "against it).")
    ex.add_argument("model", help="model weights (.safetensors with its .json card)")
    ex.add_argument("-o", "--output", "--onnx", dest="onnx", required=True, help="output .onnx file")
    ex.add_argument("--opset", type=integer(13, 23), default=17, help="ONNX opset (default 17)")
    ex.add_argument("--dataset", help="the dataset the model was trained on (optional: by default the device is "
                    "rebuilt from the committed dataset recipe the model card names, checked against its recipe "
                    "hash); its recipe and layout must be the card's")
    ex.add_argument("--json", action="store_true", help="print the report as JSON")
    ex.set_defaults(func=_cmd_export)


def _register_evaluate(sub) -> None:
    """``evaluate``: a model on a dataset split."""
    ev = sub.add_parser(
        "evaluate", help="stage 6: NPiB of a model on a dataset split (Fig. 3b-d), residual phase, gains",
        description="Stage 6c. Per sample: NPiB uncorrected, U-Net, phase conjugate and complex conjugate (the "
        "turbulence stage's bucket and normalisation), residual phase RMS; summaries by Rytov bin and noise "
        "level; CSV per sample, summary.json, Figs. 3b-d.")
    ev.add_argument("model", help="model weights (.safetensors with its .json card)")
    ev.add_argument("dataset", help="dataset folder")
    ev.add_argument("--split", default="test", choices=["test", "val", "train", "all"])
    ev.add_argument("--noise-percent", "--noise", dest="noise", type=num(0, 100, unit="%"), nargs="+",
                    default=[0.0],
                    help="test noise levels, %% of each channel's peak (default 0)")
    ev.add_argument("--photons", type=num(0, 1e15, open_lo=True), nargs="+",
                    help="also: shot noise with these photo-electrons at the peak (+3 e- read noise)")
    ev.add_argument("--limit", type=integer(1, 10**8), help="at most this many samples of the split")
    ev.add_argument("-o", "--output", help="output folder (default: DATASET/evaluation)")
    ev.add_argument("--json", action="store_true", help="print the summary as JSON")
    ev.set_defaults(func=_cmd_evaluate)


def _register_train(sub) -> None:
    """``train``: a recipe into a run folder."""
    tr = sub.add_parser(
        "train", help="stage 6: train the U-Net, or a learned refinement on top of one ([refine] recipes); resumable, DDP under torchrun",
        description="Stage 6b. Train the U-Net of a recipe on a dataset: AdamW, step schedule, noise at load; "
        "a checkpoint every epoch (--resume continues a killed run), metrics CSV/JSON and curves, the best "
        "model by validation NPiB as safetensors + JSON card. Multi-process: `torchrun --nproc_per_node N -m "
        "metadesign train ...` (NCCL on GPUs, gloo on CPU).")
    tr.add_argument("recipe", help="training recipe (TOML), e.g. sensing/train-demo.toml")
    tr.add_argument("--dataset", help="dataset folder (default: the recipe's data.dataset)")
    tr.add_argument("-o", "--output", help="run folder (default: RECIPE-run beside the recipe)")
    tr.add_argument("--resume", action="store_true", help="continue the run in -o from its checkpoint")
    tr.add_argument("--init", help="start from these weights (model.safetensors): transfer learning")
    tr.add_argument("--max-steps", type=integer(1, 10**9), help="stop after this many optimiser steps "
                    "(smoke tests, benchmarks)")
    tr.add_argument("--json", action="store_true", help="print the report as JSON")
    tr.set_defaults(func=_cmd_train)


def _register_dataset(sub):
    """``dataset``: the group of its actions (returned)."""
    ds = sub.add_parser(
        "dataset", help="stage 6: training data: dataset build RECIPE | operators | show | plot | import CAPTURES | "
        "synth-captures",
        description="Stage 6a. `dataset build RECIPE` renders seeded scintillated beacons through the "
        "as-fabricated metasurface onto the sensor (zarr v3, sharded, resumable; a local process pool or a "
        "Dask cluster). `dataset show` summarises a dataset, `dataset plot` draws a few samples and the "
        "Rytov histogram.")
    dsub = ds.add_subparsers(dest="dataset_command", metavar="ACTION")
    dsub.required = True
    return dsub


def _register_build(dsub) -> None:
    """``dataset build``."""
    b = dsub.add_parser("build", help="build (or resume) a dataset from a recipe")
    b.add_argument("recipe", help="dataset recipe (TOML), e.g. sensing/dataset-demo.toml")
    b.add_argument("-o", "--output", help="dataset folder (default: a folder named after the recipe, beside it)")
    workers_arg(b)
    b.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the shards on a Dask distributed scheduler (e.g. tcp://host:8786) instead of -j")
    b.add_argument("--samples", type=integer(1, 10_000_000), help="override the recipe's sample count")
    b.add_argument("--overwrite", action="store_true", help="replace a dataset built from a different recipe")
    b.add_argument("--json", action="store_true", help="print the report as JSON")
    b.set_defaults(func=_cmd_build)


def _register_operators(dsub) -> None:
    """``dataset operators``."""
    op = dsub.add_parser(
        "operators", help="store each sample's bucket operator: the end-to-end loss as a small matrix product",
        description="Compute each sample's bucket operator A (the bucket pixels' rows of the back-propagation "
        "through its screens, on the receiver aperture: NPiB = ||A u||^2 / ideal) and store it in the dataset; "
        "training then reads A instead of regenerating the screens (train.pib_operator = auto/stored). "
        "Resumable; a local process pool or a Dask cluster.")
    op.add_argument("dataset", help="dataset folder (from `dataset build` or `dataset import`)")
    op.add_argument("--split", "--splits", dest="splits", nargs="+", default=["train"], choices=["train", "val", "test"],
                    help="splits to compute (default: train)")
    workers_arg(op)
    op.add_argument("--scheduler", metavar="ADDRESS",
                    help="run the shards on a Dask distributed scheduler (e.g. tcp://host:8786) instead of -j")
    op.add_argument("--overwrite", action="store_true", help="recompute operators stored for other splits")
    op.add_argument("--json", action="store_true", help="print the report as JSON")
    op.set_defaults(func=_cmd_operators)


def _register_inspect(dsub) -> None:
    """``dataset show``, ``verify`` and ``plot``."""
    s = dsub.add_parser("show", help="summarise a dataset")
    s.add_argument("dataset", help="dataset folder")
    s.add_argument("--json", action="store_true", help="print as JSON")
    s.set_defaults(func=_cmd_show)
    v = dsub.add_parser("verify", help="read back every sample and check it (exit 1 when damaged)",
                        description="Integrity check: decode every shard of every array (shard-index checksums), "
                        "check finite values and each PSF tensor's normalisation (8 channels sum to 8); list the "
                        "damaged shards. Exit status 1 when any is damaged.")
    v.add_argument("dataset", help="dataset folder")
    v.add_argument("--json", action="store_true", help="print the report as JSON")
    v.set_defaults(func=_cmd_verify)
    p = dsub.add_parser("plot", help="draw a few samples and the Rytov histogram")
    p.add_argument("dataset", help="dataset folder")
    p.add_argument("-o", "--output", help="PNG path (default: DATASET/fig-dataset.png)")
    limit_arg(p, "at most this many samples drawn (1..8, default 3)", type=integer(1, 8), default=3)
    p.set_defaults(func=_cmd_plot)


def _register_import(dsub) -> None:
    """``dataset import``: camera captures into a dataset."""
    im = dsub.add_parser(
        "import", help="camera captures (frames + SLM phases + manifest) -> a dataset (propagation = slm)",
        description="Import captured frames: fit the relay misalignment from flat captures against the reference "
        "device's spots, subtract darks, mask hot pixels, flag saturation, crop the 8 quadrants around the fitted "
        "centres, normalise as synthetic data. Written aside and renamed: a failed import leaves nothing.")
    im.add_argument("folder", help="folder with manifest.csv (sample, frame_x, frame_y, slm_phase[, rytov, split])")
    im.add_argument("-o", "--output", required=True, help="dataset folder to write")
    im.add_argument("--calibration", required=True, metavar="FLAT_CSV",
                    help="CSV of flat-wavefront captures (frame_x, frame_y)")
    im.add_argument("--reference", required=True, metavar="DATASET",
                    help="synthetic dataset of the design (sensor, tensor size, path, reference spots)")
    im.add_argument("--dark", nargs="+", metavar="FILE", help="dark frame(s), averaged")
    im.add_argument("--mosaic", metavar="CAMERA_TOML",
                    help="raw captures of a polarisation (mosaic) camera: one frame_raw per sample (manifest and "
                         "calibration list), its vendor layout in this recipe ([raw] width_px, height_px, bit_depth, "
                         "packing, msb_aligned; [camera] pattern, extinction_ratio, unmix, ...)")
    im.add_argument("--orientation", choices=ORIENTATIONS, default="identity",
                    help="how the camera's frames are turned against the reference's (relay inversion: rot180; "
                         "flip-ud, flip-lr, swap-pol, ...): the flat captures are checked against the reference "
                         "device's calibration signature in every orientation, and a mismatch is refused")
    im.add_argument("--fit", choices=("similarity", "shift"), default="similarity",
                    help="relay model fitted to the spot centres (default similarity: shift, rotation, scale)")
    im.add_argument("--hot-sigma", type=num(1, 1000), default=8.0, help="hot pixel threshold, robust sigmas (8)")
    im.add_argument("--saturation", type=num(0, 1e12, open_lo=True),
                    help="saturation level, counts (default: full scale of the frame's integer type)")
    im.add_argument("--saturated", choices=("flag", "drop", "error"), default="flag",
                    help="saturated samples: flag and keep (default), drop, or refuse the import")
    im.add_argument("--phase-per-count", type=num(0, 1, open_lo=True), default=2 * 3.141592653589793 / 65536,
                    help="rad per count of SLM phases given as integer images (default 2 pi / 65536)")
    im.add_argument("--split", nargs=3, type=num(0, 1), metavar=("TRAIN", "VAL", "TEST"),
                    help="split fractions when the manifest has no split column (default 0.9 0.05 0.05)")
    im.add_argument("--seed", type=integer(0, 2**63 - 1), default=0, help="seed of the split permutation")
    im.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    im.add_argument("--json", action="store_true", help="print the report as JSON")
    im.set_defaults(func=_cmd_import)

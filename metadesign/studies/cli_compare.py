"""The ``compare`` and ``retrieve`` commands: every estimator on the same samples."""

from __future__ import annotations

import argparse
import contextlib
from dataclasses import replace
from pathlib import Path

from ..cliutil import emit, integer, log_to, num, out_dir, progress_bar, workers_arg
from ..outputs import product, zarr_input
from ..validation import InputError

__all__ = ["register"]


__all__ = ["register"]

#: the estimators metadesign registers (metadesign.reconstruction.estimators), named here so that ``--help``
#: need not import them; ``compare`` checks ``--methods`` against the live registry
BUILTIN_ESTIMATORS = ("shack_hartmann", "retrieval", "unet", "hybrid", "refine")


def _settings(a: argparse.Namespace, methods):
    from .compare import CompareSettings

    st = CompareSettings(split=a.split, limit=a.limit, noise_percent=a.noise, batch=a.batch, methods=tuple(methods))
    if a.iterations is not None:
        st = replace(st, retrieval=replace(st.retrieval, zonal_iterations=a.iterations))
    if getattr(a, "hybrid_iterations", None) is not None:
        st = replace(st, hybrid=replace(st.hybrid, zonal_iterations=a.hybrid_iterations))
    if a.starts is not None:
        st = replace(st, retrieval=replace(st.retrieval, starts=a.starts))
    return st


def _model_arg(model: str):
    if model.lower() == "none":
        return None
    from ..validation import ValidationError

    p = Path(model)
    if not p.is_file() and not p.with_name(p.name + ".json").is_file():
        raise ValidationError(f"{model}: no such model (give .safetensors with its .json card, or NONE)")
    return str(p)


def _lines(res, summ, out, tuning) -> list[str]:
    from .compare import BUDGETS_MS, label, methods_present

    ms = methods_present(res["rows"])
    lat = summ["latency_ms"]
    lines = [f"{res['n']} {res['settings'].split} samples, noise {res['settings'].noise_percent:g} % "
             f"({res['wall_seconds']:.0f} s) -> {out}",
             f"  {'method':<27} {'NPiB':>6} {'median':>7} {'latency':>11}   " + "   ".join(
                 f"@{b:g} ms" for b in BUDGETS_MS)]
    for m in ms:
        bud = "   ".join(f"{summ['budgets_ms'][f'{b:g}'][m]:6.3f}" if m in summ["budgets_ms"][f"{b:g}"] else "     -"
                         for b in BUDGETS_MS)
        lines.append(f"  {label(m):<27} {summ['npib'][m]:6.3f} {summ['npib_median'][m]:7.3f} "
                     f"{(f'{lat[m]:.3g} ms' if m in lat else '-'):>11}   {bud}")
    for k, b in summ["by_rytov"].items():
        lines.append(f"  Rytov {k:>8} (n {b['n']:3d}): " + ", ".join(f"{m} {b[m]:.3f}" for m in ms))
    if tuning:
        lines.append(f"  tuned on {tuning['samples']} {tuning['split']} samples: "
                     + "; ".join(f"{k} {v['npib']:.3f}" for k, v in tuning.items() if isinstance(v, dict)))
    return lines


def _cmd_compare(a: argparse.Namespace) -> int:
    from .compare import ESTIMATORS, run_compare, tune, write_compare
    from .madewith import made_with

    if a.methods is None:
        a.methods = list(ESTIMATORS)
    bad = [m for m in a.methods if m not in ESTIMATORS]
    if bad:
        raise InputError(f"--methods: {bad[0]!r} is not an estimator (registered: {', '.join(ESTIMATORS)})")

    model = _model_arg(a.model)
    out = out_dir(a.output or Path(a.dataset) / "compare")
    st = _settings(a, a.methods)
    log = log_to(a.json)
    inputs = {"model": a.model if model is not None else None, "dataset": zarr_input(a.dataset)}
    with product(out, "compare", inputs):
        tuning = None
        if a.tune:
            st, tuning = tune(model, a.dataset, st, a.tune, log=log)
        res = run_compare(model, a.dataset, st, workers=a.workers, progress=progress_bar("compare", unit="sample"))
        files = write_compare(res, out, tuning, made_with(model, a.dataset))
    from .compare import summarise

    summ = summarise(res)
    emit({"summary": summ, "settings": res["settings"].to_dict(), "tuning": tuning, "files": [str(f) for f in files],
          "wall_seconds": res["wall_seconds"]}, a.json, "\n".join(_lines(res, summ, out, tuning)))
    return 0


def _cmd_retrieve(a: argparse.Namespace) -> int:
    from .compare import run_compare, summarise, write_compare
    from .madewith import made_with

    model = _model_arg(a.model)
    methods = ("retrieval",) if model is None else ("unet", "hybrid")
    st = _settings(a, methods)
    if model is not None and a.iterations is not None:
        st = replace(st, hybrid=replace(st.hybrid, zonal_iterations=a.iterations))
    out = out_dir(a.output) if a.output else None
    inputs = {"model": a.model if model is not None else None, "dataset": zarr_input(a.dataset)}
    with product(out, "compare", inputs) if out else contextlib.nullcontext():
        res = run_compare(model, a.dataset, st, workers=a.workers, progress=progress_bar("retrieve", unit="sample"))
        summ = summarise(res)
        files = write_compare(res, out, made_with=made_with(model, a.dataset)) if out else []
        if out:
            files.append(_plot_convergence(res, out))
    name = methods[-1]
    mis = res["rows"][f"{name}_misfit"].mean(axis=1)
    doc = {"summary": summ, "settings": res["settings"].to_dict(), "files": [str(f) for f in files],
           "convergence": {"misfit_mean": mis.tolist(), "npib": summ["curves"].get(name)},
           "seconds_per_sample": res["wall_seconds"] / res["n"]}
    lines = _lines(res, summ, out or "(no output folder)", None)
    lines.append(f"  {name}: {res['wall_seconds'] / res['n'] * 1e3:.0f} ms per sample in batches of {st.batch}; "
                 "NPiB along the iterations: " + ", ".join(f"{c['iterations']}: {c['npib']:.3f}"
                                                        for c in summ["curves"].get(name, [])))
    emit(doc, a.json, "\n".join(lines))
    return 0


def _plot_convergence(res, out: Path) -> Path:
    import numpy as np

    from ..plotting import pyplot, save_figure
    from .compare import summarise

    plt = pyplot()
    summ = summarise(res)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for name in ("retrieval", "hybrid"):
        if f"{name}_misfit" in res["rows"]:
            m = res["rows"][f"{name}_misfit"]
            a1.semilogy(np.arange(1, len(m) + 1), m.mean(axis=1), label=name)
            cv = summ["curves"][name]
            a2.plot([c["iterations"] for c in cv], [c["npib"] for c in cv], "o-", label=name)
    a2.axhline(summ["npib"]["phase_conjugate"], ls="--", c="g", label="phase conjugate")
    a2.axhline(summ["npib"]["none"], ls=":", c="k", label="uncorrected")
    a1.set(xlabel="iteration", ylabel="mean misfit", title="convergence")
    a2.set(xlabel="iteration", ylabel="mean NPiB", title="NPiB along the iterations")
    a1.legend(fontsize=8)
    a2.legend(fontsize=8)
    return save_figure(fig, out / "convergence.png")


def _common(p, iterations_help: str) -> None:
    p.add_argument("dataset", help="dataset folder (its device pupil and provenance define the forward model)")
    p.add_argument("--split", default="test", choices=["test", "val", "train", "all"])
    p.add_argument("--limit", type=integer(1, 10**8), help="at most this many samples of the split")
    p.add_argument("--noise-percent", "--noise", dest="noise", type=num(0, 100, unit="%"), default=5.0,
                   help="sensor noise for every method, %% of each frame's peak (default 5, the demo model's)")
    p.add_argument("--iterations", type=integer(0, 100000), help=iterations_help)
    p.add_argument("--starts", type=integer(1, 64), help="retrieval: starts per sample in the modal stage (default 3)")
    p.add_argument("--batch", type=integer(1, 4096), default=8, help="samples per batch (default 8)")
    workers_arg(p)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _add_compare(sub) -> None:
    c = sub.add_parser(
        "compare", help="every estimator (Shack-Hartmann, retrieval, U-Net, hybrid, learned refinement) on the same samples: NPiB and latency",
        description="Every wavefront sensor on the same samples and the same sensor noise: uncorrected, a "
        "simulated Shack-Hartmann, model-based phase-diversity retrieval on the 8 PSFs, the U-Net, the "
        "U-Net + retrieval hybrid, the learned refinement (when MODEL is a refiner: its U-Net runs too), and "
        "the phase/complex conjugate bounds. NPiB per sample vs Rytov number, NPiB vs single-sample latency "
        "(and vs iterations or refinement steps), NPiB at 1/10/100 ms budgets; CSV, JSON and figures in -o.")
    c.add_argument("model", help="U-Net or refiner weights (.safetensors with its .json card), or NONE")
    _common(c, "zonal iterations of the retrieval (default 100)")
    c.add_argument("--hybrid-iterations", type=integer(0, 100000), help="iterations of the hybrid (default 50)")
    c.add_argument("--methods", nargs="+", metavar="ESTIMATOR",
                   help="estimators to run (default: all registered: " + ", ".join(BUILTIN_ESTIMATORS)
                   + " and any registered later)")
    c.add_argument("--tune", type=integer(0, 10000), default=0, metavar="N",
                   help="first tune every baseline on N validation samples (grids in metadesign.studies.compare)")
    c.add_argument("-o", "--output", help="output folder (default: DATASET/compare)")
    c.set_defaults(func=_cmd_compare)


def _add_retrieve(sub) -> None:
    r = sub.add_parser(
        "retrieve", help="baselines: model-based phase-diversity retrieval (or the hybrid) on a dataset split",
        description="Estimate the received phase from the 8 PSFs by fitting the differentiable as-fabricated "
        "model (Zernike start coarse to fine, then per pixel phase and amplitude; Adam). MODEL: start from "
        "the U-Net's prediction (the hybrid); NONE: retrieval alone. Reports NPiB, wall time per sample and "
        "the convergence curve.")
    r.add_argument("model", help="U-Net weights to start from (the hybrid), or NONE")
    _common(r, "zonal iterations (default 100 alone, 50 from the U-Net)")
    r.add_argument("-o", "--output", help="output folder for CSV, JSON and figures (default: print only)")
    r.set_defaults(func=_cmd_retrieve)


def register(sub, groups: dict) -> None:
    """Add ``compare`` and ``retrieve`` to ``sub``."""
    _add_compare(sub)
    _add_retrieve(sub)

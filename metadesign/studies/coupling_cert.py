"""The coupling model fitted and certified on a supercell table: a learning curve, held-out errors by source."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..library.coupling import CouplingConfig, lpa_t, relative_error, save_coupling
from ..library.coupling_net import coupling_t, fit_coupling
from ..library.locate import file_sha256, find_library
from ..library.store import load_library
from ..library.supercells import (
    SupercellTable,
    load_table,
)
from ..plotting import pyplot, save_figure
from ..validation import InputError
from .supercell_errors import _by_source, _error_histogram, _stats

__all__ = ["CouplingFit", "CouplingInputs", "load_coupling_inputs", "check_coupling_inputs", "coupling_study",
           "certify_coupling", "plot_coupling"]


@dataclass(frozen=True)
class CouplingFit:
    """How :func:`certify_coupling` fits: the learning curve's ``sizes``, the network ``cfg``, ``steps`` of Adam
    with ``weight_decay`` from ``seed``, and the ``goal`` (mean, p90) of the held-out error."""

    sizes: tuple = (250, 500, 1000)
    cfg: CouplingConfig = CouplingConfig()
    steps: int = 4000
    seed: int = 0
    weight_decay: float = 1e-3
    goal: tuple = (0.05, 0.1)


@dataclass(frozen=True)
class CouplingInputs:
    """A coupling certification's inputs: the ``table`` (at ``path``), its ``lib`` (at ``lib_path``) and the
    ``reference`` table certifying (at ``reference_path``; None: the table's own held-out rows)."""

    table: SupercellTable
    path: Path
    lib: Any
    lib_path: Path
    reference: SupercellTable | None = None
    reference_path: Path | None = None


def load_coupling_inputs(table_path: str | Path, library: str | Path | None = None) -> tuple:
    """``(table, library path, library)``: the table and its library (``library``, else found by sha256)."""
    table = load_table(table_path)
    tp = Path(table_path)
    lib_path = Path(library) if library else find_library(table.meta["library"]["sha256"],
                                                           table.meta["library"]["path"], tp.parent)
    return table, lib_path, load_library(lib_path)


def check_coupling_inputs(table: SupercellTable, lib, table_path: str | Path, library_path: Path,
                          reference: str | Path | None = None) -> CouplingInputs:
    """The inputs of a certification, checked (InputError, one line): the table needs fitting and held-out
    rows; ``reference`` (a table's path) solved against the same library, with held-out rows."""
    tp = Path(table_path)
    if not table.test.any() or table.test.all():
        raise InputError(f"{tp}: the table has {int(table.test.sum())} held-out rows of {len(table.test)}: "
                         "certification needs both fitting and held-out rows (table.test_every >= 2)")
    ref = None
    if reference:
        ref = load_table(reference)
        if ref.meta.get("library", {}).get("sha256") != table.meta.get("library", {}).get("sha256"):
            raise InputError(f"--reference {reference}: solved against another library than {tp.name}")
        if not ref.test.any():
            raise InputError(f"--reference {reference}: the table has no held-out rows")
    return CouplingInputs(table, tp, lib, library_path, ref, Path(reference) if reference else None)


def coupling_study(inputs: CouplingInputs, fit: CouplingFit, out: Path, log=lambda s: None) -> dict:
    """Fit and certify the coupling model (:func:`certify_coupling`) and write it to ``out`` with its card
    (the certification, the tables) and its figure (``out`` with .png); returns the report."""
    table, tp, ref_path = inputs.table, inputs.path, inputs.reference_path
    log(f"coupling model on {tp.name}: {int((~table.test).sum())} fitting rows, {int(table.test.sum())} held out")
    model, rep = certify_coupling(table, inputs.lib, fit, inputs.reference, log)
    fig = plot_coupling(rep, out.with_suffix(".png"))
    rep.pop("_e"), rep.pop("_e_lpa")
    card = {"certification": rep, "table": {"path": tp.name, "sha256": file_sha256(tp)}, "figure": fig.name,
            "reference_table": {"path": ref_path.name, "sha256": file_sha256(ref_path)}
            if inputs.reference is not None else None,
            "structure": "t = mean_i t_lib(w_i) + 1/4 sum_i [G(f_i, f_H, f_V, f_D) - G(f_i, f_i, f_i, f_i)]; "
                         "t_y(w) = t_x(transpose(w))"}
    save_coupling(out, model, inputs.lib_path, card)
    rep["output"], rep["figure"] = str(out), str(fig)
    return rep


def certify_coupling(table: SupercellTable, lib, fit: CouplingFit = CouplingFit(),
                     reference: SupercellTable | None = None, log=lambda s: None) -> tuple[object, dict]:
    """Fit the coupling model on the first ``n`` fitting rows of the table for each ``n`` in ``fit.sizes``
    (a learning curve) and certify each fit on every held-out row of ``reference`` (default: the table's
    own; never fitted, never used to pick a step); returns the model of the largest size and the report.
    A table at another truncation than the library's is fitted on its labels (LPA + its coupling:
    :meth:`SupercellTable.labels`); the reference's labels are its own.  Error: ``|t - t_RCWA| / rms_i |t_i|``."""
    import torch

    sizes, cfg, steps, seed, goal, weight_decay = fit.sizes, fit.cfg, fit.steps, fit.seed, fit.goal, fit.weight_decay
    torch.set_num_threads(1)
    ref = table if reference is None else reference
    fit_rows = np.flatnonzero(~table.test)
    test_rows = np.flatnonzero(ref.test)
    if not len(test_rows):
        raise ValueError("the reference table has no held-out rows")
    sizes = sorted({min(int(n), len(fit_rows)) for n in sizes})
    w_fit = table.widths[fit_rows]
    t_fit, _ = table.rows(fit_rows).lpa_labels(lib)
    w_te = ref.widths[test_rows]
    t_te, tu_te = ref.rows(test_rows).lpa_labels(lib)
    e_lpa = relative_error(lpa_t(tu_te), t_te, tu_te)
    curve, model = [], None
    for n in sizes:
        t0 = time.perf_counter()
        log(f"  fitting on {n} supercells ...")
        model, info = fit_coupling(lib, w_fit[:n], t_fit[:n], cfg, steps=steps, seed=seed,
                                   weight_decay=weight_decay, log=log)
        e = relative_error(coupling_t(model, w_te, tu_te), t_te, tu_te)
        curve.append({"supercells": n, "held_out": _stats(e), "fit_seconds": time.perf_counter() - t0,
                      "best_validation_error": info["best_validation_error"], "_e": e, "_info": info})
        log(f"    held-out |dt|/rms|t_i| mean {e.mean():.4f} (x {e[:, 0].mean():.4f}, y {e[:, 1].mean():.4f}), "
            f"p90 {np.percentile(e, 90):.4f}; LPA {e_lpa.mean():.4f}")
    last = curve[-1]
    e = last.pop("_e")
    info = last.pop("_info")
    for c in curve:
        c.pop("_e", None), c.pop("_info", None)
    by_source = _by_source(ref.source[test_rows], e, e_lpa)
    m, p90 = float(e.mean()), float(np.percentile(e, 90))
    report = {
        "metric": "|t_model - t_RCWA| / rms_i |t_i| (the four pillars' rms library |t|), per polarisation",
        "held_out_supercells": int(len(test_rows)), "fitted_supercells": int(sizes[-1]),
        "model": _stats(e), "lpa": _stats(e_lpa), "by_source": by_source,
        "goal": {"mean": goal[0], "p90": goal[1]},
        "passed": bool(m <= goal[0] and p90 <= goal[1]), "mean_both": m, "p90_both": p90,
        "lpa_mean_both": float(e_lpa.mean()), "lpa_p90_both": float(np.percentile(e_lpa, 90)),
        "learning_curve": curve, "fit": {k: v for k, v in info.items() if k != "history"},
        "table": {"supercells": len(table), "n_harmonics": table.meta.get("n_harmonics"),
                  "seed": table.meta.get("seed")},
        "reference": None if reference is None else {"supercells": len(ref), "n_harmonics": ref.meta.get("n_harmonics"),
                                                     "seed": ref.meta.get("seed")},
        "_e": e, "_e_lpa": e_lpa,
    }
    return model, report


def plot_coupling(rep: dict, out: Path) -> Path:
    """Learning curve (held-out mean and p90 vs supercells fitted, the LPA and the goal as lines) and the
    held-out error distributions of the model and the LPA."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    c = rep["learning_curve"]
    n = [r["supercells"] for r in c]
    for k, ls in (("mean", "o-"), ("p90", "s--")):
        axs[0].plot(n, [np.mean(r["held_out"][k]) for r in c], ls, color="C0", label=f"model, {k}")
        axs[0].axhline(np.mean(rep["lpa"][k]), color="C3", ls=ls[1:], label=f"LPA, {k}")
        axs[0].axhline(rep["goal"][k], color="0.5", ls=":", lw=1)
        axs[0].annotate(f"goal {k} {rep['goal'][k]:g}", (n[-1], rep["goal"][k]), fontsize=8, color="0.4",
                        ha="right", va="bottom")
    axs[0].set(xscale="log", yscale="log", xlabel="supercells fitted (RCWA solves)",
               ylabel="held-out |t - t_RCWA| / rms|t_i|",
               title=f"learning curve ({rep['held_out_supercells']} held-out supercells)")
    axs[0].set_xticks(n, [str(v) for v in n])
    axs[0].set_xticks([], minor=True)  # the log axis's own minor labels would overprint the sizes
    axs[0].legend(fontsize=8)
    e, el = rep["_e"].ravel(), rep["_e_lpa"].ravel()
    _error_histogram(axs[1], e, el, "coupling model", max(el.max(), e.max()))
    return save_figure(fig, out)

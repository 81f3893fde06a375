"""The PEDS supercell surrogate calibrated and certified on a converged supercell table (:func:`certify_peds`)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

import numpy as np

from ..cards import read_card
from ..execution import SERIAL, Execution
from ..library.coupling import CARD_FORMAT, lpa_t, relative_error
from ..library.locate import find_library
from ..library.peds import PedsModel, fit_peds, low_fidelity_couplings, peds_t
from ..library.store import load_library
from ..library.supercell import solve_supercell
from ..library.supercells import (
    SupercellTable,
    load_table,
    matched_unit_harmonics,
    unit_cells,
)
from ..plotting import pyplot, save_figure
from ..validation import InputError
from .supercell_errors import _by_source, _error_histogram, _stats

__all__ = ["PedsSettings", "load_peds_inputs", "certify_peds", "select_levels", "plot_peds"]


@dataclass(frozen=True)
class PedsSettings:
    """What :func:`certify_peds` calibrates: the low truncations ``harmonics`` (requested), the learning
    curve's fitting ``sizes``, ``select`` (the levels are candidates: cross-validation picks a subset), the
    ``goal`` (mean, p90), and the cost probe (``probe_rows`` held-out rows timed; ``probe_label``: a
    converged label timed too)."""

    harmonics: tuple = (97, 220)
    sizes: tuple = (10, 25, 50, 100, 250, 500, 1000)
    select: bool = False
    goal: tuple = (0.05, 0.1)
    probe_rows: int = 4
    probe_label: bool = True


#: candidate levels at most with ``select`` (2^K - 1 subsets are cross-validated)
MAX_CANDIDATES = 8


def load_peds_inputs(table_path: str | Path, settings: PedsSettings, library: str | Path | None = None,
                     networks=()) -> tuple:
    """``(table, library path, library, {name: certification})``: the converged table at ``table_path``, its
    library (``library``, else found by its sha256) and the certifications of the coupling models' cards
    ``networks`` (to draw beside), each checked for :func:`certify_peds` (InputError, one line)."""
    table = load_table(table_path)
    tp = Path(table_path)
    if not table.test.any() or table.test.all():
        raise InputError(f"{tp}: the table has {int(table.test.sum())} held-out rows of {len(table.test)}: "
                         "certification needs both fitting and held-out rows (table.test_every >= 2)")
    if table.t_unit is not None:
        raise InputError(f"{tp}: a table solved at nG {table.meta.get('n_harmonics')} with matched unit cells is a "
                         "low fidelity itself; calibrate on a converged table (solved at the library's truncation)")
    top = table.meta.get("n_harmonics") or 0
    if settings.select and len(set(settings.harmonics)) > MAX_CANDIDATES:
        raise InputError(f"--select: at most 8 candidate levels (2^K - 1 subsets are cross-validated), got "
                         f"{len(set(settings.harmonics))}")
    if max(settings.harmonics) >= top:
        raise InputError(f"--harmonics {max(settings.harmonics)}: the levels must lie below the table's truncation "
                         f"(nG {top})")
    lib_path = Path(library) if library else find_library(table.meta["library"]["sha256"],
                                                           table.meta["library"]["path"], tp.parent)
    lib = load_library(lib_path)
    resolved: dict[int, list[int]] = {}
    for h in sorted(set(settings.harmonics)):
        resolved.setdefault(matched_unit_harmonics(h, lib.stack)[0] - 1, []).append(h)
    for nG, hs in resolved.items():
        if len(hs) > 1:
            raise InputError(f"--harmonics {' '.join(map(str, hs))}: these requests solve the same truncation "
                             f"(nG {nG}); give distinct levels")
    certs = {}
    for i, path in enumerate(networks or ()):
        _, _, card = read_card(path, CARD_FORMAT, "coupling model")
        if not isinstance(card.get("certification"), dict) or "learning_curve" not in card["certification"]:
            raise InputError(f"--network {path}: its card holds no certification (learning curve) to draw")
        name = f"{Path(path).name.split('.')[0]}, on {(card.get('table') or {}).get('path', '?')}"
        certs[name if name not in certs else f"{name} ({i + 1})"] = card["certification"]
    return table, lib_path, lib, certs


def certify_peds(table: SupercellTable, lib, settings: PedsSettings, partial: Path,
                 run: Execution = SERIAL) -> tuple[object, dict]:
    """Calibrate the PEDS surrogate (:mod:`metadesign.library.peds`) on the table's converged labels: every row
    solved at the low truncations ``settings.harmonics`` (resumable under ``partial``, on ``run``), the
    coefficients fitted on the first ``n`` fitting rows for each ``n`` of ``settings.sizes`` (a learning curve;
    each fit certified on every held-out row, never fitted), each level alone (uncalibrated) beside it;
    returns the model of the largest size and the report (by source, cost per supercell and per million).
    ``settings.select``: the levels are candidates, and the model uses the subset that cross-validation on
    the fitting rows picks (:func:`select_levels`; the held-out rows play no part in the choice)."""
    sizes, goal, probe_rows, probe_label = settings.sizes, settings.goal, settings.probe_rows, settings.probe_label
    select, log = settings.select, run.log
    harmonics = sorted({int(h) for h in settings.harmonics})
    fit_rows, test_rows = np.flatnonzero(~table.test), np.flatnonzero(table.test)
    if not len(test_rows) or not len(fit_rows):
        raise ValueError("certification needs fitting and held-out rows")
    labels, tu = table.lpa_labels(lib)
    lpa = lpa_t(tu)
    log(f"PEDS levels nG {harmonics} on {len(table)} supercells ({len(test_rows)} held out)")
    c, nGs = low_fidelity_couplings(table.widths, lib.stack, harmonics, partial, workers=run.workers,
                                    scheduler=run.scheduler, progress=run.progress, log=log)
    te = test_rows
    e_lpa = relative_error(lpa[te], labels[te], tu[te])
    probe = table.widths[test_rows[:probe_rows]]  # the cost timed here, whatever the chunks held already
    levels = [{"requested": h, "n_harmonics": g, "seconds_per_supercell_core": _solve_seconds(probe, lib.stack, h),
               "alone": _stats(relative_error(lpa[te] + c[k][te], labels[te], tu[te]))}
              for k, (h, g) in enumerate(zip(harmonics, nGs))]
    label_h = table.meta.get("n_harmonics")
    label_cost = _solve_seconds(probe[:2], lib.stack, label_h + 1, units=False) if label_h and probe_label else None
    target = labels - lpa
    selection = None
    if select and len(harmonics) > 1:
        n_model = min(max(int(v) for v in sizes), len(fit_rows))  # the rows the model is fitted on, no more
        selection = select_levels(c, target, fit_rows[:n_model], tu, [float(g) ** 3 for g in nGs])
        keep = selection["chosen"]
        log("  levels chosen by cross-validation on the fitting rows: nG "
            + ", ".join(str(levels[k]["n_harmonics"]) for k in keep))
        for k, lv in enumerate(levels):
            lv["chosen"] = k in keep
        c, harmonics = c[keep], [harmonics[k] for k in keep]
    chosen = [lv for lv in levels if lv.get("chosen", True)]
    curve, coef = [], None
    for n in sorted({min(int(v), len(fit_rows)) for v in sizes}):
        rows = fit_rows[:n]
        coef = fit_peds(c[:, rows], target[rows])
        e = relative_error(peds_t(coef, c[:, te], lpa[te]), labels[te], tu[te])
        curve.append({"supercells": n, "held_out": _stats(e), "coef": [[a.real, a.imag] for a in coef]})
        log(f"  calibrated on {n}: held-out mean {e.mean():.4f}, p90 {np.percentile(e, 90):.4f}")
    used = fit_rows[:curve[-1]["supercells"]]
    e_fit = relative_error(peds_t(coef, c[:, used], lpa[used]), labels[used], tu[used])
    by_source = _by_source(table.source[test_rows], e, e_lpa)
    m, p90 = float(e.mean()), float(np.percentile(e, 90))
    per_sc = sum(lv["seconds_per_supercell_core"] for lv in chosen)
    report = {
        "metric": "|t_model - t_RCWA| / rms_i |t_i| (the four pillars' rms library |t|), per polarisation",
        "structure": "t = mean_i t_lib(w_i) + sum_k a_k [t_super(nG_k) - mean_i t_unit,i(nG_k)], a_k complex, "
                     "shared by both polarisations",
        "held_out_supercells": int(len(test_rows)), "fitted_supercells": curve[-1]["supercells"],
        "model": _stats(e), "fitted_rows": _stats(e_fit), "lpa": _stats(e_lpa), "by_source": by_source,
        "levels": levels, "selection": selection, "goal": {"mean": goal[0], "p90": goal[1]},
        "passed": bool(m <= goal[0] and p90 <= goal[1]), "mean_both": m, "p90_both": p90,
        "lpa_mean_both": float(e_lpa.mean()), "lpa_p90_both": float(np.percentile(e_lpa, 90)),
        "learning_curve": curve,
        "cost": {"seconds_per_supercell_core": per_sc, "core_hours_per_million": per_sc * 1e6 / 3600,
                 "label_seconds_per_supercell_core": label_cost,
                 "label_n_harmonics": label_h, "probe_supercells": int(len(probe))},
        "table": {"supercells": len(table), "n_harmonics": table.meta.get("n_harmonics"), "seed": table.meta.get("seed")},
        "_e": e, "_e_lpa": e_lpa,
    }
    return PedsModel(tuple(harmonics), tuple(complex(a) for a in coef), lib.identity), report


#: the seed of :func:`select_levels`'s folds
SELECT_SEED = 0


def select_levels(c: np.ndarray, target: np.ndarray, rows: np.ndarray, tu: np.ndarray, cost, folds: int = 5,
                  tolerance: float = 0.02) -> dict:
    """Every non-empty subset of the levels ``c`` (K, n, 2) scored by ``folds``-fold cross-validation of the
    calibration on ``rows`` only (mean error of the out-of-fold predictions against ``target`` = labels -
    LPA); the chosen subset is the cheapest (sum of the levels' ``cost``: a fixed proxy such as nG^3, so the
    choice does not depend on the machine's load) within ``tolerance`` (relative) of the best mean.  Returns
    ``{"chosen": level indices, "subsets": [{levels, cv mean, cv p90, cost}]}``."""
    parts = np.array_split(np.random.default_rng(SELECT_SEED).permutation(rows), folds)
    out = []
    for k in range(1, len(c) + 1):
        for sub in combinations(range(len(c)), k):
            cs = c[list(sub)]
            errs = []
            for f in range(folds):
                fit = np.concatenate([parts[g] for g in range(folds) if g != f])
                a = fit_peds(cs[:, fit], target[fit])
                va = parts[f]
                errs.append(relative_error(np.tensordot(a, cs[:, va], axes=1), target[va], tu[va]))
            e = np.concatenate(errs)
            out.append({"levels": list(sub), "cv_mean": float(e.mean()), "cv_p90": float(np.percentile(e, 90)),
                        "cost": float(sum(cost[j] for j in sub))})
    best = min(r["cv_mean"] for r in out)
    pick = min((r for r in out if r["cv_mean"] <= best * (1 + tolerance) + 1e-12),
               key=lambda r: (r["cost"], r["cv_mean"]))
    return {"chosen": pick["levels"], "folds": folds, "tolerance": tolerance, "rows": int(len(rows)),
            "cost": "sum of nG^3 of the levels", "subsets": out}


def _solve_seconds(widths: np.ndarray, stack, harmonics: int, units: bool = True) -> float:
    """Seconds per supercell on this core of a fresh solve at ``harmonics`` (requested), with its matched unit
    cells when ``units`` (a PEDS level; a converged label solves none), no cache."""
    ns, nu = matched_unit_harmonics(int(harmonics), stack)
    t0 = time.perf_counter()
    for w in widths:
        solve_supercell(w, stack, ns)
        if units:
            unit_cells(w[None], stack, nu)
    return (time.perf_counter() - t0) / max(1, len(widths))


def plot_peds(rep: dict, out: Path, networks: dict | None = None) -> Path:
    """Learning curve of the calibrated surrogate (held-out mean and p90 vs labels), each level alone, the LPA,
    the goal and (``networks``: name -> a coupling card's certification) the networks' curves; the held-out
    error distributions."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(12, 5.6), constrained_layout=True)
    c = rep["learning_curve"]
    n = [r["supercells"] for r in c]
    ax = axs[0]
    for k, ls in (("mean", "o-"), ("p90", "s--")):
        ax.plot(n, [np.mean(r["held_out"][k]) for r in c], ls, color="C0", label=f"PEDS ({sum(lv.get('chosen', True) for lv in rep['levels'])} "
                f"levels, a coefficient each), {k}")
        ax.axhline(np.mean(rep["lpa"][k]), color="C3", ls=ls[1:], lw=1, label=f"LPA, {k}")
        ax.axhline(rep["goal"][k], color="0.5", ls=":", lw=1)
        ax.annotate(f"goal {k} {rep['goal'][k]:g}", (n[0], rep["goal"][k]), fontsize=8, color="0.4", va="bottom")
    for j, lv in enumerate(rep["levels"]):
        ax.axhline(np.mean(lv["alone"]["mean"]), color=("C1", "C5", "C7", "C8")[j % 4], ls="-.", lw=1,
                   label=f"nG {lv['n_harmonics']} alone, mean")
    for j, (name, cert) in enumerate((networks or {}).items()):
        cc = cert["learning_curve"]
        ax.plot([r["supercells"] for r in cc], [np.mean(r["held_out"]["mean"]) for r in cc], "^-",
                color=("C2", "C4", "C6", "C9")[j % 4],
                label=f"network alone ({name}), mean")
    ax.set(xscale="log", yscale="log", xlabel="labels fitted (RCWA solves)",
           ylabel="held-out |t - t_RCWA| / rms|t_i|",
           title=f"supercell surrogates ({rep['held_out_supercells']} held-out supercells)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    e, el = rep["_e"].ravel(), rep["_e_lpa"].ravel()
    _error_histogram(axs[1], e, el, "PEDS", np.percentile(el, 99))
    return save_figure(fig, out)

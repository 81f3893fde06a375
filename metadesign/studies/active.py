"""Active learning of the supercell coupling model (issue #34): new RCWA solves where an ensemble disagrees.

The loop (Pestourie et al., npj Comput. Mater. 2020, with an ensemble's spread as the uncertainty):

1. start from the first ``start`` fitting rows of a table (draws like the design's, :func:`sample_rows`);
2. fit ``members`` coupling models (seeds 0, 1, ...) on the labels so far;
3. predict a pool of candidate supercells drawn the same way (another seed); the spread of the members'
   ``t`` (their standard deviation over the pillars' rms ``|t|``, the larger polarisation) ranks them;
4. solve the ``batch`` most uncertain candidates (the table's truncation and its matched unit cells, in the
   resumable chunks of :func:`metadesign.library.supercells.solve_table`) and add them; repeat.

After every round the ensemble's mean is certified on the held-out rows of a reference table (the
converged one); the same number of solves drawn at random (the table's own next rows) is the baseline.
Every choice is a function of the labels so far (deterministic fits, one thread), and the solves are kept
under content keys: a run killed at any point (SIGKILL included) resumes to the same bytes, whatever the
worker count or scheduler."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..execution import SERIAL, Execution
from ..library.coupling import CouplingConfig, relative_error, unit_rms
from ..library.coupling_net import coupling_t, fit_coupling
from ..library.store import interpolate_t
from ..library.supercells import SupercellTable, matched_unit_harmonics, solve_table
from ..plotting import pyplot, save_figure

__all__ = ["ActiveConfig", "active_learning", "ensemble_spread", "plot_active"]


@dataclass(frozen=True)
class ActiveConfig:
    start: int = 250
    batch: int = 250
    rounds: int = 4
    members: int = 4
    pool: int = 8000
    steps: int = 2000
    weight_decay: float = 1e-3
    model: CouplingConfig = CouplingConfig(hidden=64, layers=3, interaction="environment")


def ensemble_spread(models, widths: np.ndarray, t_units: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The members' mean ``t`` (n, 2) and their spread (n,): the standard deviation of the members' complex
    ``t`` over the pillars' rms ``|t|``, the larger of the two polarisations."""
    preds = np.stack([coupling_t(m, widths, t_units) for m in models])  # (K, n, 2)
    mean = preds.mean(0)
    sd = np.sqrt((np.abs(preds - mean) ** 2).mean(0))
    return mean, (sd / unit_rms(t_units)).max(1)


def _certify(models, lib, ref: SupercellTable) -> dict:
    held = ref.rows(np.flatnonzero(ref.test))
    t_ref, tu = held.lpa_labels(lib)
    mean, _ = ensemble_spread(models, held.widths, tu)
    e = relative_error(mean, t_ref, tu)
    return {"mean": float(e.mean()), "p90": float(np.percentile(e, 90)), "max": float(e.max()),
            "mean_per_pol": e.mean(0).tolist()}


def _fit_members(lib, widths, labels, cfg: ActiveConfig) -> list:
    return [fit_coupling(lib, widths, labels, cfg.model, steps=cfg.steps, seed=s, weight_decay=cfg.weight_decay)[0]
            for s in range(cfg.members)]


def active_learning(table: SupercellTable, reference: SupercellTable, lib, pool_widths: np.ndarray,
                    partial: str | Path, cfg: ActiveConfig = ActiveConfig(), run: Execution = SERIAL) -> dict:
    """Run the loop (module docstring) from ``table``'s fitting rows, candidates ``pool_widths`` (m, 2, 2, 2)
    solved at ``table``'s truncation into ``partial`` (resumable); returns the two learning curves
    (active, random) certified on ``reference``'s held-out rows."""
    import torch

    torch.set_num_threads(1)
    log = run.log
    stack = lib.stack
    nG = int(table.meta["n_harmonics"])
    ns, nu = matched_unit_harmonics(nG + 1, stack)
    unit = nu if table.t_unit is not None else None
    fit_rows = np.flatnonzero(~table.test)
    if len(fit_rows) < cfg.start:
        raise ValueError(f"the table has {len(fit_rows)} fitting rows, the loop starts from {cfg.start}")
    w_all = table.widths[fit_rows]
    lab_all, _ = table.rows(fit_rows).lpa_labels(lib)
    curve_active, curve_random = [], []
    W, L = w_all[:cfg.start], lab_all[:cfg.start]
    chosen = np.zeros(len(pool_widths), bool)
    tu_pool = interpolate_t(lib, pool_widths[..., 0], pool_widths[..., 1])[0]
    for r in range(cfg.rounds + 1):
        t0 = time.perf_counter()
        members = _fit_members(lib, W, L, cfg)
        cert = _certify(members, lib, reference)
        curve_active.append({"solves": len(W), **cert, "fit_seconds": time.perf_counter() - t0})
        n_rand = min(len(W), len(w_all))
        if r == 0:
            curve_random.append(curve_active[0] | {"solves": n_rand})
        else:
            rand = _fit_members(lib, w_all[:n_rand], lab_all[:n_rand], cfg)
            curve_random.append({"solves": n_rand, **_certify(rand, lib, reference)})
        log(f"  round {r}: {len(W)} solves: active {cert['mean']:.4f} (p90 {cert['p90']:.4f}), random "
            f"{curve_random[-1]['mean']:.4f} (p90 {curve_random[-1]['p90']:.4f})")
        if r == cfg.rounds:
            break
        _, spread = ensemble_spread(members, pool_widths, tu_pool)
        spread[chosen] = -np.inf
        pick = np.sort(np.argsort(-spread, kind="stable")[:cfg.batch])
        chosen[pick] = True
        t, _, _, t_unit = solve_table(pool_widths[pick], stack, ns, partial, workers=run.workers, scheduler=run.scheduler,
                                      chunk_size=25, unit_harmonics=unit, log=log)
        new = SupercellTable(pool_widths[pick], t, np.zeros(len(pick), np.int8), np.zeros(len(pick), bool),
                             table.meta, t_unit)
        W = np.concatenate([W, pool_widths[pick]])
        L = np.concatenate([L, new.lpa_labels(lib)[0]])
        curve_active[-1]["next_batch_spread"] = {"max": float(spread[pick].max()), "min": float(spread[pick].min())}
        curve_active[-1]["picked"] = pick.tolist()
    return {"active": curve_active, "random": curve_random, "config": {
        "start": cfg.start, "batch": cfg.batch, "rounds": cfg.rounds, "members": cfg.members, "pool": len(pool_widths),
        "steps": cfg.steps, "model": {"hidden": cfg.model.hidden, "layers": cfg.model.layers,
                                      "interaction": cfg.model.interaction}},
        "members": members}


def plot_active(rep: dict, out: str | Path) -> Path:
    """Held-out mean and p90 error vs RCWA solves, active and random."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.2), constrained_layout=True)
    for name, c in (("active", "C0"), ("random", "C1")):
        n = [r["solves"] for r in rep[name]]
        ax.plot(n, [r["mean"] for r in rep[name]], "o-", color=c, label=f"{name}, mean")
        ax.plot(n, [r["p90"] for r in rep[name]], "s--", color=c, label=f"{name}, p90")
    for g, ls, what in ((0.05, ":", "mean"), (0.10, "-.", "p90")):
        ax.axhline(g, color="0.5", ls=ls, lw=1, label=f"goal, {what} <= {g:g}")
    ax.set(xscale="log", yscale="log", xlabel="RCWA solves (labels fitted)",
           ylabel="held-out |t - t_RCWA| / rms|t_i|",
           title=f"coupling model: active vs random ({rep['config']['members']} members)")
    n = [r["solves"] for r in rep["active"]]
    ax.set_xticks(n, [str(v) for v in n])
    ax.set_xticks([], minor=True)
    ax.legend(fontsize=8)
    return save_figure(fig, out)

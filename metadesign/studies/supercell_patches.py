"""Beyond the periodic 2 x 2 cell: 4 x 4 patches of a design against their four supercells, the neighbour
ring's low fidelity and the overlapping windows (:func:`patch_study`)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..design.store import Design
from ..execution import SERIAL, Execution
from ..library.peds import certified_t, fit_peds, patch_harmonics, patch_windows, ring_couplings
from ..library.supercell import solve_patch, solve_supercell
from ..library.supercells import (
    matched_harmonics,
    matched_unit_harmonics,
    unit_cells,
    solve_table,
)
from ..outputs import Need
from ..plotting import pyplot, save_figure
from ..tasks import TaskFolder, content_key, run_resumable
from ..validation import InputError
from .supercell_errors import _stats

__all__ = ["PatchSettings", "design_patches", "solve_patches", "patch_study", "plot_patches"]


def _patch_task(args) -> tuple[str, dict]:
    """One 4 x 4 patch: its own solve (period 4 p, full problem) and its four 2 x 2 supercells and sixteen
    unit cells at the truncations matched to it."""
    name, w, stack, n_patch, n_super, n_unit = args
    res = solve_patch(w, stack, n_patch)
    sc = np.array([solve_supercell(w[2 * i:2 * i + 2, 2 * j:2 * j + 2], stack, n_super).jones[[0, 1], [0, 1]]
                   for i in range(2) for j in range(2)])
    units = unit_cells(w, stack, n_unit)
    return name, {"t_patch": res.jones[[0, 1], [0, 1]], "cross": np.abs(res.jones[[0, 1], [1, 0]]),
                  "t_super": sc, "t_unit": units, "n_harmonics": np.array([res.n_harmonics])}


def design_patches(design: Design, patches: int, seed: int) -> np.ndarray:
    """(patches, 4, 4, 2) widths (m) of 4 x 4 patches cut from ``design``, aligned to its supercells, all
    sixteen pillars present, drawn with ``seed`` (the same patches for the same seed, whatever the count
    asked: the first ``k`` of a larger draw are the draw of ``k``)."""
    aw = np.stack([design.atoms.wx, design.atoms.wy], 1)
    im = design.index_map
    rng = np.random.default_rng(seed)
    H, W = im.shape[0] // 4, im.shape[1] // 4
    ws = []
    while len(ws) < patches:
        I, J = int(rng.integers(H)), int(rng.integers(W))
        blk = im[4 * I:4 * I + 4, 4 * J:4 * J + 4].astype(np.int64)
        if (blk < len(aw)).all():
            ws.append(aw[blk])
    return np.array(ws)


def solve_patches(ws: np.ndarray, stack, n_harmonics: int, partial: Path,
                  run: Execution = SERIAL) -> tuple[list, int, int]:
    """Each patch of ``ws`` solved periodically at ``n_harmonics`` (requested) with its four supercells and
    sixteen unit cells at the matched truncations (:func:`_patch_task`): ``(results in order, supercell
    request, unit request)``.  One task per patch under ``partial`` (content-keyed: resumable)."""
    ns_patch, ns_super = matched_harmonics(n_harmonics, stack, 4, 2)
    _, nu = matched_unit_harmonics(ns_super, stack)
    names = ["patch-" + content_key(np.ascontiguousarray(w, "<f8"), [ns_patch, ns_super, nu, stack.wavelength,
                                    stack.period, stack.height, stack.n_pillar, stack.n_substrate,
                                    stack.n_superstrate], __version__) for w in ws]
    jobs = {nm: (nm, w, stack, ns_patch, ns_super, nu) for nm, w in zip(names, ws)}
    done, _ = run_resumable(_patch_task, jobs, TaskFolder(partial), workers=run.workers, scheduler=run.scheduler,
                            dask_key="patches", progress=run.progress, log=run.log, unit="patch")
    return [done[nm] for nm in names], ns_super, nu


@dataclass(frozen=True)
class PatchSettings:
    """The patch study's sample and its options (:func:`patch_study`): ``patches`` drawn with ``seed``, solved
    at ``harmonics`` (requested); ``ring_levels``, ``windows`` and ``peds`` as there."""

    patches: int = 8
    seed: int = 0
    harmonics: int = 1300
    ring_levels: tuple = ()
    windows: bool = False
    peds: Any = None

    def __post_init__(self) -> None:
        if self.ring_levels and self.patches < 4:
            raise InputError(f"--ring-levels: calibrating the ring's coefficients needs >= 4 patches, got "
                             f"{self.patches}")


#: memory of one 4 x 4 patch solve per harmonic squared (bytes): 1.2 GB per worker at nG 1289, measured
PATCH_BYTES_PER_NG2 = 1.2e9 / 1289**2


def patch_need(settings: PatchSettings, stack, workers: int) -> Need:
    """What the patch study of ``settings`` asks of the machine, checked before any solve: each ring level a
    low fidelity at or below the patches' own supercell truncation (a level above it would make the ring's
    patches costlier than the truth they approximate; InputError, one line), and the memory of the largest
    patch solve on each of ``workers`` (:class:`~metadesign.outputs.Need`)."""
    ns_patch, ns_super = matched_harmonics(int(settings.harmonics), stack, 4, 2)
    largest = ns_patch - 1
    for h in settings.ring_levels:
        ns_h, _ = matched_unit_harmonics(int(h), stack)
        if ns_h > ns_super:
            raise InputError(f"--ring-levels {h:g}: above the patches' own supercell truncation (nG {ns_super - 1} at "
                             f"--harmonics {settings.harmonics}): the ring's low fidelity must be cheaper than the "
                             f"truth (levels <= {settings.harmonics // 4})")
        largest = max(largest, patch_harmonics(int(h), stack)[0] - 1)
    return Need(memory=max(1, workers) * PATCH_BYTES_PER_NG2 * largest**2,
                what=f"4 x 4 patch solves at nG {largest} on {max(1, workers)} workers: fewer -j or a lower --harmonics")


@dataclass(frozen=True)
class _Solved:
    """The solved patches: widths ``ws`` (n, 4, 4, 2), their four supercells' ``t`` (n, 4, 2), their ring
    terms ``target`` (n, 2: patch - mean of its supercells) and the sixteen pillars' rms |t| (n, 2)."""

    ws: np.ndarray
    tsc: np.ndarray
    target: np.ndarray
    rms: np.ndarray


def patch_study(design: Design, lib, settings: PatchSettings, partial: Path, run: Execution = SERIAL) -> dict:
    """Beyond the periodic 2 x 2 cell (issue #34 section 2): ``patches`` 4 x 4 patches cut from ``design``
    (aligned to its supercells, all sixteen pillars present, drawn with ``seed``), each solved as a
    periodic 4 x 4 cell (2.8 um at the paper's pitch: each supercell sees other supercells around it, as
    in the device) at ``n_harmonics`` (requested), against the mean of its four 2 x 2 supercells solved
    periodically at the matched truncation (the 2 x 2 picture every coupling model here assumes), beside
    the LPA at the unit cells' matched truncation.  Errors in units of the sixteen pillars' rms ``|t|``.
    Resumable: one task per patch under ``partial`` (content-keyed).

    ``ring_levels``: requested supercell truncations of a neighbour-ring low fidelity
    (:func:`~metadesign.library.peds.ring_couplings`: each patch and its four supercells solved again at
    matched low truncations): the report's ``ring`` section gives how far each level's ring term and their
    calibrated combination (one complex coefficient per level, both polarisations; fitted leaving each patch
    out in turn, so every patch's figure is held out) fall from the patch solve's, and the coefficients
    fitted on all patches.

    ``windows``: the overlapping-window ring (:func:`~metadesign.library.peds.window_ring`): each patch as the
    mean of its sixteen 2 x 2 windows (:func:`~metadesign.library.peds.patch_windows`), the twelve that
    straddle its supercells solved at the supercells' matched truncation (``windows_exact``: the idea
    itself) and all sixteen under the certified model ``peds`` (default: the library's; ``windows_peds``:
    what the device path uses); each how far its ring term falls from the patch solve's."""
    st = settings
    patches, seed, ring_levels = st.patches, st.seed, sorted(set(st.ring_levels))
    stack = lib.stack
    ws = design_patches(design, patches, seed)
    t0 = time.perf_counter()
    done, ns_super, nu = solve_patches(ws, stack, st.harmonics, partial, run)
    seconds = time.perf_counter() - t0
    tp = np.array([r["t_patch"] for r in done])  # (n, 2)
    tsc = np.array([r["t_super"] for r in done])  # (n, 4, 2)
    tu = np.array([r["t_unit"] for r in done])  # (n, 4, 4, 2)
    rms = np.sqrt((np.abs(tu) ** 2).mean((1, 2)))  # (n, 2)
    lpa = tu.mean((1, 2))
    two = tsc.mean(1)
    beyond = np.abs(tp - two) / rms
    solved = _Solved(ws, tsc, tp - two, rms)
    ring = _ring_section(solved, stack, ring_levels, partial, run) if ring_levels else {}
    per_patch = {"beyond_2x2": beyond.tolist(), **ring.pop("per_patch", {})}
    if st.windows:
        ring.update(_window_section(solved, lib, ns_super, partial, st.peds, run))
        per_patch.update(ring.pop("per_patch"))
    if ring:
        ring["per_patch"] = per_patch
    return {"patches": patches, "seed": seed, "n_harmonics": {"patch": int(done[0]["n_harmonics"][0]),
                                                              "supercell": ns_super - 1, "unit": nu - 1},
            "beyond_2x2": _stats(beyond), "beyond_2x2_mean_both": float(beyond.mean()),
            "beyond_2x2_p90_both": float(np.percentile(beyond, 90)),
            "lpa_vs_patch": _stats(np.abs(tp - lpa) / rms), "two_by_two_vs_lpa": _stats(np.abs(two - lpa) / rms),
            "cross_polarisation_max": float(np.array([r["cross"] for r in done]).max()),
            "solve_seconds": seconds, "workers": run.workers,
            "metric": "|t| differences over the sixteen pillars' rms |t| (matched unit cells), per polarisation",
            **ring}


def _ring_section(solved: _Solved, stack, levels, partial, run: Execution) -> dict:
    """The neighbour-ring low fidelity at ``levels`` against the patches' own ring terms (n, 2)."""
    ws, target, rms, workers = solved.ws, solved.target, solved.rms, run.workers
    t0 = time.perf_counter()
    c = ring_couplings(ws, stack, levels, Path(partial), workers=workers, scheduler=run.scheduler,
                       progress=run.progress, log=run.log)
    seconds = time.perf_counter() - t0
    n = len(ws)
    raw = {str(h): _stats(np.abs(target - c[k]) / rms) for k, h in enumerate(levels)}
    held = np.zeros_like(target)
    for i in range(n):  # leave one patch out: every residual is a held-out one
        keep = np.arange(n) != i
        held[i] = np.tensordot(fit_peds(c[:, keep], target[keep]), c[:, i], axes=1)
    e_held = np.abs(target - held) / rms
    coef = fit_peds(c, target)
    return {"per_patch": {"ring_low_fidelity": e_held.tolist()},
            "ring": {"levels": [int(h) for h in levels], "raw_per_level": raw, "calibrated_held_out": _stats(e_held),
                     "calibrated_held_out_mean_both": float(e_held.mean()),
                     "calibrated_held_out_p90_both": float(np.percentile(e_held, 90)),
                     "coefficients": [[float(a.real), float(a.imag)] for a in coef],
                     "seconds": seconds, "seconds_per_patch_core": seconds * max(1, workers) / max(1, n),
                     "metric": "|ring term (patch - mean of its 2 x 2 supercells), low fidelity calibrated - "
                               "the patch solve's| over the sixteen pillars' rms |t|"}}


ALIGNED = [0, 2, 8, 10]  # the supercells among a patch's sixteen windows (patch_windows), in _patch_task's order


def _window_section(solved: _Solved, lib, ns_super, partial, peds, run: Execution) -> dict:
    """The overlapping-window ring of each patch against its patch solve's ring term (n, 2)."""
    ws, tsc, target, rms = solved.ws, solved.tsc, solved.target, solved.rms
    workers, scheduler, log = run.workers, run.scheduler, run.log
    n = len(ws)
    win = patch_windows(ws)  # (n, 16, 2, 2, 2)
    odd = [k for k in range(16) if k not in ALIGNED]
    t0 = time.perf_counter()
    log(f"  overlapping windows: {n * len(odd)} straddling windows at nG {ns_super - 1}, then all {16 * n} under "
        "the certified model ...")
    t_odd, _, _, _ = solve_table(win[:, odd].reshape(-1, 2, 2, 2), lib.stack, ns_super, Path(partial) / "windows",
                                 workers=workers, scheduler=scheduler, chunk_size=4, log=log)
    exact = (np.asarray(tsc).sum(1) + t_odd.reshape(n, len(odd), 2).sum(1)) / 16 - np.asarray(tsc).mean(1)
    t_exact = time.perf_counter() - t0
    t_p = certified_t(lib, win.reshape(-1, 2, 2, 2), Path(partial) / "peds-windows", peds, workers=workers,
                      scheduler=scheduler).reshape(n, 16, 2)
    ring_p = t_p.mean(1) - t_p[:, ALIGNED].mean(1)

    def stats(ring):
        e = np.abs(target - ring) / rms
        return {**_stats(e), "mean_both": float(e.mean()), "p90_both": float(np.percentile(e, 90))}

    def rel(z):  # (n, 2) complex -> [[re, im] per polarisation] per patch, in units of the pillars' rms |t|
        return np.stack([(z / rms).real, (z / rms).imag], -1).tolist()

    return {"per_patch": {"windows_exact": (np.abs(target - exact) / rms).tolist(),
                          "windows_peds": (np.abs(target - ring_p) / rms).tolist(),
                          "ring_term": rel(target), "ring_windows_peds": rel(ring_p)},
            "windows_exact": {**stats(exact), "seconds": t_exact, "supercell_n_harmonics": ns_super - 1},
            "windows_peds": {**stats(ring_p), "seconds": time.perf_counter() - t0 - t_exact},
            "windows_metric": "|ring term by overlapping windows (mean of the patch's sixteen 2 x 2 windows - mean "
                              "of its four supercells) - the patch solve's| over the sixteen pillars' rms |t|"}


PATCH_MODELS = {"beyond_2x2": ("every 2 x 2 model (no ring)", "C3"),
                "ring_low_fidelity": ("patch low fidelity, calibrated (held out)", "C2"),
                "windows_exact": ("overlapping windows, exact solves", "C0"),
                "windows_peds": ("overlapping windows, PEDS", "C1")}


def plot_patches(rep: dict, out: Path) -> Path:
    """The patch study at a glance: the distribution of what each way of seeing the neighbour ring leaves of
    it (per patch and polarisation, in units of the pillars' rms |t|; the goal's mean and p90 as lines),
    and the patch solve's ring term against the overlapping windows' under PEDS (real and imaginary parts)."""
    plt = pyplot()
    pp = rep.get("per_patch", {})
    two = "ring_term" in pp
    fig, axs = plt.subplots(1, 2 if two else 1, figsize=(11 if two else 6, 4.2), constrained_layout=True,
                            squeeze=False)
    ax = axs[0, 0]
    top = 0.0
    for k, (name, colour) in PATCH_MODELS.items():
        if k in pp:
            e = np.sort(np.ravel(pp[k]))
            top = max(top, e.max())
            ax.step(e, np.arange(1, len(e) + 1) / len(e), where="post", color=colour,
                    label=f"{name}: {e.mean():.3f} / {np.percentile(e, 90):.3f}")
    ax.axvline(0.05, color="0.5", ls=":", lw=1, label="goal: mean 0.05")
    ax.axvline(0.10, color="0.5", ls="--", lw=1, label="goal: p90 0.10 (where the curves cross 0.9)")
    ax.axhline(0.9, color="0.8", lw=0.8)
    ax.set(xlabel="|ring term left| / rms|t_i| (per patch and polarisation)", ylabel="fraction of patches",
           xlim=(0, 1.05 * top), ylim=(0, 1.02), title=f"{rep['patches']} patches: what each model leaves of the ring (mean / p90)")
    ax.legend(fontsize=7, loc="lower right")
    if two:
        ax = axs[0, 1]
        t, m = np.asarray(pp["ring_term"]), np.asarray(pp["ring_windows_peds"])  # (n, 2 pol, 2 re/im)
        for pol, marker in ((0, "o"), (1, "s")):
            for part, colour in ((0, "C0"), (1, "C1")):
                ax.plot(t[:, pol, part], m[:, pol, part], marker, ms=4, color=colour, alpha=0.7,
                        label=f"{'xy'[pol]}-pol, {('real', 'imaginary')[part]} part")
        lim = 1.1 * max(np.abs(t).max(), np.abs(m).max())
        ax.plot([-lim, lim], [-lim, lim], color="0.5", lw=0.8)
        ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel="ring term, patch solve (/ rms|t_i|)",
               ylabel="ring term, overlapping windows under PEDS", title="the ring, solved and modelled")
        ax.legend(fontsize=7)
    return save_figure(fig, out)

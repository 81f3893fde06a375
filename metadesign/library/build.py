"""Library sweep: convergence certification, parallel resumable build.

Work is split into chunks of cells; each finished chunk is written atomically
into ``<output>.partial/`` (:func:`metadesign.execution.scratch_path`; the folder carries the scratch
marker from its first moment).  A killed build resumes from the chunks on disk
(only those made with the same recipe and code version are reused) and the
final library is written atomically, after which the partial folder is
removed.  Workers are spawned processes with single-threaded BLAS.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .. import __version__
from ..config import InputError
from ..execution import scratch_path
from ..optics.phase import wrap
from ..parallel import WorkerPool
from ..tasks import TaskFolder, content_key, run_resumable
from .rcwa import SolverSettings, Stack, solve_cell
from .recipe import LibraryRecipe
from .store import UnitCellLibrary, save_library
from .supercell import solve_tapered

__all__ = ["build_library", "certify_convergence", "ConvergenceReport", "solve_cells"]


@dataclass(frozen=True)
class ConvergenceReport:
    n_harmonics: int
    reference_n_harmonics: int
    max_phase_change_rad: float
    max_T0_change: float
    tolerance_rad: float
    per_cell: tuple  # ((wx_um, wy_um, dphi_x, dphi_y), ...)

    @property
    def passed(self) -> bool:
        return self.max_phase_change_rad <= self.tolerance_rad

    def to_dict(self) -> dict:
        return {
            "n_harmonics": self.n_harmonics,
            "reference_n_harmonics": self.reference_n_harmonics,
            "max_phase_change_rad": self.max_phase_change_rad,
            "max_T0_change": self.max_T0_change,
            "tolerance_rad": self.tolerance_rad,
            "passed": self.passed,
            "per_cell": [list(c) for c in self.per_cell],
        }


def _solve_chunk(args) -> tuple[int, dict]:
    key, cells, stack, settings = args
    return key, _pack([solve_cell(wx, wy, stack, settings) for wx, wy in cells])


def _pack(res) -> dict:
    return {
        "jones": np.array([r.jones for r in res]),
        "T0": np.array([r.T0 for r in res]),
        "T_total": np.array([r.T_total for r in res]),
        "R_total": np.array([r.R_total for r in res]),
        "n_harmonics": np.array([r.n_harmonics for r in res]),
    }


def _solve_chunk_axes(args) -> tuple[int, dict]:
    """Cells ``(wx, wy, height, sidewall_deg)``: a vertical pillar at 90 degrees (the library's own solver),
    else a tapered one as ``slices`` slices."""
    from dataclasses import replace

    key, cells, stack, settings, slices = args
    res = []
    for wx, wy, h, a in cells:
        st = replace(stack, height=h)
        res.append(solve_cell(wx, wy, st, settings) if a == 90.0 else solve_tapered(wx, wy, a, slices, st, settings))
    return key, _pack(res)


def certify_slices(recipe: LibraryRecipe, pool=None) -> dict:
    """Slice-count convergence of tapered pillars: the check cells at the smallest sidewall angle and the
    tallest height, ``slices`` vs ``reference_slices``."""
    fa = recipe.fab_axes
    a, h = min(fa.sidewalls), max(fa.heights)
    if a == 90.0:
        return {"slices": fa.slices, "reference_slices": fa.reference_slices, "max_phase_change_rad": 0.0,
                "angle_deg": a, "height_m": h, "passed": True, "note": "no tapered pillar in the sweep"}
    cells = [(wx, wy, h, a) for wx, wy in recipe.check_cells]
    jobs = [(0, cells, recipe.stack, recipe.settings, fa.slices), (1, cells, recipe.stack, recipe.settings,
                                                                   fa.reference_slices)]
    out = dict((pool.map if pool is not None else map)(_solve_chunk_axes, jobs))
    ja, jb = out[0]["jones"], out[1]["jones"]
    d = np.abs(wrap(np.angle(ja[:, [0, 1], [0, 1]]) - np.angle(jb[:, [0, 1], [0, 1]])))
    return {"slices": fa.slices, "reference_slices": fa.reference_slices, "max_phase_change_rad": float(d.max()),
            "max_T0_change": float(np.abs(out[0]["T0"] - out[1]["T0"]).max()), "angle_deg": a, "height_m": h,
            "tolerance_rad": recipe.tolerance, "passed": bool(d.max() <= recipe.tolerance)}


def solve_cells(cells: Sequence[tuple[float, float]], stack: Stack, settings,
                workers: int = 1, pool: "WorkerPool | None" = None) -> dict:
    """Solve a list of (wx, wy) cells; returns stacked result arrays in order.

    ``settings`` is one :class:`SolverSettings` or one per cell; ``pool`` (kept
    open) reuses a caller's workers instead of starting new ones."""
    per_cell = settings if isinstance(settings, (list, tuple)) else [settings] * len(cells)
    own = pool is None
    pool = WorkerPool(workers) if own else pool
    try:
        jobs = [(i, [c], stack, s) for i, (c, s) in enumerate(zip(cells, per_cell))]
        out = dict(pool.map(_solve_chunk, jobs))
    finally:
        if own:
            pool.close()
    return {k: np.concatenate([out[i][k] for i in range(len(cells))]) for k in out[0]}


def certify_convergence(recipe: LibraryRecipe, workers: int = 1, pool: "WorkerPool | None" = None) -> ConvergenceReport:
    """Solve the check cells at the recipe's setting and at the reference one (one batch)."""
    cells = list(recipe.check_cells)
    ref_settings = SolverSettings(recipe.reference_n_harmonics, recipe.settings.truncation,
                                  recipe.settings.factorization, recipe.settings.use_symmetry)
    k = len(cells)
    both = solve_cells(cells + cells, recipe.stack, [recipe.settings] * k + [ref_settings] * k, workers, pool)
    a = {key: v[:k] for key, v in both.items()}
    b = {key: v[k:] for key, v in both.items()}
    ja, jb = a["jones"], b["jones"]
    dphi = np.abs(wrap(np.angle(ja[:, [0, 1], [0, 1]]) - np.angle(jb[:, [0, 1], [0, 1]])))
    dT = np.abs(a["T0"] - b["T0"])
    per = tuple((round(wx * 1e6, 6), round(wy * 1e6, 6), float(d[0]), float(d[1]))
                for (wx, wy), d in zip(cells, dphi))
    return ConvergenceReport(
        n_harmonics=int(a["n_harmonics"][0]),
        reference_n_harmonics=int(b["n_harmonics"][0]),
        max_phase_change_rad=float(dphi.max()),
        max_T0_change=float(dT.max()),
        tolerance_rad=recipe.tolerance,
        per_cell=per,
    )


def _unique_cells(widths: np.ndarray) -> list[tuple[int, int]]:
    """(i, j) with i <= j: the mirror cell (j, i) follows from symmetry."""
    n = len(widths)
    return [(i, j) for i in range(n) for j in range(i, n)]


def _build_key(recipe: LibraryRecipe) -> str:
    """What shapes the solved cells: the recipe without its name and convergence check, and the version."""
    d = recipe.to_dict()
    d.pop("name")
    d.pop("convergence")
    return content_key(d, __version__)


def build_library(
    recipe: LibraryRecipe,
    output: str | Path,
    *,
    workers: int = 2,
    chunk_size: int = 32,
    allow_unconverged: bool = False,
    progress: Callable[[int, int], None] | None = None,
    log: Callable[[str], None] = lambda s: None,
    _stop_after_chunks: int | None = None,
    scheduler: str | None = None,
) -> tuple[UnitCellLibrary, dict]:
    """Build (or resume) the library for ``recipe`` into ``output``.

    Returns the library and a report dict.  ``_stop_after_chunks`` simulates a
    kill (tests): the build raises ``KeyboardInterrupt`` after that many chunks.
    """
    output = Path(output)
    t_start = time.perf_counter()
    log(f"convergence check on {len(recipe.check_cells)} cells "
        f"(nG {recipe.settings.n_harmonics} vs {recipe.reference_n_harmonics}) ...")
    pool = WorkerPool(workers)  # one set of workers for the check and the sweep
    try:
        return _build(recipe, output, pool, workers, chunk_size, allow_unconverged, progress, log,
                      _stop_after_chunks, t_start, scheduler)
    finally:
        pool.close()


def _assemble(chunks, done: dict, n: int, extra: tuple):
    """The (n, n[, heights, angles]) arrays from the solved chunks (cells with wx <= wy), mirrored across
    the diagonal; and the set of harmonic counts the solver used."""
    jones = np.zeros((n, n, *extra, 2, 2), complex)
    T0 = np.zeros((n, n, *extra, 2))
    Tt = np.zeros((n, n, *extra, 2))
    Rt = np.zeros((n, n, *extra, 2))
    nG_actual = set()
    swap = [1, 0]
    for k, cells in enumerate(chunks):
        r = done[k]
        nG_actual.update(int(v) for v in r["n_harmonics"])
        for c, cell in enumerate(cells):
            i, j = cell[:2]
            ax = tuple(cell[2:])
            jones[(i, j, *ax)] = r["jones"][c]
            T0[(i, j, *ax)], Tt[(i, j, *ax)], Rt[(i, j, *ax)] = r["T0"][c], r["T_total"][c], r["R_total"][c]
            # mirror across the diagonal: t_x(wx, wy) = t_y(wy, wx), t_xy <-> t_yx (a taper is the same on
            # both axes, so this holds at every height and angle)
            jones[(j, i, *ax)] = r["jones"][c][np.ix_(swap, swap)]
            T0[(j, i, *ax)], Tt[(j, i, *ax)], Rt[(j, i, *ax)] = (r["T0"][c][swap], r["T_total"][c][swap],
                                                               r["R_total"][c][swap])
    return jones, T0, Tt, Rt, nG_actual


def _build(recipe, output, pool, workers, chunk_size, allow_unconverged, progress, log, _stop_after_chunks,
           t_start, scheduler=None):
    conv = certify_convergence(recipe, workers, pool)
    log(f"  max phase change {conv.max_phase_change_rad:.4f} rad "
        f"(tolerance {conv.tolerance_rad:g}), max T0 change {conv.max_T0_change:.2e}")
    if not conv.passed and not allow_unconverged:
        raise InputError(
            f"convergence check failed: phase changes by {conv.max_phase_change_rad:.4f} rad between "
            f"nG {conv.n_harmonics} and {conv.reference_n_harmonics} (tolerance {conv.tolerance_rad:g} rad); "
            "raise solver.n_harmonics or pass --allow-unconverged"
        )

    slice_conv = None
    if recipe.fab_axes is not None:
        slice_conv = certify_slices(recipe, pool)
        log(f"  tapered pillars: {recipe.fab_axes.slices} vs {recipe.fab_axes.reference_slices} slices change the "
            f"phase by {slice_conv['max_phase_change_rad']:.4f} rad")
        if not slice_conv["passed"] and not allow_unconverged:
            raise InputError(
                f"slice convergence check failed: phase changes by {slice_conv['max_phase_change_rad']:.4f} rad "
                f"between {recipe.fab_axes.slices} and {recipe.fab_axes.reference_slices} slices (tolerance "
                f"{recipe.tolerance:g} rad); raise fab_axes.slices or pass --allow-unconverged")
    widths = recipe.widths
    n = len(widths)
    pairs = _unique_cells(widths)
    axes = [(None, None)] if recipe.fab_axes is None else [
        (ih, ia) for ih in range(len(recipe.fab_axes.heights)) for ia in range(len(recipe.fab_axes.sidewalls))]
    if recipe.fab_axes is not None:
        pairs = [(i, j, ih, ia) for ih, ia in axes for i, j in pairs]
    chunks = [pairs[k:k + chunk_size] for k in range(0, len(pairs), chunk_size)]
    part_dir = scratch_path(output)
    folder = TaskFolder(part_dir, _build_key(recipe), log, chunk_size=chunk_size, n_chunks=len(chunks))
    chunk_size = int(folder.manifest().get("chunk_size", chunk_size))  # a resumed build keeps its chunking
    chunks = [pairs[k:k + chunk_size] for k in range(0, len(pairs), chunk_size)]
    names = [f"chunk-{k:05d}" for k in range(len(chunks))]
    n_cells_total = len(pairs)
    t_sweep = time.perf_counter()
    if recipe.fab_axes is None:
        jobs = {names[k]: (names[k], [(widths[i], widths[j]) for i, j in chunks[k]], recipe.stack, recipe.settings)
                for k in range(len(chunks))}
        fn = _solve_chunk
    else:
        fa = recipe.fab_axes
        jobs = {names[k]: (names[k], [(widths[i], widths[j], fa.heights[ih], fa.sidewalls[ia])
                                      for i, j, ih, ia in chunks[k]], recipe.stack, recipe.settings, fa.slices)
                for k in range(len(chunks))}
        fn = _solve_chunk_axes
    size = {names[k]: len(chunks[k]) for k in range(len(chunks))}
    res, _ = run_resumable(fn, jobs, folder, pool=pool, scheduler=scheduler, weight=size.__getitem__,
                           progress=progress, log=log, unit="cell", stop_after=_stop_after_chunks)
    done = {k: res[names[k]] for k in range(len(chunks))}
    sweep_s = time.perf_counter() - t_sweep

    extra = () if recipe.fab_axes is None else (len(recipe.fab_axes.heights), len(recipe.fab_axes.sidewalls))
    jones, T0, Tt, Rt, nG_actual = _assemble(chunks, done, n, extra)
    fab = None
    if recipe.fab_axes is not None:
        fa = recipe.fab_axes
        fab = {"heights": np.array(fa.heights), "sidewalls": np.array(fa.sidewalls), "jones": jones, "T0": T0,
               "T_total": Tt, "R_total": Rt}
        ih = int(np.argmin(np.abs(np.array(fa.heights) - recipe.stack.height)))
        ia = fa.sidewalls.index(90.0)
        # the main arrays hold the nominal slice (stack height, vertical walls): every 2-D consumer is unchanged
        jones, T0, Tt, Rt = (a[:, :, ih, ia] for a in (jones, T0, Tt, Rt))
    st = recipe.stack
    meta = {
        "version": __version__,
        "recipe": recipe.to_dict(),
        "stack": {
            "wavelength_m": st.wavelength, "period_m": st.period, "height_m": st.height,
            "n_pillar": st.n_pillar, "n_substrate": st.n_substrate, "n_superstrate": st.n_superstrate,
            "materials": {"pillar": "a-Si", "substrate": "fused silica", "superstrate": "air"},
        },
        "solver": {
            "name": "grcwa", "factorization": recipe.settings.factorization.value,
            "truncation": recipe.settings.truncation.value,
            "use_symmetry": recipe.settings.use_symmetry,
            "n_harmonics_requested": recipe.settings.n_harmonics,
            "n_harmonics": sorted(nG_actual)[0] if len(nG_actual) == 1 else sorted(nG_actual),
            "incidence": "normal, from the substrate",
        },
        "convergence": conv.to_dict(),
        "convention": {
            "time": "exp(-i omega t)",
            "field_phase": "exp(+i phi)",
            "t": "0th-order E at pillar top (z = h) over incident E at z = 0, times exp(-i k0 n_sup h); "
                 "no pillar gives 2 n_sub / (n_sub + n_sup)",
            "jones_index": "[out, in], 0 = x-pol (paper TE), 1 = y-pol (paper TM)",
            "array_index": "[i_wx, i_wy]",
        },
        "symmetry_used": "t_x(wx, wy) = t_y(wy, wx)",
    }
    if fab is not None:
        meta["fab_axes"] = {**recipe.fab_axes.to_dict(), "slice_convergence": slice_conv,
                            "taper": "width at mid-height = the nominal width; w(z) = w + 2 (h/2 - z) cot(angle); "
                                     "slices of equal thickness at their own mid-height width",
                            "nominal_slice": "the main arrays = height_um == stack height, sidewall 90 deg"}
    lib = UnitCellLibrary(widths.copy(), widths.copy(), jones, T0, Tt, Rt, meta, fab=fab)
    save_library(output, lib)
    folder.remove()
    report = {
        "output": str(output),
        "cells": n * n * int(np.prod(extra)) if extra else n * n,
        "cells_solved": n_cells_total,
        "sweep_seconds": sweep_s,
        "total_seconds": time.perf_counter() - t_start,
        "workers": workers,
        "convergence": conv.to_dict(),
    }
    if slice_conv is not None:
        report["slice_convergence"] = slice_conv
    return lib, report

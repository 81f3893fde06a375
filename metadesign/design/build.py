"""Tile-wise discretization of a full design in bounded memory."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .. import jit
from .discretize import AtomTable, Metric, NearestAtom, optimal_offsets
from .kernel import lens_table, map_rows_kernel
from .phase import SupercellSpec, aperture_mask, design_phase, wrap

__all__ = ["DesignResult", "DesignStream", "map_rows", "map_rows_numpy", "accumulate", "discretize_design", "empty_index", "OFFSET_GRID"]

OFFSET_GRID = 256  # resolution of the constant-offset search (2 pi / 256 = 0.025 rad)


def empty_index(n_atoms: int, needs_empty: bool):
    """(dtype, sentinel) of the index map.  The sentinel (the dtype's max value)
    marks cells without a pillar and exists only when the design has such
    cells (circular clear aperture); uint8 whenever it fits."""
    n = n_atoms + (1 if needs_empty else 0)
    dtype = np.uint8 if n <= 256 else np.uint16
    return dtype, (int(np.iinfo(dtype).max) if needs_empty else None)


@dataclass
class DesignResult:
    index_map: np.ndarray  # [iy, ix] atom index, sentinel = no pillar (outside a circular aperture)
    offsets: tuple[float, float]  # constant added to the x-pol / y-pol design phase (rad)
    empty: int | None  # the no-pillar sentinel, if any
    metrics: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)  # timings (kept out of the files: same inputs, same bytes)


def _sample_rows(n: int, target: int = 1024) -> np.ndarray:
    """Rows/columns for the offset histogram: an odd stride keeps every
    supercell sub-lattice equally represented."""
    s = max(1, n // target)
    if s % 2 == 0:
        s += 1
    return np.arange(0, n, s)


def _phase_sample(spec: SupercellSpec, idx: np.ndarray):
    """Design phases (no offsets) on the sampled sub-grid ``idx x idx``, inside the clear aperture."""
    mask = aperture_mask(spec, idx, idx)
    keep = np.ones((idx.size, idx.size), bool) if mask is None else mask
    return (design_phase(spec, 0, idx, idx, wrapped=False)[keep],
            design_phase(spec, 1, idx, idx, wrapped=False)[keep])


def map_rows(spec: SupercellSpec, atoms: AtomTable, mapper, offsets, dtype, empty, r0: int, r1: int,
             c0: int = 0, c1: int | None = None):
    """Rows ``r0:r1`` (columns ``c0:c1``) of the index map and their error sums ``(sse, peak, eff,
    count, used)``: the kernel of the discretizer, whole-array or tiled.  Compiled
    (:mod:`metadesign.design.kernel`) for the phase metric, else (or without numba) its numpy twin
    :func:`map_rows_numpy`: the same index map and sums, bit for bit."""
    c1 = spec.n_cells if c1 is None else c1
    if not (jit.enabled() and mapper.metric is Metric.PHASE):
        return map_rows_numpy(spec, atoms, mapper, offsets, dtype, empty, r0, r1, c0, c1)
    iy, ix = np.arange(r0, r1), np.arange(c0, c1)
    lenses = lens_table(spec)
    phases = None if lenses is not None else (design_phase(spec, 0, iy, ix, wrapped=False),
                                              design_phase(spec, 1, iy, ix, wrapped=False))
    mask = aperture_mask(spec, iy, ix) if spec.aperture_wkt else None
    return map_rows_kernel(spec, atoms, mapper, offsets, dtype, empty, r0, r1, c0, c1, lenses, phases, mask)


def map_rows_numpy(spec: SupercellSpec, atoms: AtomTable, mapper, offsets, dtype, empty, r0: int, r1: int,
                   c0: int = 0, c1: int | None = None):
    """:func:`map_rows` in numpy (the reference of the compiled kernel, and its path for other metrics)."""
    c1 = spec.n_cells if c1 is None else c1
    iy, ix = np.arange(r0, r1), np.arange(c0, c1)
    ax = design_phase(spec, 0, iy, ix, offsets[0])
    ay = design_phase(spec, 1, iy, ix, offsets[1])
    k = mapper(ax, ay)
    mask = aperture_mask(spec, iy, ix)
    if mask is not None:
        k_in, ax, ay = k[mask], ax[mask], ay[mask]
    else:
        k_in = k.ravel()
        ax, ay = ax.ravel(), ay.ravel()
    ph = atoms.phase
    sse, peak, eff = np.zeros(2), np.zeros(2), np.zeros(2)
    for p, a in ((0, ax), (1, ay)):
        e = wrap(ph[k_in, p] - a)
        sse[p] = float(np.sum(e * e))  # numpy's pairwise sum: no BLAS threads, the same bits in any process
        if e.size:
            peak[p] = float(np.abs(e).max())
        eff[p] = float(atoms.T0[k_in, p].sum())
    used = np.bincount(k_in, minlength=len(atoms))[:len(atoms)]
    blk = k.astype(dtype)
    if mask is not None:
        blk[~mask] = empty
    return blk, (sse, peak, eff, int(k_in.size), used)


def accumulate(total, part):
    """Sum two ``(sse, peak, eff, count, used)`` in order (the same floats, whatever the tiling of the
    rows into tasks: sums run in row order)."""
    sse, peak, eff, count, used = total
    s2, p2, e2, c2, u2 = part
    return sse + s2, np.maximum(peak, p2), eff + e2, count + c2, used + u2


class DesignStream:
    """The discretization of a design as a stream of ``tile_rows``-row blocks of the index map
    (iterate once): peak memory is one block, whatever the aperture.  After the iteration
    :meth:`result` has the metrics; :func:`discretize_design` is this stream collected."""

    def __init__(self, spec: SupercellSpec, atoms: AtomTable, metric: Metric = Metric.PHASE,
                 optimise_offsets: bool = True, tile_rows: int = 256,
                 progress: Callable[[int, int], None] | None = None):
        t0 = time.perf_counter()
        self.t0, self.spec, self.atoms, self.metric = t0, spec, atoms, metric
        self.tile_rows, self.progress = tile_rows, progress
        n = spec.n_cells
        self.mapper = mapper = NearestAtom(atoms, metric)
        self.t_lut = time.perf_counter() - t0
        # --- constant offsets (one FFT correlation on a sub-sampled histogram)
        idx = _sample_rows(n)
        spx, spy = _phase_sample(spec, idx)
        offsets = (0.0, 0.0)
        G = OFFSET_GRID
        if optimise_offsets:
            hx = np.floor((wrap(spx) + np.pi) * (G / (2 * np.pi))).astype(np.int64) % G
            hy = np.floor((wrap(spy) + np.pi) * (G / (2 * np.pi))).astype(np.int64) % G
            hist = np.bincount(hx * G + hy, minlength=G * G).reshape(G, G).astype(np.float64)
            cx, cy, _ = optimal_offsets(hist, mapper.min_cost_grid(G))
            offsets = (cx, cy)  # adding i * step to every phase moves bin u to bin u + i
        self.offsets = offsets
        # --- the other metric's figures on the same sample, for comparison
        comparison = {}
        for m in Metric:
            mp = mapper if m is metric else NearestAtom(atoms, m)
            ax, ay = wrap(spx + offsets[0]), wrap(spy + offsets[1])
            k = mp(ax, ay)
            ph = atoms.phase
            ex, ey = wrap(ph[k, 0] - ax), wrap(ph[k, 1] - ay)
            comparison[m.value] = {
                "rmse_rad": [float(np.sqrt(np.mean(ex**2))), float(np.sqrt(np.mean(ey**2)))],
                "mean_T0": [float(atoms.T0[k, 0].mean()), float(atoms.T0[k, 1].mean())],
                "sampled_cells": int(ax.size),
            }
        self.comparison = comparison
        self.dtype, self.empty = empty_index(len(atoms), spec.bounded)
        self.shape = (n, n)
        self._done = False
        self.t_map = time.perf_counter()

    def finish(self, stats) -> None:
        """Take the summed ``(sse, peak, eff, count, used)`` of every row, computed elsewhere (the tiled
        path's workers with :func:`map_rows`, summed with :func:`accumulate` in row order)."""
        self._stats, self._done = tuple(stats), True

    def __iter__(self):
        if self._done:
            raise RuntimeError("a DesignStream is iterated once")
        spec, atoms, n = self.spec, self.atoms, self.spec.n_cells
        sse, peak, eff = np.zeros(2), np.zeros(2), np.zeros(2)
        used = np.zeros(len(atoms), np.int64)
        count = 0
        offsets, empty = self.offsets, self.empty
        self.t_map = time.perf_counter()
        for r0 in range(0, n, self.tile_rows):
            r1 = min(n, r0 + self.tile_rows)
            blk, st = map_rows(spec, atoms, self.mapper, offsets, self.dtype, empty, r0, r1)
            sse, peak, eff, count, used = accumulate((sse, peak, eff, count, used), st)
            yield r0, blk
            if self.progress:
                self.progress(r1, n)
        self._stats = (sse, peak, eff, count, used)
        self._done = True

    def result(self, index_map: np.ndarray | None = None) -> DesignResult:
        if not self._done:
            raise RuntimeError("iterate the DesignStream before asking for its result")
        sse, peak, eff, count, used = self._stats
        atoms = self.atoms
        metrics = {
            "metric": self.metric.value,
            "n_cells": int(self.spec.n_cells ** 2),
            "n_cells_in_aperture": int(count),
            "rmse_rad": (np.sqrt(sse / max(count, 1))).tolist(),
            "peak_error_rad": peak.tolist(),
            "mean_T0": (eff / max(count, 1)).tolist(),
            "phase_offsets_rad": list(self.offsets),
            "n_atoms": int(len(atoms)),
            "n_atoms_used": int((used > 0).sum()),
            "n_empty_bins": atoms.n_empty_bins,
            "n_kept_library_cells": atoms.n_kept_cells,
            "lut_unsafe_fraction": self.mapper.unsafe_fraction,
            "comparison_on_sample": self.comparison,
        }
        now = time.perf_counter()
        seconds = {"lookup_table": self.t_lut, "mapping": now - self.t_map, "total": now - self.t0}
        return DesignResult(index_map=index_map, offsets=self.offsets, empty=self.empty, metrics=metrics,
                            seconds=seconds)


def discretize_design(
    spec: SupercellSpec,
    atoms: AtomTable,
    metric: Metric = Metric.PHASE,
    optimise_offsets: bool = True,
    tile_rows: int = 256,
    progress: Callable[[int, int], None] | None = None,
) -> DesignResult:
    """Map every cell's design pair to an atom; accumulate error metrics (the whole index map in memory;
    :class:`DesignStream` for one block at a time)."""
    st = DesignStream(spec, atoms, metric, optimise_offsets, tile_rows, progress)
    index_map = np.empty(st.shape, st.dtype)
    for r0, blk in st:
        index_map[r0:r0 + len(blk)] = blk
    return st.result(index_map)


def discretized_phase(index_map: np.ndarray, atoms: AtomTable, pol: int, empty: int | None = None) -> np.ndarray:
    """Atom phase map (NaN where there is no pillar)."""
    ph = np.append(atoms.phase[:, pol], np.nan).astype(np.float32)
    k = index_map.astype(np.int64)
    if empty is not None:
        k = np.where(index_map == empty, len(atoms), k)
    return ph[k]


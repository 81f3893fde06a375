"""Birefringent discretizer: atom selection by torus binning, exact nearest-atom
mapping, constant-offset optimisation, and error metrics (pure kernels).

Metrics of the mapping:

* ``Metric.PHASE``: wrapped (torus) Euclidean distance between the design
  pair ``(phi_x, phi_y)`` and the atom's ``(arg t_x, arg t_y)``;
* ``Metric.AMPLITUDE``: ``sum_p |exp(i phi_p) - tn_p|^2`` with the
  power-normalised transmission ``tn = t sqrt(n_sup / n_sub)`` (``|tn|^2 = T0``),
  which trades phase error for efficiency.

Nearest-atom search is exact and fast: a ``G x G`` lookup table over the torus
holds each table cell's winner at its centre; a table cell is *safe* when the
runner-up's cost exceeds the winner's by more than ``2 L h`` (L: Lipschitz
constant of the cost, h: half-diagonal of a table cell), so its winner is the
exact argmin everywhere inside it.  Points in unsafe cells are resolved
exactly among the cell's possible winners.  The tests prove equality with
brute force.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from .phase import wrap

__all__ = ["Metric", "AtomTable", "select_atoms", "NearestAtom", "brute_force_nearest", "optimal_offsets"]


class Metric(str, enum.Enum):
    PHASE = "phase"
    AMPLITUDE = "amplitude"


@dataclass(frozen=True)
class AtomTable:
    """The discretized library: at most bins^2 pillars."""

    wx: np.ndarray  # (n,) metres
    wy: np.ndarray
    t: np.ndarray  # (n, 2) complex: [t_x, t_y]
    T0: np.ndarray  # (n, 2)
    lib_index: np.ndarray  # (n, 2) int: (i_wx, i_wy) in the library grid
    n_empty_bins: int  # bins with no kept cell inside (filled from a neighbour)
    n_kept_cells: int
    tn_scale: float  # sqrt(n_sup / n_sub): tn = t * tn_scale has |tn|^2 = T0

    @property
    def phase(self) -> np.ndarray:
        return np.angle(self.t)

    def __len__(self) -> int:
        return len(self.wx)


def _torus_d2(px, py, ax, ay):
    return wrap(px[:, None] - ax[None, :]) ** 2 + wrap(py[:, None] - ay[None, :]) ** 2


def select_atoms(t_x, t_y, T0, wx, wy, threshold: float = 0.7, bins: int = 16,
                 tn_scale: float = 1.0) -> AtomTable:
    """Choose one kept cell per (phase_x, phase_y) bin: the one nearest to the
    bin centre on the torus (possibly from a neighbouring bin when the bin is
    empty), then deduplicate.  Arrays are library grids ``[i_wx, i_wy]``."""
    keep = (T0[..., 0] >= threshold) & (T0[..., 1] >= threshold)
    ii, jj = np.nonzero(keep)
    if ii.size == 0:
        raise ValueError(f"no library cell has T0 >= {threshold:g} in both polarisations")
    px, py = np.angle(t_x[ii, jj]), np.angle(t_y[ii, jj])
    c = -np.pi + (np.arange(bins) + 0.5) * 2 * np.pi / bins
    cx, cy = np.meshgrid(c, c, indexing="ij")
    cx, cy = cx.ravel(), cy.ravel()
    d2 = _torus_d2(cx, cy, px, py)  # (bins^2, n_kept)
    # nearest; ties broken towards the more transmissive cell
    score = d2 - 1e-12 * (T0[ii, jj, 0] + T0[ii, jj, 1])[None, :]
    pick = np.argmin(score, axis=1)
    bx = np.floor((px + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    by = np.floor((py + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    occupied = np.zeros((bins, bins), bool)
    occupied[bx, by] = True
    uniq = np.unique(pick)  # sorted: deterministic atom order
    i, j = ii[uniq], jj[uniq]
    return AtomTable(
        wx=wx[i].copy(), wy=wy[j].copy(),
        t=np.stack([t_x[i, j], t_y[i, j]], axis=1),
        T0=T0[i, j].copy(), lib_index=np.stack([i, j], axis=1),
        n_empty_bins=int((~occupied).sum()), n_kept_cells=int(ii.size), tn_scale=float(tn_scale),
    )


def _axis_tables(c: np.ndarray, atoms: AtomTable, metric: Metric):
    """Per-axis cost tables (len(c), n_atoms): cost(c_u, c_v) = A[u] + B[v]."""
    if metric is Metric.PHASE:
        ph = atoms.phase
        return wrap(c[:, None] - ph[None, :, 0]) ** 2, wrap(c[:, None] - ph[None, :, 1]) ** 2
    tn = atoms.t * atoms.tn_scale
    tabs = []
    for p in (0, 1):
        tabs.append(1.0 + np.abs(tn[None, :, p]) ** 2
                    - 2.0 * (np.cos(c)[:, None] * tn[None, :, p].real + np.sin(c)[:, None] * tn[None, :, p].imag))
    return tabs[0], tabs[1]


def _cost(px, py, atoms: AtomTable, metric: Metric) -> np.ndarray:
    """Cost matrix (n_points, n_atoms), float64."""
    if metric is Metric.PHASE:
        ph = atoms.phase
        return _torus_d2(px, py, ph[:, 0], ph[:, 1])
    tn = atoms.t * atoms.tn_scale
    c = np.abs(tn[:, 0]) ** 2 + np.abs(tn[:, 1]) ** 2 + 2.0  # |e^{i phi}|^2 = 1 per pol
    # |e^{i phi} - tn|^2 = 1 + |tn|^2 - 2 Re(e^{-i phi} tn)
    re = (np.cos(px)[:, None] * tn[None, :, 0].real + np.sin(px)[:, None] * tn[None, :, 0].imag
          + np.cos(py)[:, None] * tn[None, :, 1].real + np.sin(py)[:, None] * tn[None, :, 1].imag)
    return c[None, :] - 2.0 * re


def brute_force_nearest(px, py, atoms: AtomTable, metric: Metric = Metric.PHASE, chunk: int = 65536):
    """Reference argmin over all atoms (lowest index wins exact ties)."""
    px = np.asarray(px, np.float64).ravel()
    py = np.asarray(py, np.float64).ravel()
    out = np.empty(px.size, np.int64)
    for s in range(0, px.size, chunk):
        out[s:s + chunk] = np.argmin(_cost(px[s:s + chunk], py[s:s + chunk], atoms, metric), axis=1)
    return out


class NearestAtom:
    """Exact nearest-atom lookup for large maps (see module docstring)."""

    def __init__(self, atoms: AtomTable, metric: Metric = Metric.PHASE, grid: int = 1024):
        self.atoms, self.metric, self.G = atoms, metric, grid
        G = grid
        step = 2 * np.pi / G
        c = -np.pi + (np.arange(G) + 0.5) * step
        h = step / np.sqrt(2.0)  # half-diagonal of a table cell
        if metric is Metric.PHASE:
            # squared distance is not Lipschitz-friendly: compare distances (1-Lipschitz)
            lip = 1.0
        else:
            tn = np.abs(atoms.t * atoms.tn_scale)
            lip = 2.0 * float(np.sqrt((tn[:, 0].max()) ** 2 + (tn[:, 1].max()) ** 2))
        margin = 2 * lip * h * (1 + 1e-9) + 1e-12
        self.lut = np.empty(G * G, np.int32)
        # the cost is separable: cost[u, v, a] = A[u, a] + B[v, a]
        A, B = _axis_tables(c, atoms, metric)
        unsafe_cells, cand_masks = [], []
        for r0 in range(0, G, 32):
            cost = (A[r0:r0 + 32, None, :] + B[None, :, :]).reshape(-1, len(atoms))
            rows = np.arange(cost.shape[0])
            best = np.argmin(cost, axis=1)
            bval = cost[rows, best]
            cost[rows, best] = np.inf
            second = cost.min(axis=1)
            cost[rows, best] = bval
            if metric is Metric.PHASE:  # distances, not squared distances, are 1-Lipschitz
                dbest = np.sqrt(bval)
                gap = np.sqrt(second) - dbest
                limit = (dbest + margin) ** 2
            else:
                gap = second - bval
                limit = bval + margin
            self.lut[r0 * G: r0 * G + cost.shape[0]] = best
            bad = np.nonzero(gap <= margin)[0]
            unsafe_cells.append(r0 * G + bad)
            # every atom that can win somewhere inside the cell
            cand_masks.append(cost[bad] <= limit[bad, None])
        cells = np.concatenate(unsafe_cells)
        mask = np.concatenate(cand_masks) if cand_masks else np.zeros((0, len(atoms)), bool)
        self.unsafe = np.zeros(G * G, bool)
        self.unsafe[cells] = True
        K = int(mask.sum(axis=1).max()) if len(cells) else 1
        r, a = np.nonzero(mask)  # row-major: atoms ascending within a row, so ties resolve as brute force
        pos = np.arange(r.size) - np.searchsorted(r, r)
        self.cand = np.full((len(cells), K), -1, np.int64)
        self.cand[r, pos] = a
        self.cand_row = np.full(G * G, -1, np.int64)
        self.cand_row[cells] = np.arange(len(cells))
        self.unsafe_fraction = float(self.unsafe.mean())
        # one look-up for compiled kernels: the cell's atom, or -(row + 1) of its candidates when unsafe
        self.code = np.where(self.unsafe, -(self.cand_row + 1), self.lut).astype(np.int32)

    def cell_of(self, px, py):
        G = self.G
        # truncation, not floor: the two differ only below 0, which the clip maps to 0 either way
        ix = ((px + np.pi) * (G / (2 * np.pi))).astype(np.int64)
        iy = ((py + np.pi) * (G / (2 * np.pi))).astype(np.int64)
        np.clip(ix, 0, G - 1, out=ix)  # wrapped inputs: only rounding at +pi can step out
        np.clip(iy, 0, G - 1, out=iy)
        ix *= G
        ix += iy
        return ix

    def __call__(self, px, py) -> np.ndarray:
        """Nearest atom of wrapped phase pairs (any shape); returns int32 of that shape."""
        shape = np.shape(px)
        px = np.asarray(px, np.float64).ravel()
        py = np.asarray(py, np.float64).ravel()
        cell = self.cell_of(px, py)
        out = self.lut[cell]
        sel = np.nonzero(self.unsafe[cell])[0]
        if sel.size:
            cand = self.cand[self.cand_row[cell[sel]]]  # (n_sel, K)
            valid = cand >= 0
            candc = np.where(valid, cand, 0)
            spx, spy = px[sel][:, None], py[sel][:, None]
            if self.metric is Metric.PHASE:
                ph = self.atoms.phase
                cost = wrap(spx - ph[candc, 0]) ** 2 + wrap(spy - ph[candc, 1]) ** 2
            else:
                tn = self.atoms.t * self.atoms.tn_scale
                t0, t1 = tn[candc, 0], tn[candc, 1]
                cost = (np.abs(t0) ** 2 + np.abs(t1) ** 2 + 2.0
                        - 2.0 * (np.cos(spx) * t0.real + np.sin(spx) * t0.imag
                                 + np.cos(spy) * t1.real + np.sin(spy) * t1.imag))
            cost = np.where(valid, cost, np.inf)
            out[sel] = candc[np.arange(sel.size), np.argmin(cost, axis=1)]
        return out.reshape(shape)

    def min_cost_grid(self, n: int) -> np.ndarray:
        """Cost of the best atom at the centres of an ``n x n`` torus grid
        (squared phase error for PHASE)."""
        c = -np.pi + (np.arange(n) + 0.5) * 2 * np.pi / n
        px = np.repeat(c, n)
        py = np.tile(c, n)
        best = self(px, py)
        return _point_cost(px, py, best, self.atoms, self.metric).reshape(n, n)


def _point_cost(px, py, idx, atoms: AtomTable, metric: Metric) -> np.ndarray:
    if metric is Metric.PHASE:
        ph = atoms.phase
        return wrap(ph[idx, 0] - px) ** 2 + wrap(ph[idx, 1] - py) ** 2
    tn = atoms.t * atoms.tn_scale
    ex = np.cos(px) - tn[idx, 0].real, np.sin(px) - tn[idx, 0].imag
    ey = np.cos(py) - tn[idx, 1].real, np.sin(py) - tn[idx, 1].imag
    return ex[0] ** 2 + ex[1] ** 2 + ey[0] ** 2 + ey[1] ** 2


def optimal_offsets(hist: np.ndarray, cost_grid: np.ndarray) -> tuple[float, float, float]:
    """Best constant offsets ``(c_x, c_y)`` given the histogram of design phase
    pairs and the mapping cost on the same torus grid: minimises
    ``sum_u hist[u] cost[u + c]`` over all grid shifts by one FFT correlation.
    Returns ``(c_x, c_y, mean_cost)``."""
    n = hist.shape[0]
    J = np.real(np.fft.ifft2(np.conj(np.fft.fft2(hist)) * np.fft.fft2(cost_grid)))
    i, j = np.unravel_index(np.argmin(J), J.shape)
    step = 2 * np.pi / n
    return float(wrap(i * step)), float(wrap(j * step)), float(J[i, j] / hist.sum())


def distinct_supercells(index_map: np.ndarray, m: int = 2, cover=(0.5, 0.9, 0.99)) -> dict:
    """How many distinct ``m x m`` supercells (tuples of atom indices, in reading order) a design has, and
    how many of the most frequent ones cover the given fractions of all supercells: what a per-supercell
    solver or a look-up cache would have to handle (issue #34).  Index values must be < 2^15."""
    nr, nc = (index_map.shape[0] // m) * m, (index_map.shape[1] // m) * m
    key = np.zeros((nr // m, nc // m), np.int64)
    for b in range(m):
        for a in range(m):
            key = key * (1 << 15) + index_map[b:nr:m, a:nc:m].astype(np.int64)
    _, counts = np.unique(key, return_counts=True)
    cum = np.cumsum(np.sort(counts)[::-1]) / key.size
    return {"supercells": int(key.size), "distinct": int(counts.size),
            "most_frequent_covering": {f"{q:g}": int(np.searchsorted(cum, q - 1e-12) + 1) for q in cover}}

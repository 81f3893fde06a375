"""A table of 2 x 2 supercells solved with supercell RCWA: the data the coupling model is fitted to.

A row is one supercell, ``widths[r, c] = (wx, wy)`` (m) of the pillar at ``x = c p, y = r p`` (the layout
of :func:`metadesign.library.supercell.supercell_rects`), and its 0th-order transmission ``t`` for x- and
y-polarised light (the Jones diagonal; the sector solve has no cross terms).  The supercell's harmonic set
is matched to a unit cell's: its even harmonics, halved, are the unit cell's set
(:func:`matched_unit_harmonics`), so four identical pillars give that unit cell's own ``t`` and the
difference is the coupling alone, not a truncation mismatch.  At the library's own truncation (nG 797 for
its 197) the unit cell is the library; at any other (a cheaper table, a convergence ladder) the table also
solves each row's four unit cells at the matched truncation (``t_unit``), and the row's label is the
coupling measured at that truncation added to the library's LPA (:meth:`SupercellTable.labels`):

    t_label = mean_i t_lib(w_i) + [ t_super(nG) - mean_i t_unit(w_i; nG matched) ]

The bracket (the coupling) converges much faster with nG than either term (their truncation errors
cancel); its convergence is what :func:`metadesign.studies.supercells.convergence_ladder` measures.

:func:`solve_table` is the library build's engine for this table: rows in chunks, each finished chunk
written atomically into ``<output>.partial/`` under a name that hashes its widths and the solver settings,
so a killed build resumes from what is on disk, a larger build reuses a smaller one's chunks, and the
table is the same bytes whatever the worker count or scheduler (each row depends on its widths alone)."""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..execution import remove_scratch
from ..io import atomic_write_text, read_npz, write_npz
from ..tasks import TaskFolder, content_key, run_resumable
from ..validation import ValidationError
from .coupling import lpa_t
from .rcwa import SolverSettings, Stack, solve_cell
from .store import interpolate_t
from .supercell import solve_supercell, solve_tapered

__all__ = ["SupercellTable", "matched_unit_harmonics", "matched_harmonics", "solve_table", "unit_cells", "load_table", "save_table", "TABLE_FORMAT"]

TABLE_FORMAT = "metadesign.supercells/1"


def matched_harmonics(n_big: int, stack: Stack, big: int, small: int) -> tuple[int, int]:
    """Requested harmonic counts ``(big cell, small cell)`` whose sets match, for cells of ``big`` and ``small``
    pitches (``big`` a multiple of ``small``): the small cell's harmonics are the big cell's multiples of
    ``big / small``, divided.  See :func:`matched_unit_harmonics` (big 2, small 1)."""
    from grcwa.kbloch import Lattice_getG, Lattice_Reciprocate

    if big % small:
        raise ValueError(f"a cell of {big} pitches does not hold cells of {small}")
    q = big // small

    def gset(n, L):  # grcwa's circular truncation of the unit lattice (Init_Setup's, without its dense matrices)
        G, nG = Lattice_getG(int(n), *Lattice_Reciprocate([1.0, 0.0], [0.0, 1.0]), method=0)
        return {tuple(g) for g in np.asarray(G)}, int(nG)

    s, ns = gset(n_big, big * stack.period)
    sub = {(a // q, b // q) for a, b in s if a % q == 0 and b % q == 0}
    u, nu = gset(len(sub) + 1, small * stack.period)  # grcwa keeps whole shells below the first incomplete one
    if u != sub:
        raise RuntimeError(f"no truncation of the {small}-pitch cell matches the {big}-pitch cell's (nG {ns})")
    return ns + 1, nu + 1


def matched_unit_harmonics(n_super: int, stack: Stack) -> tuple[int, int]:
    """Requested harmonic counts ``(supercell, unit cell)`` whose sets match: the unit cell's harmonics are
    the supercell's even ones, halved (circular truncation of the same radius in reciprocal space).  grcwa
    keeps the whole shells below the first incomplete one, so a count that ends exactly on a shell loses
    it: the requests returned are one more than the set sizes."""
    return matched_harmonics(n_super, stack, 2, 1)


@dataclass(frozen=True)
class SupercellTable:
    """Solved supercells: ``widths`` (n, 2, 2, 2) m, ``t`` (n, 2) complex (x-pol, y-pol), ``source`` (n,)
    int (index into ``meta["sources"]``), ``test`` (n,) bool (held out of every fit), ``meta`` (provenance);
    ``t_unit`` (n, 2, 2, 2 pol) complex: each pillar's unit cell at the matched truncation, for a table
    solved at another truncation than the library's (None: the library is the matched unit cell)."""

    widths: np.ndarray
    t: np.ndarray
    source: np.ndarray
    test: np.ndarray
    meta: dict
    t_unit: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)

    def head(self, n: int) -> "SupercellTable":
        return self.rows(np.arange(min(n, len(self))))

    def rows(self, idx) -> "SupercellTable":
        return SupercellTable(self.widths[idx], self.t[idx], self.source[idx], self.test[idx], self.meta,
                              None if self.t_unit is None else self.t_unit[idx])

    def coupling(self) -> np.ndarray | None:
        """(n, 2) the coupling measured at the table's truncation, ``t - mean_i t_unit,i`` (None without
        ``t_unit``)."""
        return None if self.t_unit is None else self.t - self.t_unit.mean((1, 2))

    def labels(self, t_lpa: np.ndarray) -> np.ndarray:
        """(n, 2) the rows' supercell ``t`` in the library's frame: ``t`` itself at the library's truncation,
        else the LPA ``t_lpa`` (n, 2) plus the coupling measured at the table's (module docstring)."""
        return self.t if self.t_unit is None else np.asarray(t_lpa) + self.coupling()

    def lpa_labels(self, lib) -> tuple[np.ndarray, np.ndarray]:
        """``(labels (n, 2), t_units (n, 2, 2, 2))``: :meth:`labels` on the library's LPA, with the pillars'
        library ``t`` (bilinear, as every coupling model looks them up)."""
        tu = interpolate_t(lib, self.widths[..., 0], self.widths[..., 1])[0]
        return self.labels(lpa_t(tu)), tu


def _chunk_name(widths: np.ndarray, n_harmonics: int, stack: Stack, unit_harmonics: int | None = None,
                taper: tuple[float, int] | None = None) -> str:
    """A chunk's task name: the content key of its rows and of what shapes their solve."""
    extra = ([] if unit_harmonics is None else [unit_harmonics]) + ([] if taper is None else ["taper", *taper])
    return "chunk-" + content_key(np.ascontiguousarray(widths, "<f8"), [n_harmonics, stack.wavelength, stack.period,
                                  stack.height, stack.n_pillar, stack.n_substrate, stack.n_superstrate, *extra],
                                  __version__)


def unit_cells(widths: np.ndarray, stack: Stack, unit_harmonics: int,
               taper: tuple[float, int] | None = None) -> np.ndarray:
    """(n, 2, 2, 2 pol) each pillar's unit cell (period ``p``) at ``unit_harmonics`` (requested); ``taper =
    (sidewall_deg, slices)``: tapered pillars, widths at mid-height.  A pillar solved before in this process
    is not solved again (a design's pillars are a few hundred atoms)."""
    w = np.asarray(widths, float).reshape(-1, 2)
    tp = None if taper is None else (float(taper[0]), int(taper[1]))
    out = np.array([_unit_t(float(wx), float(wy), stack, int(unit_harmonics), tp) for wx, wy in w])
    return out.reshape(*np.shape(widths)[:-1], 2)


@functools.lru_cache(maxsize=8192)
def _unit_t(wx: float, wy: float, stack: Stack, unit_harmonics: int, taper: tuple[float, int] | None) -> np.ndarray:
    st = SolverSettings(unit_harmonics)
    res = solve_cell(wx, wy, stack, st) if taper is None else solve_tapered(wx, wy, *taper, stack, st)
    t = res.jones[[0, 1], [0, 1]]
    t.flags.writeable = False
    return t


def _solve_rows(args) -> tuple[str, dict]:
    name, widths, stack, n_harmonics, unit_harmonics, taper = args
    res = [solve_supercell(w, stack, n_harmonics, taper=taper) for w in widths]
    out = {"t": np.array([r.jones[[0, 1], [0, 1]] for r in res]),
           "n_harmonics": np.array([r.n_harmonics for r in res])}
    if unit_harmonics is not None:
        out["t_unit"] = unit_cells(widths, stack, unit_harmonics, taper)
    return name, out


def solve_table(widths: np.ndarray, stack: Stack, n_harmonics: int, partial: str | Path, *, workers: int = 1,
                scheduler: str | None = None, chunk_size: int = 8, unit_harmonics: int | None = None,
                progress: Callable[[int, int], None] | None = None, log: Callable[[str], None] = lambda s: None,
                taper: tuple[float, int] | None = None, _stop_after_chunks: int | None = None):
    """``t`` (n, 2) of the supercells ``widths`` (n, 2, 2, 2), solved at ``n_harmonics`` (requested), chunks
    kept in the folder ``partial`` (made with the scratch marker first, :class:`~metadesign.tasks.TaskFolder`;
    resumable; the caller removes it once the table is saved, :func:`remove_partial`).  Returns
    ``(t, nG, seconds spent solving, t_unit)``: ``t_unit`` every pillar's unit cell at ``unit_harmonics``
    (requested; the matched unit cell's, :func:`matched_unit_harmonics`), None without it.  ``taper =
    (sidewall_deg, slices)``: every pillar (and unit cell) with sloped walls, the widths at mid-height."""
    taper = None if taper is None or float(taper[0]) == 90.0 else (float(taper[0]), int(taper[1]))
    widths = np.asarray(widths, float)
    if widths.ndim != 4 or widths.shape[1:] != (2, 2, 2):
        raise ValueError(f"widths must be (n, 2, 2, 2), got {widths.shape}")
    folder = TaskFolder(partial)  # chunks named by their rows' content: a larger table reuses a smaller one's
    chunks = [(k, min(k + chunk_size, len(widths))) for k in range(0, len(widths), chunk_size)]
    names = [_chunk_name(widths[a:b], n_harmonics, stack, unit_harmonics, taper) for a, b in chunks]
    jobs = {nm: (nm, widths[a:b], stack, n_harmonics, unit_harmonics, taper) for (a, b), nm in zip(chunks, names)}
    size = {nm: b - a for (a, b), nm in zip(chunks, names)}
    t0 = time.perf_counter()
    done, _ = run_resumable(_solve_rows, jobs, folder, workers=workers, scheduler=scheduler, dask_key="supercells",
                            weight=size.__getitem__, progress=progress, log=log, unit="supercell",
                            stop_after=_stop_after_chunks)
    seconds = time.perf_counter() - t0
    t = np.concatenate([done[nm]["t"] for nm in names])
    nGs = {int(v) for nm in names for v in done[nm]["n_harmonics"]}
    if len(nGs) != 1:
        raise RuntimeError(f"the chunks were solved at different truncations: {sorted(nGs)}")
    t_unit = None if unit_harmonics is None else np.concatenate([done[nm]["t_unit"] for nm in names])
    return t, nGs.pop(), seconds, t_unit


def save_table(path: str | Path, table: SupercellTable) -> None:
    meta = {"format": TABLE_FORMAT, **table.meta}
    extra = {} if table.t_unit is None else {"t_unit": table.t_unit.astype(np.complex128)}
    write_npz(path, {"widths_m": table.widths, "t": table.t.astype(np.complex128), "source": table.source,
                     "test": table.test, "meta": np.array(json.dumps(meta, sort_keys=True)), **extra})


def load_table(path: str | Path) -> SupercellTable:
    d = read_npz(path, "supercell table")
    need = ("widths_m", "t", "source", "test", "meta")
    missing = [k for k in need if k not in d]
    meta = json.loads(str(d["meta"])) if "meta" in d else {}
    if missing or meta.get("format") != TABLE_FORMAT:
        raise ValidationError(f"{path}: not a supercell table ({TABLE_FORMAT}"
                              + (f"; missing {', '.join(missing)})" if missing else ")"))
    t_unit = d.get("t_unit")
    _check_table_arrays(path, d)
    if t_unit is not None and t_unit.shape != (*d["t"].shape[:1], 2, 2, 2):
        raise ValidationError(f"{path}: t_unit has shape {t_unit.shape}, expected ({len(d['t'])}, 2, 2, 2)")
    return SupercellTable(d["widths_m"], d["t"], d["source"], d["test"].astype(bool), meta, t_unit)


def _check_table_arrays(path, d: dict) -> None:
    """A table's rows agree (widths (n, 2, 2, 2) of finite positive metres below 1 mm, labels
    (n, 2) finite complex, one source and test flag per row): one line naming the array otherwise."""
    w, t = np.asarray(d["widths_m"]), np.asarray(d["t"])
    n = len(w) if w.ndim else -1
    if w.shape != (n, 2, 2, 2) or w.dtype.kind != "f":
        raise ValidationError(f"{path}: widths_m has shape {w.shape} {w.dtype}, expected (rows, 2, 2, 2) real")
    if not np.isfinite(w).all() or (w <= 0).any() or (w >= 1e-3).any():
        raise ValidationError(f"{path}: widths_m must be finite widths in (0, 1 mm) (NaN, infinite, negative or "
                              "absurd widths found)")
    if t.shape != (n, 2) or t.dtype.kind != "c" or not np.isfinite(t).all():
        raise ValidationError(f"{path}: t (the labels) must be ({n}, 2) finite complex values, got {t.shape} {t.dtype}"
                              + ("" if t.dtype.kind != "c" or np.isfinite(t).all() else " with NaN or infinite values"))
    for k in ("source", "test"):
        if np.shape(d[k]) != (n,):
            raise ValidationError(f"{path}: {k} has shape {np.shape(d[k])}, expected ({n},)")


def remove_partial(partial: str | Path) -> None:
    """Remove a job's scratch folder once its product is saved (only if metadesign made it: it carries the
    scratch marker; a user's folder stays)."""
    remove_scratch(partial)


def write_json(path: str | Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1))

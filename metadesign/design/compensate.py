"""A supercell-aware discretizer: choose each 2 x 2 supercell's four atoms jointly so that its propagating
order under the coupling model (:mod:`metadesign.library.coupling`) matches the sum of the four lens fields.

The nearest-atom discretizer picks every pillar for its own lens (the LPA: the supercell's 0th order is
the mean of the four pillars' ``t``).  Under coupling that mean is wrong by about a third of a pillar's
transmission, so here the target of a supercell is ``S_p = gamma_p mean_i exp(i phi_i,p)`` (the four
channels' design phases with the design's offsets; ``gamma_p`` one complex factor per polarisation, fitted
once by least squares to the nearest-atom design under the model, so the compensation neither fights a
global phase nor the atoms' mean amplitude) and the cost ``sum_p |t_model,p(a) - S_p|^2``.  Starting from
today's choice, coordinate descent: each of the four positions in turn tries its atom's ``neighbours``
nearest atoms on the (phase_x, phase_y) torus (itself included, so the cost never rises), for ``sweeps``
sweeps, every supercell at once.  Candidates are scored from the model's pair tables (a change of one
atom touches seven look-ups per polarisation), so the paper's 12.75 M supercells take minutes.  Atoms stay
in the 16 x 16 table: design rules are the table's (no new widths, no new gaps)."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable

import numpy as np

from ..library.coupling import tuple_t
from ..library.coupling_net import pair_tables
from .phase import design_phase, design_phase_rows, wrap
from .store import Design

__all__ = ["atom_neighbours", "compensate_design", "supercell_targets", "sampled_supercells", "descend_under"]


def atom_neighbours(phase: np.ndarray, k: int) -> np.ndarray:
    """(A, k) the ``k`` atoms nearest to each atom on the (phase_x, phase_y) torus, itself first."""
    px, py = phase[:, 0], phase[:, 1]
    d2 = wrap(px[:, None] - px[None, :]) ** 2 + wrap(py[:, None] - py[None, :]) ** 2
    np.fill_diagonal(d2, -1.0)
    return np.argsort(d2, axis=1, kind="stable")[:, :k]


def _blocks(a: np.ndarray) -> np.ndarray:
    """(R, C, ...) -> (R/2 * C/2, 2, 2, ...) supercells ``[n, r, c]``."""
    R2, C2 = a.shape[0] // 2, a.shape[1] // 2
    a = a[:2 * R2, :2 * C2]
    return a.reshape(R2, 2, C2, 2, *a.shape[2:]).swapaxes(1, 2).reshape(R2 * C2, 2, 2, *a.shape[2:])


def _unblocks(b: np.ndarray, R: int, C: int) -> np.ndarray:
    return b.reshape(R // 2, C // 2, 2, 2).swapaxes(1, 2).reshape(R, C)


def supercell_targets(d: Design, r0: int, r1: int) -> np.ndarray:
    """(n, 2) ``mean_i exp(i phi_i,p)`` of the supercells of rows ``r0:r1`` (the design's offsets included)."""
    out = []
    for p in (0, 1):
        ph = design_phase_rows(d.spec, p, r0, r1, offset=d.offsets[p])
        e = np.cos(ph).astype(np.float32) + 1j * np.sin(ph).astype(np.float32)
        out.append(_blocks(e).mean((1, 2)))
    return np.stack(out, 1)


# the neighbour of position (r, c) of each kind: 0 the row's other pillar, 1 the column's, 2 the diagonal
_POS = [(0, 0), (0, 1), (1, 0), (1, 1)]
_NB = {(r, c): ((r, 1 - c), (1 - r, c), (1 - r, 1 - c)) for r, c in _POS}


def _descend(a: np.ndarray, S: np.ndarray, tab: np.ndarray, ta: np.ndarray, nbr: np.ndarray, sweeps: int):
    """Coordinate descent of atom 4-tuples ``a`` (n, 2, 2) towards targets ``S`` (n, 2); in place."""
    t = tuple_t(tab, ta, a)
    for _ in range(sweeps):
        for r, c in _POS:
            cur = a[:, r, c]
            cand = nbr[cur]  # (n, K)
            nb = [a[:, rr, cc] for rr, cc in _NB[(r, c)]]
            dt = np.zeros((*cand.shape, 2), np.complex64)
            for p in (0, 1):
                d = ta[cand, p] - ta[cur, p][:, None]
                for kind, b in enumerate(nb):
                    d += tab[kind, p, cand, b[:, None]] - tab[kind, p, cur, b][:, None]  # as the pillar itself
                    d += tab[kind, p, b[:, None], cand] - tab[kind, p, b, cur][:, None]  # as the neighbour's
                dt[..., p] = d / 4
            new = t[:, None, :] + dt
            cost = (np.abs(new - S[:, None, :]) ** 2).sum(-1)
            j = np.argmin(cost, axis=1)  # candidate 0 is the current atom: the cost never rises
            rows = np.arange(len(a))
            a[:, r, c] = cand[rows, j]
            t = new[rows, j]
    return t


def sampled_supercells(d: Design, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(atoms (n, 2, 2) int, targets (n, 2) complex)`` of the design's supercells ``ids`` (flat ``I * (n //
    2) + J``: rows ``2I, 2I+1``, columns ``2J, 2J+1``): their atom indices and :func:`supercell_targets`
    (``mean_i exp(i phi_i,p)``, the design's offsets included), read supercell by supercell (a sample of a
    device of any size)."""
    ids = np.asarray(ids, np.int64)
    C2 = d.spec.n_cells // 2
    I, J = ids // C2, ids % C2
    im = d.atom_indices()
    a = np.stack([im[2 * I + r, 2 * J + c] for r in (0, 1) for c in (0, 1)], 1).reshape(-1, 2, 2).astype(np.int64)
    S = np.zeros((len(ids), 2), np.complex128)
    for k, (i, j) in enumerate(zip(I, J)):
        for p in (0, 1):
            ph = design_phase(d.spec, p, np.array([2 * i, 2 * i + 1]), np.array([2 * j, 2 * j + 1]), d.offsets[p])
            S[k, p] = (np.cos(ph) + 1j * np.sin(ph)).mean()
    return a, S


def descend_under(a: np.ndarray, S: np.ndarray, nbr: np.ndarray, evaluate: Callable[[np.ndarray], np.ndarray],
                  sweeps: int = 1, t: np.ndarray | None = None,
                  progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """:func:`_descend`'s coordinate descent of atom 4-tuples ``a`` (n, 2, 2; in place) towards ``S`` (n, 2)
    under any supercell model: ``evaluate(tuples (m, 2, 2) int) -> t (m, 2)`` scores every candidate tuple
    whole (a model without pair tables: the certified one).  Each position in turn tries its atom's
    neighbours ``nbr`` (itself first, so the cost never rises); ties go to the earlier candidate, as in
    :func:`_descend`.  ``t``: the tuples' current ``t`` if known.  Returns the final ``t``."""
    n, K = len(a), nbr.shape[1]
    t = evaluate(a) if t is None else np.asarray(t)
    rows, step = np.arange(n), 0
    for _ in range(sweeps):
        for r, c in _POS:
            cand = nbr[a[:, r, c]]  # (n, K), the current atom first
            trial = np.repeat(a[:, None], K - 1, 1)
            trial[:, :, r, c] = cand[:, 1:]
            tt = np.asarray(evaluate(trial.reshape(-1, 2, 2))).reshape(n, K - 1, 2)
            new = np.concatenate([t[:, None, :], tt], 1)
            j = np.argmin((np.abs(new - S[:, None, :]) ** 2).sum(-1), axis=1)
            a[:, r, c] = cand[rows, j]
            t = new[rows, j]
            step += 1
            if progress:
                progress(step, 4 * sweeps)
    return t


def compensate_design(d: Design, model, neighbours: int = 9, sweeps: int = 2, tile_rows: int = 512,
                      progress: Callable[[int, int], None] | None = None) -> tuple[Design, dict]:
    """The design with every complete supercell's atoms re-chosen under the coupling ``model`` (a pair
    model).  Returns the new design (its metrics gain ``coupling_compensation``) and that report."""
    if d.spec.supercell != 2:
        raise ValueError("the coupling model is for 2 x 2 supercells")
    t0 = time.perf_counter()
    A = len(d.atoms)
    aw = np.stack([d.atoms.wx, d.atoms.wy], 1)
    ta = d.atoms.t.astype(np.complex64)
    tab = pair_tables(model, aw, ta)
    nbr = atom_neighbours(d.atoms.phase, min(neighbours, A))
    n = d.spec.n_cells
    tile_rows = max(2, tile_rows // 2 * 2)
    # gamma_p: one complex factor per polarisation, least squares of the nearest-atom design under the model
    num, den = np.zeros(2, np.complex128), np.zeros(2)
    for r0 in range(0, n - n % 2, max(2, (n // 16) // 2 * 2)):
        r1 = min(r0 + 2, n - n % 2)
        a = _blocks(d.atom_indices()[r0:r1].astype(np.int64))
        ok = (a < A).all((1, 2))
        S = supercell_targets(d, r0, r1)[ok]
        t = tuple_t(tab, ta, a[ok])
        num += (np.conj(S) * t).sum(0)
        den += (np.abs(S) ** 2).sum(0)
    gamma = num / np.maximum(den, 1e-30)
    im = d.index_map.copy()
    res0, res1, changed, total = np.zeros(2), np.zeros(2), 0, 0
    for r0 in range(0, n - n % 2, tile_rows):
        r1 = min(r0 + tile_rows, n - n % 2)
        blk = d.atom_indices()[r0:r1].astype(np.int64)
        a = _blocks(blk)
        ok = (a < A).all((1, 2))
        S = (supercell_targets(d, r0, r1) * gamma.astype(np.complex64))[ok]
        a_ok = a[ok].copy()
        before = tuple_t(tab, ta, a_ok)
        after = _descend(a_ok, S, tab, ta, nbr, sweeps)
        res0 += (np.abs(before - S) ** 2).sum(0)
        res1 += (np.abs(after - S) ** 2).sum(0)
        changed += int((a_ok != a[ok]).sum())
        total += int(ok.sum()) * 4
        a[ok] = a_ok
        new = _unblocks(a, r1 - r0, n)
        keep = blk >= A  # empty cells stay empty
        im[r0:r1] = np.where(keep, im[r0:r1], new.astype(im.dtype))
        if progress:
            progress(r1, n)
    m = max(total // 4, 1)
    rep = {"neighbours": int(nbr.shape[1]), "sweeps": sweeps, "supercells": m,
           "gamma": [[float(g.real), float(g.imag)] for g in gamma],
           "residual_rms_before": np.sqrt(res0 / m).tolist(), "residual_rms_after": np.sqrt(res1 / m).tolist(),
           "pillars_changed_fraction": changed / max(total, 1), "seconds": time.perf_counter() - t0,
           "cost": "sum_p |t_model,p - gamma_p mean_i exp(i phi_i,p)|^2 per supercell"}
    metrics = {**d.metrics, "coupling_compensation": rep}
    meta = {**d.meta, "metrics": metrics, "coupling_compensated": True}
    return replace(d, index_map=im, metrics=metrics, meta=meta), rep

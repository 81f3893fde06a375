"""A physics-enhanced surrogate of the 2 x 2 supercell (issue #34): cheap supercell solves, calibrated.

The low fidelity is the project's own supercell RCWA (:func:`~metadesign.library.supercell.solve_supercell`)
at a few low truncations, each with its four unit cells at the matched truncation, so that what a level
measures is the coupling ``c_k = t_super(nG_k) - mean_i t_unit,i(nG_k)`` (the truncation errors of the two
terms cancel in part: :meth:`~metadesign.library.supercells.SupercellTable.labels`).  The surrogate is

    t = mean_i t_lib(w_i) + sum_k a_k c_k

with one complex coefficient ``a_k`` per level, shared by both polarisations, fitted by least squares on
converged labels (PEDS: Pestourie et al., Nature Machine Intelligence 2023, a low-fidelity solver plus a
learned correction; here the correction is a linear extrapolation in truncation, which a handful of labels
pins down).  By construction four identical pillars give the library's unit cell exactly (every ``c_k`` is
zero at a matched truncation), and the lattice symmetries are the solver's (a translated supercell is the
same periodic structure; the x <-> y mirror swaps the polarisations, which share the coefficients).

The cost is the solves: a fraction of a second per supercell instead of seconds at convergence, which
certifies single supercells (checks, samples, labels) but not a device's millions in minutes; the device
path keeps the fast coupling network (:mod:`metadesign.library.coupling_net`).  Numpy only.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..cards import read_card, save_card
from ..paths import repo_root
from ..tasks import TaskFolder, content_key, run_resumable
from ..validation import ValidationError
from .coupling import lpa_t
from .locate import find_fitted
from .rcwa import Stack
from .store import UnitCellLibrary, interpolate_t
from .supercell import solve_patch, solve_supercell
from .supercells import matched_harmonics, matched_unit_harmonics, solve_table

__all__ = ["PEDS_FORMAT", "PedsModel", "low_fidelity_couplings", "fit_peds", "peds_t", "save_peds", "load_peds",
           "find_peds", "certified_t", "patch_harmonics", "ring_couplings", "patch_windows", "neighbour_windows",
           "window_ring"]

PEDS_FORMAT = "metadesign.peds/1"


@dataclass(frozen=True)
class PedsModel:
    """Low-fidelity levels (requested supercell truncations, ascending) and one complex coefficient per level;
    ``library_sha256`` the unit-cell library it was calibrated against; ``card`` its certification."""

    harmonics: tuple[int, ...]
    coef: tuple[complex, ...]
    library_sha256: str = ""
    card: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        if not self.harmonics or len(self.harmonics) != len(self.coef):
            raise ValidationError(f"PEDS model: {len(self.harmonics)} levels but {len(self.coef)} coefficients")
        if list(self.harmonics) != sorted(set(self.harmonics)) or min(self.harmonics) < 20:
            raise ValidationError(f"PEDS model: levels must be distinct truncations >= 20, ascending; got "
                                  f"{list(self.harmonics)}")
        if not all(np.isfinite(complex(a).real) and np.isfinite(complex(a).imag) for a in self.coef):
            raise ValidationError("PEDS model: a coefficient is not finite")


def low_fidelity_couplings(widths: np.ndarray, stack: Stack, harmonics, partial: str | Path, *, workers: int = 1,
                           scheduler: str | None = None, chunk_size: int = 16,
                           progress: Callable[[int, int], None] | None = None,
                           log: Callable[[str], None] = lambda s: None,
                           taper: tuple[float, int] | None = None) -> tuple[np.ndarray, list[int]]:
    """``(c (K, n, 2) complex, nG per level)``: the coupling of each supercell
    ``widths`` (n, 2, 2, 2) m at each requested truncation of ``harmonics``, its unit cells at the matched
    truncation (``taper = (sidewall_deg, slices)``: tapered pillars, both).  Chunks under
    ``partial/nG-<n>`` (content-keyed: resumable, the same bytes on any worker count; a rerun on the same
    rows solves nothing)."""
    out, nGs = [], []
    for h in harmonics:
        ns, nu = matched_unit_harmonics(int(h), stack)
        t, nG, _, t_unit = solve_table(widths, stack, ns, Path(partial) / f"nG-{ns - 1}", workers=workers,
                                             scheduler=scheduler, chunk_size=chunk_size, unit_harmonics=nu,
                                             progress=progress, log=log, taper=taper)
        out.append(t - t_unit.mean((1, 2)))
        nGs.append(int(nG))
    return np.stack(out), nGs


def fit_peds(couplings: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares complex coefficients ``a`` (K,) of ``target (n, 2) ~= sum_k a_k couplings[k] (n, 2)``
    (``target``: the labels minus the LPA), one set for both polarisations."""
    c = np.asarray(couplings)
    M = c.reshape(len(c), -1).T
    a, *_ = np.linalg.lstsq(M, np.asarray(target).ravel(), rcond=None)
    return a


def peds_t(coef, couplings: np.ndarray, t_lpa: np.ndarray) -> np.ndarray:
    """(n, 2) the surrogate's supercell ``t``: the LPA plus the calibrated couplings."""
    return np.asarray(t_lpa) + np.tensordot(np.asarray(coef, complex), np.asarray(couplings), axes=1)


def patch_harmonics(n_super: int, stack: Stack) -> tuple[int, int]:
    """Requested harmonic counts ``(4 x 4 patch, 2 x 2 supercell)`` whose sets match, the supercell's being the
    set a supercell solve at the requested ``n_super`` uses (the PEDS level's): the smallest patch truncation
    whose even multiples, halved, are that set (a patch repeating one supercell then equals it exactly)."""
    ns, _ = matched_unit_harmonics(int(n_super), stack)  # ns - 1: the supercell's own nG at this request
    target = ns - 1
    for n in range(max(20, 3 * target), 8 * target + 64):
        nb, nsub = matched_harmonics(n, stack, 4, 2)
        if nsub - 1 == target:
            return nb, nsub
        if nsub - 1 > target:
            break
    raise ValidationError(f"no 4 x 4 patch truncation matches a supercell at nG {target}")


def _ring_task(args) -> tuple[str, dict]:
    """One patch at one level: its solve and its four supercells', matched."""
    name, w, stack, n_patch, n_super = args
    tp = solve_patch(w, stack, n_patch).jones[[0, 1], [0, 1]]
    ts = np.array([solve_supercell(w[2 * i:2 * i + 2, 2 * j:2 * j + 2], stack, n_super).jones[[0, 1], [0, 1]]
                   for i in range(2) for j in range(2)])
    return name, {"ring": tp - ts.mean(0)}


def ring_couplings(patches: np.ndarray, stack: Stack, harmonics, partial: str | Path, *, workers: int = 1,
                   scheduler: str | None = None, progress: Callable[[int, int], None] | None = None,
                   log: Callable[[str], None] = lambda s: None) -> np.ndarray:
    """(K, n, 2) complex: the neighbour-ring coupling of 4 x 4 patches ``patches`` (n, 4, 4, 2) m at each
    requested supercell truncation of ``harmonics``: the periodic patch's ``t`` minus the mean of its four
    2 x 2 supercells' (each periodic), both at matched truncations (:func:`patch_harmonics`), so a patch
    repeating one supercell has none.  It is what the patch's mean transmission owes to each supercell
    seeing other supercells around it rather than copies of itself (issue #34 section 2).  One task per
    patch and level under ``partial`` (content-keyed: resumable, the same bytes on any worker count)."""
    w = np.asarray(patches, float)
    if w.ndim != 4 or w.shape[1:] != (4, 4, 2):
        raise ValidationError(f"ring_couplings: patches must be (n, 4, 4, 2) metres, got {w.shape}")
    out = []
    for h in harmonics:
        npch, nsup = patch_harmonics(int(h), stack)
        key = [npch, nsup, stack.wavelength, stack.period, stack.height, stack.n_pillar, stack.n_substrate,
               stack.n_superstrate]
        names = [f"ring-{content_key(np.ascontiguousarray(x, '<f8'), key, __version__)}" for x in w]
        jobs = {nm: (nm, x, stack, npch, nsup) for nm, x in zip(names, w)}
        done, _ = run_resumable(_ring_task, jobs, TaskFolder(Path(partial) / f"ring-nG-{nsup - 1}"), workers=workers,
                                scheduler=scheduler, dask_key=f"ring-{nsup - 1}", progress=progress, log=log,
                                unit="patch")
        out.append(np.array([done[nm]["ring"] for nm in names]).reshape(len(w), 2))
    return np.stack(out) if out else np.zeros((0, len(w), 2), complex)


def patch_windows(patches: np.ndarray) -> np.ndarray:
    """(n, 16, 2, 2, 2): every 2 x 2 window of periodic 4 x 4 patches (n, 4, 4, 2), the one starting at
    pillar row ``a``, column ``b`` at index ``4 a + b`` (wrapping round the patch's period); the four at even
    ``a`` and ``b`` are its supercells."""
    w = np.asarray(patches)
    rows = [[a, (a + 1) % 4] for a in range(4)]
    return np.stack([w[:, r][:, :, c] for r in rows for c in rows], 1)


def neighbour_windows(nbhd: np.ndarray) -> np.ndarray:
    """(n, 3, 2, 2, 2): the three 2 x 2 windows that straddle a supercell's edges towards +x, +y and +x+y,
    from its 3 x 3 pillar neighbourhood ``nbhd`` (n, 3, 3, 2) (the supercell at rows and columns 0-1):
    the windows starting at pillar (0, 1), (1, 0) and (1, 1)."""
    w = np.asarray(nbhd)
    return np.stack([w[:, 0:2, 1:3], w[:, 1:3, 0:2], w[:, 1:3, 1:3]], 1)


def window_ring(t_windows: np.ndarray, t_self: np.ndarray) -> np.ndarray:
    """(n, 2) the neighbour-ring term of supercells under overlapping windows: the mean of the supercell's
    own ``t_self`` (n, 2) and its three straddling windows' ``t_windows`` (n, 3, 2) (each a 2 x 2 cell
    solved periodically: :func:`neighbour_windows`), minus its own.  Summed over a device (or a periodic
    patch) it makes the device's transmission the mean over every 2 x 2 window of its pillars, so each
    pillar sees its actual neighbours on all four sides rather than copies of its own supercell: the
    overlapping-patch idea (WO2023218712; Zhelyeznyakov et al., Communications Engineering 2023) at the
    scale of the 2 x 2 model, with no new fitted parameter."""
    tw = np.asarray(t_windows)
    return (tw.sum(1) + np.asarray(t_self)) / 4 - np.asarray(t_self)


def save_peds(path: str | Path, model: PedsModel) -> Path:
    """The model as one JSON file, a card-only model of :mod:`metadesign.cards` (:func:`~metadesign.cards.save_card`:
    format, levels, coefficients, library, the card's entries; ``trained_on``: the card's ``table``)."""
    rec = {"harmonics": list(model.harmonics),
           "coef": [[float(complex(a).real), float(complex(a).imag)] for a in model.coef],
           "library": {"sha256": model.library_sha256}, **{k: v for k, v in model.card.items() if k != "trained_on"}}
    return save_card(path, PEDS_FORMAT, rec, trained_on=model.card.get("trained_on", model.card.get("table")))


def load_peds(path: str | Path, lib: UnitCellLibrary | None = None) -> PedsModel:
    """A saved model (:func:`~metadesign.cards.read_card`; files written before ``trained_on`` read the same);
    with ``lib``, checked to be calibrated against that library."""
    try:
        rec = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise ValidationError(f"{path}: not a PEDS supercell model ({e})") from None
    if not isinstance(rec, dict) or rec.get("format") != PEDS_FORMAT:
        raise ValidationError(f"{path}: not a PEDS supercell model ({PEDS_FORMAT})")
    _, _, rec = read_card(path, PEDS_FORMAT, "PEDS supercell model")
    try:
        sha = str((rec.get("library") or {}).get("sha256", ""))
        harmonics = tuple(int(h) for h in rec["harmonics"])
        coef = tuple(complex(float(a), float(b)) for a, b in rec["coef"])
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ValidationError(f"{path}: a PEDS model needs harmonics, coef ([re, im] per level) and library "
                              f"({type(e).__name__}: {e})") from None
    if lib is not None and sha != lib.identity:
        raise ValidationError(f"{path}: calibrated against another library (sha256 {sha[:12]}), not this one "
                              f"({lib.identity[:12]})")
    card = {k: v for k, v in rec.items() if k not in ("format", "harmonics", "coef", "library")}
    card["library"] = rec.get("library")
    return PedsModel(harmonics, coef, sha, card)


def find_peds(lib: UnitCellLibrary) -> Path:
    """The PEDS model calibrated against ``lib`` among the JSON files of the products' ``library/`` folder."""
    found = find_fitted(lib.identity, PEDS_FORMAT, (repo_root() / "library",))
    if found is not None:
        return found[0]
    raise ValidationError(f"no PEDS supercell model calibrated against this library (sha256 {lib.identity[:12]}) "
                          "in library/; calibrate one (metadesign library peds TABLE)")


def certified_t(lib: UnitCellLibrary, widths: np.ndarray, partial: str | Path, model: PedsModel | str | Path | None = None,
                *, workers: int = 1, scheduler: str | None = None,
                progress: Callable[[int, int], None] | None = None, stack: Stack | None = None,
                t_unit: np.ndarray | None = None, taper: tuple[float, int] | None = None) -> np.ndarray:
    """(n, 2) complex: the certified surrogate's transmissions (x-pol, y-pol) of supercells ``widths``
    (n, 2, 2, 2) m, for ``lib`` (``model``: a :class:`PedsModel`, its file, or None for the one in
    ``library/`` calibrated against ``lib``).  Solves each supercell at the model's levels (chunks under
    ``partial``: resumable; the caller removes it).  ``stack``: the pillars' stack if not the library's
    (an etch-depth error: the low-fidelity solves at that height), with ``t_unit`` (n, 2, 2, 2 pol) the
    four pillars' unit-cell ``t`` there (the LPA part; default: the library's); ``taper = (sidewall_deg,
    slices)``: the low-fidelity solves with sloped walls (the widths at mid-height)."""
    if not isinstance(model, PedsModel):
        model = load_peds(model if model is not None else find_peds(lib), lib)
    elif model.library_sha256 and model.library_sha256 != lib.identity:
        raise ValidationError(f"certified_t: the model was calibrated against another library (sha256 "
                              f"{model.library_sha256[:12]}), not this one ({lib.identity[:12]})")
    w = np.asarray(widths, float)
    if w.ndim != 4 or w.shape[1:] != (2, 2, 2):
        raise ValidationError(f"certified_t: widths must be (n, 2, 2, 2) metres, got {w.shape}")
    st = lib.stack if stack is None else stack
    if (st.wavelength, st.period) != (lib.stack.wavelength, lib.stack.period):
        raise ValidationError("certified_t: the stack's wavelength and period must be the library's")
    c, _ = low_fidelity_couplings(w, st, model.harmonics, partial, workers=workers, scheduler=scheduler,
                                  progress=progress, taper=taper)
    tu = interpolate_t(lib, w[..., 0], w[..., 1])[0] if t_unit is None else np.asarray(t_unit)
    return peds_t(model.coef, c, lpa_t(tu))

"""As-fabricated transmission: pillar widths read from the layout, fab
perturbations, and complex-t look-up in the full RCWA library.

The complex transmission (never the wrapped phase) is interpolated
bilinearly across the library's (wx, wy) grid.  Perturbations, applied to
each pillar's widths before the look-up:

* ``bias`` per axis (nm, uniform);
* ``jitter`` (nm, Gaussian sigma, independent per pillar and axis, seeded);
* ``corner_radius`` (nm): rounded corners replaced by the rectangle of equal
  area and equal aspect ratio (an approximation: the rounded pillar's modes
  are not exactly those of that rectangle);
* ``height`` (etch depth error, nm) and ``sidewall_deg`` (wall angle), global, each with an optional
  linear across-wafer gradient along x (``*_gradient``: the change at the aperture's +x edge, the
  opposite at the -x edge).  These need a library built with height / sidewall axes
  (``[fab_axes]``): the look-up is then multilinear in (wx, wy, height, angle).

Pillars pushed outside the library's width range are clamped to it and
*counted* (reported by the callers), never silently.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .. import jit
from ..library.store import UnitCellLibrary, interpolate_t
from ..validation import ValidationError, check_int, check_number

__all__ = ["Perturbation", "interpolate_t", "interpolate_t_fab", "perturb_widths", "pillar_transmission",
           "couple_supercells", "coupling_model", "unit_t_as_made"]


@dataclass(frozen=True)
class Perturbation:
    bias_x: float = 0.0  # m
    bias_y: float = 0.0  # m
    jitter: float = 0.0  # m (sigma)
    corner_radius: float = 0.0  # m
    seed: int = 0
    height: float = 0.0  # m: etch depth error (pillar height - nominal)
    sidewall_deg: float = 90.0  # wall angle (90: vertical)
    height_gradient: float = 0.0  # m: extra height error at the aperture's +x edge (linear in x)
    sidewall_gradient_deg: float = 0.0  # extra wall angle at the +x edge

    def __post_init__(self) -> None:
        for name in ("bias_x", "bias_y"):
            check_number(f"perturbation.{name}", getattr(self, name), -200e-9, 200e-9, unit="m")
        check_number("perturbation.jitter", self.jitter, 0, 100e-9, unit="m")
        check_number("perturbation.corner_radius", self.corner_radius, 0, 500e-9, unit="m")
        check_int("perturbation.seed", self.seed, 0, 2**63 - 1)
        check_number("perturbation.height", self.height, -500e-9, 500e-9, unit="m")
        check_number("perturbation.sidewall_deg", self.sidewall_deg, 60, 90)
        check_number("perturbation.height_gradient", self.height_gradient, -500e-9, 500e-9, unit="m")
        check_number("perturbation.sidewall_gradient_deg", self.sidewall_gradient_deg, -30, 30)

    #: the perturbation kinds, by their one spelling (recipes, CLI options, records: lengths in nm)
    KINDS = ("bias_x_nm", "bias_y_nm", "jitter_nm", "corner_nm", "seed", "height_nm", "sidewall_deg",
             "height_gradient_nm", "sidewall_gradient_deg")

    @classmethod
    def from_nm(cls, bias_x_nm: float = 0.0, bias_y_nm: float | None = None, jitter_nm: float = 0.0,
                corner_nm: float = 0.0, seed: int = 0, height_nm: float = 0.0, sidewall_deg: float = 90.0,
                height_gradient_nm: float = 0.0, sidewall_gradient_deg: float = 0.0) -> "Perturbation":
        """From the recorded units (nm, degrees); ``bias_y_nm`` defaults to ``bias_x_nm`` (isotropic)."""
        return cls(bias_x_nm * 1e-9, (bias_x_nm if bias_y_nm is None else bias_y_nm) * 1e-9, jitter_nm * 1e-9,
                   corner_nm * 1e-9, int(seed), height_nm * 1e-9, sidewall_deg, height_gradient_nm * 1e-9,
                   sidewall_gradient_deg)

    @classmethod
    def from_config(cls, section: dict) -> "Perturbation":
        """From a parsed recipe section keyed by :attr:`KINDS` (lengths already in metres: the config layer
        converts ``*_nm`` keys once at load)."""
        f = section
        return cls(f["bias_x_nm"], f["bias_y_nm"], f["jitter_nm"], f["corner_nm"], f["seed"], f["height_nm"],
                   f["sidewall_deg"], f["height_gradient_nm"], f["sidewall_gradient_deg"])

    @property
    def has_fab_axes(self) -> bool:
        return bool(self.height or self.sidewall_deg != 90.0 or self.height_gradient or self.sidewall_gradient_deg)

    def to_dict(self) -> dict:
        d = {"bias_x_nm": self.bias_x * 1e9, "bias_y_nm": self.bias_y * 1e9, "jitter_nm": self.jitter * 1e9,
             "corner_nm": self.corner_radius * 1e9, "seed": self.seed}
        if self.has_fab_axes:  # absent when unused: records (and the hashes made of them) are unchanged
            d.update({"height_nm": self.height * 1e9, "sidewall_deg": self.sidewall_deg,
                      "height_gradient_nm": self.height_gradient * 1e9,
                      "sidewall_gradient_deg": self.sidewall_gradient_deg})
        return d

    @property
    def is_null(self) -> bool:
        return not (self.bias_x or self.bias_y or self.jitter or self.corner_radius or self.has_fab_axes)


def perturb_widths(wx: np.ndarray, wy: np.ndarray, pert: Perturbation,
                   rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Perturbed widths (m) of pillars with nominal widths ``wx, wy``."""
    wx = np.asarray(wx, np.float64) + pert.bias_x
    wy = np.asarray(wy, np.float64) + pert.bias_y
    if pert.jitter:
        rng = rng or np.random.default_rng(pert.seed)
        wx = wx + rng.normal(0.0, pert.jitter, wx.shape)
        wy = wy + rng.normal(0.0, pert.jitter, wy.shape)
    if pert.corner_radius:
        r = np.minimum(pert.corner_radius, 0.5 * np.minimum(wx, wy))
        s = np.sqrt(np.clip(1.0 - (4.0 - np.pi) * r * r / (wx * wy), 0.0, 1.0))
        wx, wy = wx * s, wy * s
    return wx, wy


def _interp_fab(lib: UnitCellLibrary, wx, wy, height, angle):
    """``(t (..., 2) complex, clamped (...) bool)``: multilinear in the four axes of ``lib.fab``."""
    fab = lib.fab
    if fab is None:
        raise ValidationError("height / sidewall perturbations need a library with fab axes (build one with a "
                              "[fab_axes] section: heights_um, sidewall_deg; pass it as --fab-library)")
    vals = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (wx, wy, height, angle)))
    grids = (lib.wx, lib.wy, np.asarray(fab["heights"]), np.asarray(fab["sidewalls"]))
    out = np.zeros(vals[0].shape, bool)
    idx, frac = [], []
    for v, g in zip(vals, grids):
        tol = 1e-9 * max(1.0, abs(g[-1])) if g[-1] > 1e-3 else 1e-12  # degrees / metres
        out |= (v < g[0] - tol) | (v > g[-1] + tol)
        if len(g) == 1:  # a single value on this axis: its only corner, weight 1
            idx.append(np.zeros(v.shape, np.int64))
            frac.append(None)
            continue
        f = np.interp(v, g, np.arange(len(g)))
        i0 = np.minimum(np.floor(f).astype(np.int64), len(g) - 2)
        idx.append(i0)
        frac.append(f - i0)
    tab = np.stack([fab["jones"][..., 0, 0], fab["jones"][..., 1, 1]], axis=-1)  # (nx, ny, nh, na, 2)
    t = np.zeros((*out.shape, 2), complex)
    for bits in itertools.product((0, 1), repeat=4):
        if any(b and f is None for b, f in zip(bits, frac)):
            continue
        w = np.ones(out.shape)
        for b, f in zip(bits, frac):
            if f is not None:
                w = w * (f if b else 1 - f)
        t += w[..., None] * tab[tuple(i0 + b for i0, b in zip(idx, bits))]
    return t, out


def interpolate_t_fab(lib: UnitCellLibrary, wx, wy, height, angle):
    """Multilinear complex interpolation of ``(t_x, t_y)`` in (wx, wy, height, sidewall angle) of a library
    with fab axes; arguments broadcast.  Returns ``(t (..., 2) complex64, n_clamped)`` (pillars outside any
    axis are clamped to it and counted)."""
    t, out = _interp_fab(lib, wx, wy, height, angle)
    return t.astype(np.complex64), int(out.sum())


def _fab_axes_of(pert: Perturbation, lib: UnitCellLibrary, shape: tuple[int, int], cols: int):
    """Per-pillar height (m) and wall angle (deg) of rows of ``shape`` (gradients linear in the column)."""
    h0 = float(lib.meta["stack"]["height_m"]) + pert.height
    u = (np.arange(shape[1]) - (cols - 1) / 2) / (cols / 2)  # -1 .. +1 across the aperture
    h = h0 + pert.height_gradient * u
    a = pert.sidewall_deg + pert.sidewall_gradient_deg * u
    return np.broadcast_to(h[None, :], shape), np.broadcast_to(np.minimum(a, 90.0)[None, :], shape)


def pillar_transmission(index_map: np.ndarray, atom_widths_nm: np.ndarray, lib: UnitCellLibrary,
                        pert: Perturbation = Perturbation(), rows: slice | None = None,
                        rng: np.random.Generator | None = None, fab_lib: UnitCellLibrary | None = None,
                        coupling=None):
    """Complex transmission ``(rows, n, 2)`` of the pillars in ``index_map``
    (``-1`` = no pillar: the bare stack's ``t``), perturbed.  Without jitter the
    look-up is done once per atom.  Returns ``(t, n_clamped)``.

    Height and sidewall perturbations: ``t = t_lib(w) + t_F(w, h, a) - t_F(w, h0, 90)`` with ``F`` the
    library with fab axes (``fab_lib``, or ``lib`` itself when it has them): exact when ``F`` is ``lib``
    with axes, and otherwise a correction from a (possibly coarser) fab library on top of the design's own
    library, which the nominal device keeps exactly.

    ``coupling`` (a :mod:`metadesign.library.coupling` model, or any supercell surrogate of
    :mod:`metadesign.library.surrogates` that gives per-pillar terms; None = the LPA, unchanged): every pillar
    of a complete 2 x 2 supercell gets its coupling term from its neighbours' perturbed widths and looked-up
    ``t`` (:func:`couple_supercells`); ``rows`` must then start on a supercell row."""
    im = index_map if rows is None else index_map[rows]
    coupling = coupling_model(coupling)
    want = coupling is not None
    if want and rows is not None and (rows.start or 0) % 2:
        raise ValueError("coupled transmission needs row tiles that start on a supercell (even) row")
    if pert.has_fab_axes:
        t, clamped, w, atoms = _pillar_transmission_fab(im, index_map.shape[1], atom_widths_nm, lib, pert, rng,
                                                        fab_lib, want)
    else:
        t, clamped, w, atoms = _pillar_transmission_lpa(im, atom_widths_nm, lib, pert, rng, want)
    if want:
        t = couple_supercells(t, w, im >= 0, coupling, atoms=atoms)
    return t, clamped


class _SurrogateTerms:
    """A supercell surrogate's per-pillar terms in the coupling network's calling convention."""

    cfg = None

    def __init__(self, s):
        self.surrogate = s

    def terms(self, widths, t_units, batch: int = 65536):
        return self.surrogate.pillar_terms(widths, t_units)


def coupling_model(coupling):
    """What the pupil runs for ``coupling``: None (the LPA) and a coupling network as they are; a supercell
    surrogate (:mod:`metadesign.library.surrogates`): none for the LPA, its network for the coupling network
    (pair tables included), else its :meth:`pillar_terms` (a model without them refuses, one line)."""
    if coupling is None or hasattr(coupling, "cfg"):
        return coupling
    if getattr(coupling, "name", None) == "lpa":
        return None
    net = getattr(coupling, "model", None)
    if hasattr(net, "cfg") and hasattr(net, "terms"):
        return net
    return _SurrogateTerms(coupling)


def couple_supercells(t: np.ndarray, w: np.ndarray, has: np.ndarray, model, batch: int = 65536,
                      atoms: tuple | None = None) -> np.ndarray:
    """``t`` (R, C, 2) of pillars with widths ``w`` (R, C, 2) m, plus each pillar's coupling term where its
    whole 2 x 2 supercell (rows 2I, 2I+1; columns 2J, 2J+1) has pillars; elsewhere (an aperture's edge,
    empty cells) the LPA's ``t`` stays.  Supercells are evaluated in batches (bounded memory).
    ``atoms = (index (R, C), widths (A, 2), t (A, 2))``: the pillars are drawn from a finite table (no
    jitter), so a pair model's terms are table look-ups (:func:`metadesign.library.coupling_net.pair_tables`,
    the same numbers without running the network per supercell)."""
    model = coupling_model(model)
    if model is None:
        return t
    R2, C2 = t.shape[0] // 2, t.shape[1] // 2

    def blocks(a):  # (R, C, ...) -> (R2 * C2, 2, 2, ...) as [supercell, r, c]
        a = a[:2 * R2, :2 * C2]
        return a.reshape(R2, 2, C2, 2, *a.shape[2:]).swapaxes(1, 2).reshape(R2 * C2, 2, 2, *a.shape[2:])

    full = blocks(has).all((1, 2))
    idx = np.flatnonzero(full)
    if not len(idx):
        return t
    terms = np.zeros((R2 * C2, 2, 2, 2), np.complex64)
    if atoms is not None and getattr(getattr(model, "cfg", None), "interaction", None) == "pair":
        k_at, w_at, t_at = atoms
        tab = _pair_table_cache(model, w_at, t_at)
        ab = blocks(np.asarray(k_at))[idx]  # (n, 2, 2) atom of each pillar
        for r in range(2):
            for c in range(2):
                own = ab[:, r, c]
                for kind, (rr, cc) in enumerate(((r, 1 - c), (1 - r, c), (1 - r, 1 - c))):
                    terms[idx, r, c] += tab[kind][:, own, ab[:, rr, cc]].T
    else:
        wb, tb = blocks(w), blocks(t)
        for a in range(0, len(idx), batch):
            k = idx[a:a + batch]
            terms[k] = model.terms(wb[k], tb[k], batch)
    out = t.copy()
    out[:2 * R2, :2 * C2] += terms.reshape(R2, C2, 2, 2, 2).swapaxes(1, 2).reshape(2 * R2, 2 * C2, 2)
    return out


_TABLES: dict = {}


def _pair_table_cache(model, w_at, t_at):
    """The pair tables of ``model`` over an atom table, kept for the row tiles of one pupil."""
    key = (id(model), np.asarray(w_at).tobytes(), np.asarray(t_at).tobytes())
    if key not in _TABLES:
        _TABLES.clear()
        _TABLES[key] = model.tables(np.asarray(w_at), np.asarray(t_at))
    return _TABLES[key]


@jit.njit
def _lookup(im, table):
    """``table[im]`` per pillar, the last row of ``table`` for an empty cell (``im < 0``): numpy's fancy
    index without its int64 copy of the map (the same values)."""
    R, C = im.shape
    empty = table.shape[0] - 1
    t = np.empty((R, C, 2), table.dtype)
    for r in range(R):
        for c in range(C):
            k = im[r, c]
            if k < 0:
                k = empty
            t[r, c, 0] = table[k, 0]
            t[r, c, 1] = table[k, 1]
    return t


def _pillar_transmission_lpa(im, atom_widths_nm, lib, pert, rng, want_widths: bool):
    n_sub = lib.meta["stack"]["n_substrate"]
    n_sup = lib.meta["stack"]["n_superstrate"]
    bare = np.complex64(2 * n_sub / (n_sub + n_sup))
    w = np.asarray(atom_widths_nm, np.float64) * 1e-9
    if not pert.jitter:
        wx, wy = perturb_widths(w[:, 0], w[:, 1], pert)
        t_atoms, _, n_out_atoms = interpolate_t(lib, wx, wy)
        table = np.concatenate([t_atoms, np.full((1, 2), bare, np.complex64)])
        if (jit.enabled() and not want_widths and not n_out_atoms  # the nominal look-up, compiled
                and (im.size == 0 or int(im.max()) < len(w))):  # (an index beyond the atoms: numpy raises)
            return _lookup(np.ascontiguousarray(im), table), 0, None, None
        k = np.where(im < 0, len(w), im)
        t = table[k]
        clamped = 0
        if n_out_atoms:
            bad = np.zeros(len(w) + 1, bool)
            bad[:-1] = ((wx < lib.wx[0]) | (wx > lib.wx[-1]) | (wy < lib.wy[0]) | (wy > lib.wy[-1]))
            clamped = int(bad[k].sum())
        widths = np.stack([np.append(wx, 0.0)[k], np.append(wy, 0.0)[k]], -1) if want_widths else None
        return t, clamped, widths, (k, np.stack([wx, wy], -1), t_atoms) if want_widths else None
    has = im >= 0
    k = np.where(has, im, 0)
    wx, wy = perturb_widths(w[k, 0], w[k, 1], pert, rng)
    t, _, clamped = interpolate_t(lib, np.where(has, wx, lib.wx[0]), np.where(has, wy, lib.wy[0]))
    t[~has] = bare
    return t, clamped, (np.stack([wx, wy], -1) if want_widths else None), None


def _fab_t(lib: UnitCellLibrary, F: UnitCellLibrary, wx, wy, h, a):
    """``t_lib(w) + t_F(w, h, a) - t_F(w, h0, 90)`` (just ``t_F`` when ``F`` is ``lib``) and the clamped mask."""
    tf, out = _interp_fab(F, wx, wy, h, a)
    if F is lib:
        return tf, out
    h0 = float(lib.meta["stack"]["height_m"])
    base, _, _ = interpolate_t(lib, wx, wy)
    tn, _ = _interp_fab(F, wx, wy, h0, 90.0)
    gx, gy = lib.wx, lib.wy
    out = out | (wx < gx[0] - 1e-12) | (wx > gx[-1] + 1e-12) | (wy < gy[0] - 1e-12) | (wy > gy[-1] + 1e-12)
    return base + tf - tn, out


def unit_t_as_made(lib: UnitCellLibrary, wx, wy, pert: Perturbation = Perturbation(),
                   fab_lib: UnitCellLibrary | None = None) -> np.ndarray:
    """(..., 2) complex64: the unit-cell ``t`` of pillars of (already perturbed) widths ``wx, wy`` m at the
    global etch depth and wall angle of ``pert``, as the device's pillars get it (the design's library, plus
    ``fab_lib``'s change with height and angle).  Across-aperture gradients are per-pillar: not here."""
    if pert.height_gradient or pert.sidewall_gradient_deg:
        raise ValueError("unit_t_as_made: global height and wall angle only (gradients vary across the device)")
    if not pert.has_fab_axes:
        return interpolate_t(lib, wx, wy)[0]
    F = fab_lib if fab_lib is not None else lib
    h0 = float(lib.meta["stack"]["height_m"])
    return _fab_t(lib, F, np.asarray(wx, np.float64), np.asarray(wy, np.float64), h0 + pert.height,
                  min(pert.sidewall_deg, 90.0))[0].astype(np.complex64)


def _pillar_transmission_fab(im, cols, atom_widths_nm, lib, pert, rng, fab_lib=None, want_widths=False):
    """The look-up with height / sidewall perturbations: once per atom for a global height and angle without
    jitter, else per pillar (gradients and jitter make every pillar its own)."""
    F = fab_lib if fab_lib is not None else lib
    for key in ("wavelength_m", "period_m", "height_m"):
        if abs(F.meta["stack"][key] - lib.meta["stack"][key]) > 1e-12:
            raise ValidationError(f"the fab library's stack differs from the design's library ({key})")
    n_sub = lib.meta["stack"]["n_substrate"]
    n_sup = lib.meta["stack"]["n_superstrate"]
    bare = np.complex64(2 * n_sub / (n_sub + n_sup))
    w = np.asarray(atom_widths_nm, np.float64) * 1e-9
    has = im >= 0
    h0 = float(lib.meta["stack"]["height_m"])
    if not (pert.jitter or pert.height_gradient or pert.sidewall_gradient_deg):
        ax, ay = perturb_widths(w[:, 0], w[:, 1], pert)
        t_atoms, bad = _fab_t(lib, F, ax, ay, h0 + pert.height, min(pert.sidewall_deg, 90.0))
        table = np.concatenate([t_atoms.astype(np.complex64), np.full((1, 2), bare, np.complex64)])
        k = np.where(has, im, len(w))
        widths = np.stack([np.append(ax, 0.0)[k], np.append(ay, 0.0)[k]], -1) if want_widths else None
        atoms = (k, np.stack([ax, ay], -1), t_atoms.astype(np.complex64)) if want_widths else None
        return table[k], int(np.append(bad, False)[k].sum()), widths, atoms
    k = np.where(has, im, 0)
    wx, wy = perturb_widths(w[k, 0], w[k, 1], pert, rng if pert.jitter else None)
    h, a = _fab_axes_of(pert, lib, im.shape, cols)
    t = np.full((*im.shape, 2), bare, np.complex64)
    tt, bad = _fab_t(lib, F, wx[has], wy[has], h[has], a[has])
    t[has] = tt
    return t, int(bad.sum()), (np.stack([wx, wy], -1) if want_widths else None), None

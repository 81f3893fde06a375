"""As-fabricated transmission: pillar widths read from the layout, fab
perturbations, and complex-t look-up in the full RCWA library.

The complex transmission (never the wrapped phase) is interpolated
bilinearly across the library's (wx, wy) grid.  Perturbations, applied to
each pillar's widths before the look-up:

* ``bias`` per axis (nm, uniform);
* ``jitter`` (nm, Gaussian sigma, independent per pillar and axis, seeded);
* ``corner_radius`` (nm): rounded corners replaced by the rectangle of equal
  area and equal aspect ratio (an approximation: the rounded pillar's modes
  are not exactly those of that rectangle).

Pillars pushed outside the library's width range are clamped to it and
*counted* (reported by the callers), never silently.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..library.store import UnitCellLibrary
from ..validation import check_int, check_number

__all__ = ["Perturbation", "interpolate_t", "perturb_widths", "pillar_transmission"]


@dataclass(frozen=True)
class Perturbation:
    bias_x: float = 0.0  # m
    bias_y: float = 0.0  # m
    jitter: float = 0.0  # m (sigma)
    corner_radius: float = 0.0  # m
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("bias_x", "bias_y"):
            check_number(f"perturbation.{name}", getattr(self, name), -200e-9, 200e-9, unit="m")
        check_number("perturbation.jitter", self.jitter, 0, 100e-9, unit="m")
        check_number("perturbation.corner_radius", self.corner_radius, 0, 500e-9, unit="m")
        check_int("perturbation.seed", self.seed, 0, 2**63 - 1)

    def to_dict(self) -> dict:
        return {"bias_x_nm": self.bias_x * 1e9, "bias_y_nm": self.bias_y * 1e9, "jitter_nm": self.jitter * 1e9,
                "corner_radius_nm": self.corner_radius * 1e9, "seed": self.seed}

    @property
    def is_null(self) -> bool:
        return not (self.bias_x or self.bias_y or self.jitter or self.corner_radius)


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


def interpolate_t(lib: UnitCellLibrary, wx: np.ndarray, wy: np.ndarray):
    """Bilinear complex interpolation of ``(t_x, t_y)`` and ``T0`` at widths
    (m).  Returns ``(t (..., 2) complex64, T0 (..., 2) float32, n_clamped)``."""
    wx = np.asarray(wx, np.float64)
    wy = np.asarray(wy, np.float64)
    gx, gy = lib.wx, lib.wy
    out = (wx < gx[0] - 1e-12) | (wx > gx[-1] + 1e-12) | (wy < gy[0] - 1e-12) | (wy > gy[-1] + 1e-12)
    fx = np.interp(wx, gx, np.arange(len(gx)))
    fy = np.interp(wy, gy, np.arange(len(gy)))
    i0 = np.minimum(np.floor(fx).astype(np.int64), len(gx) - 2)
    j0 = np.minimum(np.floor(fy).astype(np.int64), len(gy) - 2)
    ax, ay = (fx - i0)[..., None], (fy - j0)[..., None]
    tab = np.stack([lib.t_x, lib.t_y], axis=-1)  # (nx, ny, 2)
    T = lib.T0
    t = ((1 - ax) * (1 - ay) * tab[i0, j0] + ax * (1 - ay) * tab[i0 + 1, j0]
         + (1 - ax) * ay * tab[i0, j0 + 1] + ax * ay * tab[i0 + 1, j0 + 1])
    T0 = ((1 - ax) * (1 - ay) * T[i0, j0] + ax * (1 - ay) * T[i0 + 1, j0]
          + (1 - ax) * ay * T[i0, j0 + 1] + ax * ay * T[i0 + 1, j0 + 1])
    return t.astype(np.complex64), T0.astype(np.float32), int(out.sum())


def pillar_transmission(index_map: np.ndarray, atom_widths_nm: np.ndarray, lib: UnitCellLibrary,
                        pert: Perturbation = Perturbation(), rows: slice | None = None,
                        rng: np.random.Generator | None = None):
    """Complex transmission ``(rows, n, 2)`` of the pillars in ``index_map``
    (``-1`` = no pillar: the bare stack's ``t``), perturbed.  Without jitter the
    look-up is done once per atom.  Returns ``(t, n_clamped)``."""
    im = index_map if rows is None else index_map[rows]
    n_sub = lib.meta["stack"]["n_substrate"]
    n_sup = lib.meta["stack"]["n_superstrate"]
    bare = np.complex64(2 * n_sub / (n_sub + n_sup))
    w = np.asarray(atom_widths_nm, np.float64) * 1e-9
    if not pert.jitter:
        wx, wy = perturb_widths(w[:, 0], w[:, 1], pert)
        t_atoms, _, n_out_atoms = interpolate_t(lib, wx, wy)
        table = np.concatenate([t_atoms, np.full((1, 2), bare, np.complex64)])
        k = np.where(im < 0, len(w), im)
        t = table[k]
        clamped = 0
        if n_out_atoms:
            bad = np.zeros(len(w) + 1, bool)
            bad[:-1] = ((wx < lib.wx[0]) | (wx > lib.wx[-1]) | (wy < lib.wy[0]) | (wy > lib.wy[-1]))
            clamped = int(bad[k].sum())
        return t, clamped
    has = im >= 0
    k = np.where(has, im, 0)
    wx, wy = perturb_widths(w[k, 0], w[k, 1], pert, rng)
    t, _, clamped = interpolate_t(lib, np.where(has, wx, lib.wx[0]), np.where(has, wy, lib.wy[0]))
    t[~has] = bare
    return t, clamped

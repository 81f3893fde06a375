"""The unit-cell library product: save, load (validated, no pickle), export."""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import InputError
from ..tasks import file_key
from ..io import atomic_path, json_array, read_product, write_npz
from .rcwa import Stack

__all__ = ["UnitCellLibrary", "interpolate_t", "load_library", "save_library", "export_csv", "FORMAT"]

FORMAT = "metadesign.unit-cell-library/1"
EFFICIENCY_TOL = 1e-6


@dataclass(frozen=True)
class UnitCellLibrary:
    """Complex transmission of a (wx, wy) pillar sweep.

    Arrays are indexed ``[i_wx, i_wy, ...]``; ``jones[..., out, in]`` with
    0 = x-pol, 1 = y-pol; efficiencies ``[..., in]``.  Widths in metres.
    """

    wx: np.ndarray
    wy: np.ndarray
    jones: np.ndarray
    T0: np.ndarray
    T_total: np.ndarray
    R_total: np.ndarray
    meta: dict = field(default_factory=dict)
    identity: str = ""  # sha256 of the file it was loaded from
    #: optional height / sidewall axes: {"heights" (nh,) m, "sidewalls" (na,) deg, "jones" (nx, ny, nh, na, 2, 2),
    #: "T0", "T_total", "R_total" (nx, ny, nh, na, 2)}; the main arrays are its nominal slice
    fab: dict | None = None

    @property
    def t_x(self) -> np.ndarray:
        return self.jones[..., 0, 0]

    @property
    def t_y(self) -> np.ndarray:
        return self.jones[..., 1, 1]

    @property
    def phase_x(self) -> np.ndarray:
        return np.angle(self.t_x)

    @property
    def phase_y(self) -> np.ndarray:
        return np.angle(self.t_y)

    @property
    def wavelength(self) -> float:
        return float(self.meta["stack"]["wavelength_m"])

    @property
    def period(self) -> float:
        return float(self.meta["stack"]["period_m"])

    @property
    def stack(self) -> Stack:
        """The layer stack the table was solved for (wavelength, period, height, indices)."""
        st = self.meta["stack"]
        return Stack(st["wavelength_m"], st["period_m"], st["height_m"], st["n_pillar"], st["n_substrate"],
                     st["n_superstrate"])

    def summary(self, threshold: float = 0.7) -> dict:
        keep = (self.T0[..., 0] >= threshold) & (self.T0[..., 1] >= threshold)
        conv = self.meta.get("convergence", {})
        return {
            "file_identity": self.identity,
            "grid": {
                "n_wx": int(len(self.wx)),
                "n_wy": int(len(self.wy)),
                "wx_um": [float(self.wx[0] * 1e6), float(self.wx[-1] * 1e6)],
                "wy_um": [float(self.wy[0] * 1e6), float(self.wy[-1] * 1e6)],
                "step_nm": float(np.round((self.wx[1] - self.wx[0]) * 1e9, 4)) if len(self.wx) > 1 else 0.0,
            },
            "stack": self.meta.get("stack"),
            "solver": self.meta.get("solver"),
            "convergence": {k: conv.get(k) for k in ("passed", "max_phase_change_rad", "max_T0_change",
                                                      "n_harmonics", "reference_n_harmonics", "tolerance_rad")},
            "transmission_threshold": threshold,
            "fraction_above_threshold": float(keep.mean()),
            "n_cells_above_threshold": int(keep.sum()),
            "mean_T0": [float(self.T0[..., 0].mean()), float(self.T0[..., 1].mean())],
            "max_cross_pol": float(np.abs(self.jones[..., [0, 1], [1, 0]]).max()),
            "max_energy_error": float(np.abs(self.T_total + self.R_total - 1).max()),
            "phase_coverage_2d": float(coverage_fraction(self, threshold)),
        }


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


def coverage_fraction(lib: UnitCellLibrary, threshold: float = 0.7, bins: int = 16) -> float:
    """Fraction of the bins x bins (phase_x, phase_y) torus cells holding a kept pillar."""
    keep = (lib.T0[..., 0] >= threshold) & (lib.T0[..., 1] >= threshold)
    px = lib.phase_x[keep]
    py = lib.phase_y[keep]
    ix = np.floor((px + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    iy = np.floor((py + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    occ = np.zeros((bins, bins), bool)
    occ[ix, iy] = True
    return occ.mean()


def save_library(path: str | Path, lib: UnitCellLibrary) -> None:
    meta = dict(lib.meta)
    meta["format"] = FORMAT
    arrays = {
        "wx_m": lib.wx.astype(np.float64),
        "wy_m": lib.wy.astype(np.float64),
        "jones": lib.jones.astype(np.complex128),
        "T0": lib.T0.astype(np.float64),
        "T_total": lib.T_total.astype(np.float64),
        "R_total": lib.R_total.astype(np.float64),
        "meta": json_array(meta),
    }
    if lib.fab is not None:  # 2-D libraries: no extra arrays, the same bytes as before the axes existed
        arrays.update({
            "fab_height_m": np.asarray(lib.fab["heights"], np.float64),
            "fab_sidewall_deg": np.asarray(lib.fab["sidewalls"], np.float64),
            "fab_jones": np.asarray(lib.fab["jones"], np.complex128),
            "fab_T0": np.asarray(lib.fab["T0"], np.float64),
            "fab_T_total": np.asarray(lib.fab["T_total"], np.float64),
            "fab_R_total": np.asarray(lib.fab["R_total"], np.float64),
        })
    write_npz(path, arrays)


def load_library(path: str | Path) -> UnitCellLibrary:
    """Load and validate a library file; problems raise a one-line InputError."""
    path = Path(path)
    z, meta = read_product(path, "unit-cell library", ("wx_m", "wy_m", "jones", "T0", "T_total", "R_total"), FORMAT)
    wx, wy = z["wx_m"], z["wy_m"]
    nx, ny = len(wx), len(wy)
    shapes = {"jones": (nx, ny, 2, 2), "T0": (nx, ny, 2), "T_total": (nx, ny, 2), "R_total": (nx, ny, 2)}
    for k, shp in shapes.items():
        if z[k].shape != shp:
            raise InputError(f"{path}: array {k} has shape {z[k].shape}, expected {shp}")
    for k in ("wx_m", "wy_m", "jones", "T0", "T_total", "R_total"):
        if not np.all(np.isfinite(z[k])):
            raise InputError(f"{path}: array {k} holds non-finite values")
    if nx < 2 or ny < 2 or np.any(np.diff(wx) <= 0) or np.any(np.diff(wy) <= 0):
        raise InputError(f"{path}: width grids must be strictly increasing with >= 2 points")
    for k in ("T0", "T_total", "R_total"):
        a = z[k]
        if a.max() > 1 + EFFICIENCY_TOL or a.min() < -EFFICIENCY_TOL:
            raise InputError(f"{path}: efficiency {k} outside [0, 1] (max {a.max():.6g}, min {a.min():.6g})")
    if np.any(z["T0"] > z["T_total"] + EFFICIENCY_TOL):
        raise InputError(f"{path}: 0th-order efficiency exceeds total efficiency")
    fab = None
    if "fab_jones" in z:
        nh, na = len(z.get("fab_height_m", ())), len(z.get("fab_sidewall_deg", ()))
        want = {"fab_jones": (nx, ny, nh, na, 2, 2), "fab_T0": (nx, ny, nh, na, 2), "fab_T_total": (nx, ny, nh, na, 2),
                "fab_R_total": (nx, ny, nh, na, 2)}
        for k, shp in want.items():
            if k not in z or z[k].shape != shp or not np.all(np.isfinite(z[k])):
                raise InputError(f"{path}: fab-axes array {k} missing, non-finite or not of shape {shp}")
        h, a = z["fab_height_m"], z["fab_sidewall_deg"]
        if nh < 1 or na < 1 or np.any(np.diff(h) <= 0) or np.any(np.diff(a) <= 0):
            raise InputError(f"{path}: fab axes must be strictly increasing")
        fab = {"heights": h, "sidewalls": a, "jones": z["fab_jones"], "T0": z["fab_T0"], "T_total": z["fab_T_total"],
               "R_total": z["fab_R_total"]}
    digest = file_key(path)
    return UnitCellLibrary(wx, wy, z["jones"], z["T0"], z["T_total"], z["R_total"], meta, digest, fab)


def export_csv(lib: UnitCellLibrary, out: str | Path) -> int:
    """One row per cell; returns the number of rows."""
    cols = ["wx_um", "wy_um", "t_x_re", "t_x_im", "t_y_re", "t_y_im", "phase_x_rad", "phase_y_rad",
            "t_xy_re", "t_xy_im", "t_yx_re", "t_yx_im", "T0_x", "T0_y", "Ttot_x", "Ttot_y", "R_x", "R_y"]
    n = 0
    with atomic_path(out) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(cols)
            for i, x in enumerate(lib.wx):
                for j, y in enumerate(lib.wy):
                    J = lib.jones[i, j]
                    w.writerow([f"{x*1e6:.4f}", f"{y*1e6:.4f}"] + [f"{v:.9g}" for v in (
                        J[0, 0].real, J[0, 0].imag, J[1, 1].real, J[1, 1].imag,
                        np.angle(J[0, 0]), np.angle(J[1, 1]),
                        J[0, 1].real, J[0, 1].imag, J[1, 0].real, J[1, 0].imag,
                        lib.T0[i, j, 0], lib.T0[i, j, 1], lib.T_total[i, j, 0], lib.T_total[i, j, 1],
                        lib.R_total[i, j, 0], lib.R_total[i, j, 1])])
                    n += 1
    return n

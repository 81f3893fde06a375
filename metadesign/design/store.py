"""Design file I/O and the ``metadesign design`` job (the I/O edge of stage 2).

``DESIGN/design.npz`` (read with ``allow_pickle=False``):

* ``index_map`` ``[iy, ix]`` uint8 (uint16 past 254 atoms): atom of each cell,
  the dtype's max value = no pillar (outside a circular clear aperture);
* ``atom_wx_m``, ``atom_wy_m`` (n,), ``atom_t`` (n, 2) complex ``[t_x, t_y]``,
  ``atom_T0`` (n, 2), ``atom_lib_index`` (n, 2);
* ``meta``: JSON with the recipe, the design spec (lenses, offsets), the
  library identity (sha256) and path, the constant phase offsets, the
  metrics, the conventions and the version.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..config import ConfigError, InputError
from ..io import atomic_write_text, json_array, read_product, write_npz
from ..library.locate import find_library, relative_to_product
from ..library.store import UnitCellLibrary, load_library
from ..validation import check_memory
from .build import DesignResult, discretize_design, empty_index
from .discretize import AtomTable, select_atoms
from .phase import LensChannel, SupercellSpec
from .recipe import DesignRecipe

__all__ = ["Design", "run_design", "save_design", "load_design", "design_file", "DESIGN_FORMAT", "check_library", "design_meta",
           "select_recipe_atoms", "design_memory_bytes"]

DESIGN_FORMAT = "metadesign.design/1"


@dataclass(frozen=True)
class Design:
    spec: SupercellSpec
    atoms: AtomTable
    index_map: np.ndarray
    offsets: tuple[float, float]
    metrics: dict
    meta: dict
    empty: int | None = None  # index-map value meaning "no pillar", if the design has such cells
    seconds: dict | None = None

    def atom_indices(self) -> np.ndarray:
        """The index map with the sentinel replaced by len(atoms) (for table look-ups)."""
        im = self.index_map
        return np.where(im == self.empty, len(self.atoms), im) if self.empty is not None else im


def check_library(recipe: DesignRecipe, lib: UnitCellLibrary) -> None:
    """Refuse a library made for another wavelength or period."""
    spec = recipe.spec
    for key, want, have, unit, scale in (
        ("design.wavelength_nm", spec.wavelength, lib.wavelength, "nm", 1e9),
        ("design.period_um", spec.period, lib.period, "um", 1e6),
    ):
        if abs(want - have) > 1e-9 * have:
            raise ConfigError(key, f"{want * scale:g} {unit} does not match the library ({have * scale:g} {unit}, "
                                   f"{recipe.library_path})")


def _spec_dict(spec: SupercellSpec) -> dict:
    ch = lambda cs: [c.record() for c in cs]  # noqa: E731
    return {"wavelength_m": spec.wavelength, "period_m": spec.period, "n_cells": spec.n_cells,
            "supercell": spec.supercell, "circular_aperture": spec.circular_aperture,
            "aperture_wkt": spec.aperture_wkt,
            "channels_x": ch(spec.channels_x), "channels_y": ch(spec.channels_y)}


def _spec_from_dict(d: dict) -> SupercellSpec:
    ch = lambda cs: tuple(LensChannel.from_record(c) for c in cs)  # noqa: E731
    return SupercellSpec(d["wavelength_m"], d["period_m"], int(d["n_cells"]), int(d["supercell"]),
                         ch(d["channels_x"]), ch(d["channels_y"]), bool(d["circular_aperture"]),
                         d.get("aperture_wkt"))


def select_recipe_atoms(recipe: DesignRecipe, lib: UnitCellLibrary) -> AtomTable:
    """The recipe's atom table: the library's cells above the threshold, binned on the phase torus."""
    n_sup = lib.meta["stack"]["n_superstrate"]
    n_sub = lib.meta["stack"]["n_substrate"]
    try:
        return select_atoms(lib.t_x, lib.t_y, lib.T0, lib.wx, lib.wy, recipe.threshold, recipe.bins,
                            tn_scale=float(np.sqrt(n_sup / n_sub)))
    except ValueError as exc:
        raise ConfigError("discretizer.transmission_threshold", str(exc)) from None


def design_meta(recipe: DesignRecipe, lib: UnitCellLibrary, atoms: AtomTable, offsets, empty, metrics,
                out: Path) -> dict:
    """The design file's metadata (``metrics`` may be filled in later, by a streamed build)."""
    return {
        "format": DESIGN_FORMAT,
        "version": __version__,
        "name": recipe.name,
        "recipe": recipe.raw,
        "spec": _spec_dict(recipe.spec),
        # the path is relative to the design's folder; the sha256 finds the library if it moved
        "library": {"path": relative_to_product(recipe.library_path, out), "sha256": lib.identity,
                    "n_harmonics": lib.meta["solver"]["n_harmonics"]},
        "discretizer": {"threshold": recipe.threshold, "bins": recipe.bins, "metric": recipe.metric.value,
                        "tn_scale": atoms.tn_scale},
        "phase_offsets_rad": list(offsets),
        "empty_index": empty,
        "metrics": metrics,
        "conventions": {
            "index_map": "[iy, ix]; cell (ix, iy) at x = (ix - (n-1)/2) p, y = (iy - (n-1)/2) p",
            "channel": "k = 1 + (ix mod m) + m (iy mod m); PSF of channel k at (offset_x_k, offset_y_k)",
            "empty": "max value of the index dtype = no pillar",
            "phase": "exp(+i phi), exp(-i omega t); converging lens phi <= 0 away from its axis",
        },
    }


def run_design(recipe: DesignRecipe, out_dir: Path | None = None,
               progress: Callable[[int, int], None] | None = None) -> tuple[Design, Path]:
    """Validate against the library, select atoms, discretize, write the design."""
    out = Path(out_dir or recipe.default_output())
    check_memory("this design", design_memory_bytes(recipe.spec.n_cells),
                 "lower design.aperture_mm or raise design.period_um, or use the tiled path "
                 "(metadesign layout tiled RECIPE)")
    lib = load_library(recipe.library_path)
    check_library(recipe, lib)
    atoms = select_recipe_atoms(recipe, lib)
    res: DesignResult = discretize_design(recipe.spec, atoms, recipe.metric, recipe.optimise_offsets,
                                          recipe.tile_rows, progress)
    meta = design_meta(recipe, lib, atoms, res.offsets, res.empty, res.metrics, out)
    design = Design(recipe.spec, atoms, res.index_map, res.offsets, res.metrics, meta, res.empty, res.seconds)
    save_design(out, design)
    return design, out


def design_memory_bytes(n_cells: int) -> float:
    """Planned peak memory of ``run_design`` (measured: 0.67 GB at 7142^2 cells = 13 B/cell, plus the
    library tables)."""
    return 16.0 * n_cells**2 + 0.4e9


def design_library(d: "Design", path: str | Path | None = None):
    """The unit-cell library of a loaded design (``path`` overrides; else found by its sha256)."""
    lib_meta = d.meta.get("library", {})
    if path is not None:
        return load_library(path)
    base = Path(d.meta.get("_file", ".")).parent
    return load_library(find_library(lib_meta.get("sha256"), lib_meta.get("path"), base))


def save_design(out_dir: Path, d: Design) -> Path:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    a = d.atoms
    write_npz(out_dir / "design.npz", {
        "index_map": d.index_map, "atom_wx_m": a.wx, "atom_wy_m": a.wy, "atom_t": a.t, "atom_T0": a.T0,
        "atom_lib_index": a.lib_index, "meta": json_array({k: v for k, v in d.meta.items() if k != "_file"}),
    })
    atomic_write_text(out_dir / "metrics.json", json.dumps(d.metrics, indent=2, sort_keys=True))
    return out_dir / "design.npz"


def design_file(path: str | Path) -> Path:
    """The file a design argument names: ``DESIGN/design.npz`` for a design folder, else the path itself."""
    p = Path(path)
    return p / "design.npz" if p.is_dir() else p


#: the atom table's arrays: (kind of dtype, trailing shape); each has one row per atom
_ATOM_ARRAYS = {"atom_wx_m": ("f", ()), "atom_wy_m": ("f", ()), "atom_t": ("c", (2,)), "atom_T0": ("f", (2,)),
                "atom_lib_index": ("iu", (2,))}


def _check_atoms(path: Path, z: dict) -> int:
    """The number of atoms of a design file whose atom arrays agree in length, shape and kind, are finite and
    have positive widths (one line naming the array otherwise)."""
    n = np.shape(z["atom_wx_m"])[0] if np.ndim(z["atom_wx_m"]) == 1 else -1
    if n < 1:
        raise InputError(f"{path}: atom_wx_m has shape {np.shape(z['atom_wx_m'])}, expected (n_atoms,) with n_atoms >= 1")
    for name, (kinds, tail) in _ATOM_ARRAYS.items():
        a = np.asarray(z[name])
        if a.shape != (n, *tail) or a.dtype.kind not in kinds:
            want = {"f": "real", "c": "complex", "iu": "integer"}[kinds]
            raise InputError(f"{path}: {name} has shape {a.shape} {a.dtype}, expected {(n, *tail)} {want} "
                             "(one row per atom)")
        if a.dtype.kind in "fc" and not np.isfinite(a).all():
            raise InputError(f"{path}: {name} holds NaN or infinite values")
    if (np.asarray(z["atom_wx_m"]) <= 0).any() or (np.asarray(z["atom_wy_m"]) <= 0).any():
        raise InputError(f"{path}: atom widths must be > 0")
    return n


def load_design(path: str | Path) -> Design:
    path = design_file(path)
    z, meta = read_product(path, "design file",
                           ("index_map", "atom_wx_m", "atom_wy_m", "atom_t", "atom_T0", "atom_lib_index"), DESIGN_FORMAT)
    spec = _spec_from_dict(meta["spec"])
    im = z["index_map"]
    n = _check_atoms(path, z)
    dtype, empty = empty_index(n, spec.bounded)
    if im.shape != (spec.n_cells, spec.n_cells) or im.dtype != dtype or meta.get("empty_index") != empty:
        raise InputError(f"{path}: index_map has shape {im.shape} {im.dtype}, expected "
                         f"{(spec.n_cells, spec.n_cells)} {np.dtype(dtype)}")
    used = im[im != empty] if empty is not None else im
    if int(used.max(initial=0)) >= n:
        raise InputError(f"{path}: index_map refers to atoms beyond the table ({n} atoms)")
    m = meta["metrics"]
    atoms = AtomTable(z["atom_wx_m"], z["atom_wy_m"], z["atom_t"], z["atom_T0"], z["atom_lib_index"],
                      int(m.get("n_empty_bins", 0)), int(m.get("n_kept_library_cells", 0)),
                      float(meta["discretizer"]["tn_scale"]))
    meta["_file"] = str(path)  # where it was read from (not stored): finds the library relative to it
    return Design(spec, atoms, im, tuple(meta["phase_offsets_rad"]), m, meta, empty)

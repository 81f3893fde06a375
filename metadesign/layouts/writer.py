"""OASIS/GDS writer with gdstk: one cell per atom, one Reference per atom
holding an explicit-offsets Repetition of all its positions.

Geometry (database unit 1 nm, user unit 1 nm):

* the layout is centred on the aperture centre: cell ``(ix, iy)`` of the
  design sits at ``x = ix p + x0``, ``y = iy p + y0`` nm with
  ``x0 = y0 = -(n - 1) p / 2`` (integer nm: checked);
* atom cell ``ATOM_###`` holds one rectangle ``wx x wy`` (widths snapped to
  the grid) centred on its origin; an odd-nm width cannot be centred on a
  1 nm grid and is placed with its centre 0.5 nm towards -x / -y (reported);
* each atom's reference is anchored on its first pillar in raster order
  (lowest y, then lowest x), the other pillars are offsets (gdstk includes
  the origin itself); raster order keeps consecutive deltas small.
"""

from __future__ import annotations

import datetime
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..config import InputError
from ..io import atomic_path, atomic_write_text
from ..library.locate import relative_to_product
from ..validation import check_number

__all__ = ["LayoutOptions", "write_layout", "snap_widths", "layout_geometry", "outline_polygons", "provenance_of",
           "TOP_CELL", "PROPERTY"]

TOP_CELL = "METASURFACE"
PROPERTY = "metadesign"


@dataclass(frozen=True)
class LayoutOptions:
    layer: int = 1
    datatype: int = 0
    grid_nm: int = 1  # width snapping grid
    outline_layer: int | None = 10  # aperture outline (None: off)
    label_layer: int | None = 11  # provenance text + optional label (None: off)
    label: str | None = None
    compression_level: int = 1

    def __post_init__(self) -> None:
        for name in ("layer", "datatype"):
            v = getattr(self, name)
            if not 0 <= v <= 65535:
                raise InputError(f"--{name}: expected an integer in [0, 65535], got {v}")
        if not 1 <= self.grid_nm <= 100:
            raise InputError(f"--grid-nm: expected an integer in [1, 100], got {self.grid_nm}")
        pillar = (self.layer, self.datatype)
        for name in ("outline_layer", "label_layer"):
            v = getattr(self, name)
            if v is not None and (not 0 <= v <= 65535 or (v, self.datatype) == pillar):
                raise InputError(f"--{name.replace('_', '-')}: must be in [0, 65535] and off the pillar layer "
                                 f"{self.layer}/{self.datatype}, got {v}")


def snap_widths(w_m: np.ndarray, grid_nm: int) -> tuple[np.ndarray, float]:
    """Widths in integer nm on the grid, and the largest snapping error (nm)."""
    w_nm = np.asarray(w_m) * 1e9
    snapped = (np.round(w_nm / grid_nm) * grid_nm).astype(np.int64)
    return snapped, float(np.abs(snapped - w_nm).max()) if w_nm.size else 0.0


def layout_geometry(n_cells: int, period_m: float) -> tuple[int, int]:
    """(period_nm, x0_nm): integer nm lattice, centred on the aperture."""
    p = period_m * 1e9
    p_nm = int(round(p))
    if abs(p - p_nm) > 1e-6:
        raise InputError(f"period {p:g} nm is not an integer number of nm (database unit 1 nm)")
    if (p_nm * (n_cells - 1)) % 2:
        raise InputError(f"period {p_nm} nm x {n_cells} cells cannot be centred on the 1 nm grid")
    return p_nm, -(p_nm * (n_cells - 1)) // 2


def _rect(w: int, h: int):
    import gdstk

    x0, y0 = -(w // 2) - (w % 2), -(h // 2) - (h % 2)
    return gdstk.rectangle((x0, y0), (x0 + w, y0 + h))


def build_gdstk_library(design, opts: LayoutOptions, provenance: dict):
    """The gdstk Library for ``design`` (a :class:`~metadesign.design.store.Design`)."""
    import gdstk

    spec, atoms, im = design.spec, design.atoms, design.index_map
    n = spec.n_cells
    p_nm, x0 = layout_geometry(n, spec.period)
    wx, ex = snap_widths(atoms.wx, opts.grid_nm)
    wy, ey = snap_widths(atoms.wy, opts.grid_nm)
    lib = gdstk.Library(name="METADESIGN", unit=1e-9, precision=1e-9)
    flat = im.ravel()
    order = np.argsort(flat, kind="stable")  # raster order within each atom (radix sort for uint8/16)
    counts = np.bincount(flat, minlength=len(atoms) + 1)
    # only the atoms the layout places: a mask shop expects one top cell, and an unreferenced cell is one
    # (the whole atom table stays in the provenance, so a reader still knows every atom's rectangle)
    cells = []
    for a in range(len(atoms)):
        c = None
        if counts[a]:
            c = lib.new_cell(f"ATOM_{a:03d}")
            r = _rect(int(wx[a]), int(wy[a]))
            r.layer, r.datatype = opts.layer, opts.datatype
            c.add(r)
        cells.append(c)
    top = lib.new_cell(TOP_CELL)
    start = 0
    for a in range(len(atoms)):
        cnt = int(counts[a])
        idx = order[start:start + cnt]
        start += cnt
        if cnt == 0:
            continue
        iy, ix = np.divmod(idx, n)
        ox, oy = int(ix[0]) * p_nm + x0, int(iy[0]) * p_nm + x0  # square lattice: same origin on both axes
        ref = gdstk.Reference(cells[a], (ox, oy))
        if cnt > 1:
            d = (ix[1:] - ix[0]).astype(np.float64) * p_nm + 1j * ((iy[1:] - iy[0]).astype(np.float64) * p_nm)
            ref.repetition = gdstk.Repetition(offsets=d.tolist())
        top.add(ref)
    if opts.outline_layer is not None:
        top.add(*outline_polygons(spec, p_nm, opts))
    if opts.label_layer is not None:
        half = (n * p_nm) // 2
        text = opts.label or design.meta.get("name", "metadesign")
        top.add(gdstk.Label(text, (-half, -half - 5000), layer=opts.label_layer, texttype=0))
        top.add(gdstk.Label(json.dumps(provenance, sort_keys=True), (-half, -half - 10000),
                            layer=opts.label_layer, texttype=1))
    top.set_property(PROPERTY, json.dumps(provenance, sort_keys=True))
    snapping = {"grid_nm": opts.grid_nm, "max_error_nm": max(ex, ey),
                "odd_width_atoms": int(np.sum((wx % 2) | (wy % 2)))}
    return lib, snapping


def outline_polygons(spec, p_nm: int, opts: LayoutOptions) -> list:
    """The aperture outline (gdstk polygons, nm) on ``opts.outline_layer``: a 1 um frame around the
    array minus the clear aperture (circle, polygon, or the full square)."""
    import gdstk

    half = (spec.n_cells * p_nm) // 2
    frame = gdstk.rectangle((-half - 1000, -half - 1000), (half + 1000, half + 1000))
    if spec.aperture_wkt:
        hole = _wkt_polygons_nm(spec.aperture_wkt)
    elif spec.circular_aperture:
        hole = gdstk.ellipse((0, 0), half, tolerance=10)
    else:
        hole = gdstk.rectangle((-half, -half), (half, half))
    return gdstk.boolean(frame, hole, "not", layer=opts.outline_layer, datatype=opts.datatype)


def _wkt_polygons_nm(wkt: str) -> list:
    """gdstk polygons (nm) of a WKT (multi)polygon in metres, holes included."""
    import gdstk
    import shapely

    g = shapely.from_wkt(wkt)
    polys = []
    for part in getattr(g, "geoms", [g]):
        shell = gdstk.Polygon((np.asarray(part.exterior.coords) * 1e9).tolist())
        holes = [gdstk.Polygon((np.asarray(h.coords) * 1e9).tolist()) for h in part.interiors]
        polys += gdstk.boolean(shell, holes, "not") if holes else [shell]
    return polys


def channel_table(spec) -> list[dict]:
    """The lenses as data: one row per (polarisation, k = 1..4)."""
    return [{"pol": pol, "k": k, **c.record()}
            for pol, chans in (("x", spec.channels_x), ("y", spec.channels_y)) for k, c in enumerate(chans, 1)]


def provenance_of(design, opts: LayoutOptions) -> dict:
    p_nm, x0 = layout_geometry(design.spec.n_cells, design.spec.period)
    return {
        "tool": "metadesign", "version": __version__, "design": design.meta.get("name"),
        "wavelength_m": design.spec.wavelength, "supercell": design.spec.supercell,
        "channels": channel_table(design.spec), "clear_aperture": design.spec.aperture_record(),
        "recipe": design.meta.get("recipe"), "library_sha256": design.meta.get("library", {}).get("sha256"),
        "n_cells": design.spec.n_cells, "period_nm": p_nm, "origin_nm": [x0, x0],
        "n_atoms": len(design.atoms), "layer": [opts.layer, opts.datatype],
        "empty_index": design.empty,
        "atom_widths_nm": [[int(a), int(b)] for a, b in zip(snap_widths(design.atoms.wx, opts.grid_nm)[0],
                                                              snap_widths(design.atoms.wy, opts.grid_nm)[0])],
    }


def layout_library(design, opts: LayoutOptions = LayoutOptions(), unit: float = 1e-9):
    """The ``gdstk.Library`` :func:`write_layout` would write for ``design``, in memory, for users who place
    the metasurface into a larger mask: one top cell (``lib.top_level()[0]``) referencing one cell per
    placed atom, the provenance as the top cell's properties.  Coordinates are in ``unit`` (metres per
    user unit: 1e-9, the layout's nm, by default; give the host library's, e.g. 1e-6 for a gdsfactory
    or gdstk library in um): gdstk cells carry no unit of their own, so a cell placed into a host of
    another unit would be scaled by the ratio (a 1 nm cell in a 1 um host: 1000x too large)."""
    import gdstk

    check_number("unit", unit, 1e-12, 1.0)
    lib = build_gdstk_library(design, opts, provenance_of(design, opts))[0]
    if unit == lib.unit:
        return lib
    f = lib.unit / unit
    for cell in lib.cells:
        for poly in cell.polygons:
            poly.scale(f)
        for ref in cell.references:
            ref.origin = (ref.origin[0] * f, ref.origin[1] * f)
            if ref.repetition is not None and ref.repetition.offsets is not None:
                ref.repetition = gdstk.Repetition(offsets=(np.asarray(ref.repetition.offsets) * f).tolist())
        for lab in cell.labels:
            lab.origin = (lab.origin[0] * f, lab.origin[1] * f)
    lib.unit = unit
    lib.precision = min(lib.precision, unit)
    return lib


def write_layout(design, out: Path, fmt: str = "oas", opts: LayoutOptions = LayoutOptions()) -> dict:
    """Write ``out`` (``.oas`` or ``.gds``) atomically plus ``out.json`` side-car."""
    out = Path(out)
    t0 = time.perf_counter()
    prov = provenance_of(design, opts)
    lib_rec = design.meta.get("library", {}).get("path")
    if lib_rec and design.meta.get("_file"):
        prov["library_path"] = relative_to_product(Path(design.meta["_file"]).parent / lib_rec, out.parent)
    lib, snapping = build_gdstk_library(design, opts, prov)
    t_build = time.perf_counter() - t0
    with atomic_path(out) as tmp:
        if fmt == "oas":
            lib.write_oas(str(tmp), compression_level=opts.compression_level, validation="crc32")
        elif fmt == "gds":
            # fixed timestamp: same design, same bytes (GDSII otherwise stores the write time)
            lib.write_gds(str(tmp), timestamp=datetime.datetime(2000, 1, 1))
        else:
            raise InputError(f"--format: expected oas, gds or both, got {fmt!r}")
    seconds = time.perf_counter() - t0
    n_pillars = int(np.count_nonzero(design.index_map != design.empty)) if design.empty is not None \
        else int(design.index_map.size)
    report = {
        "file": str(out), "format": fmt, "bytes": out.stat().st_size, "pillars": n_pillars,
        "atoms": len(design.atoms), "snapping": snapping, "seconds": seconds, "build_seconds": t_build,
        "options": asdict(opts), "provenance": prov,
    }
    side = {k: v for k, v in report.items() if k not in ("seconds", "build_seconds")}
    atomic_write_text(out.with_suffix(out.suffix + ".json"), json.dumps(side, indent=2, sort_keys=True))
    return report

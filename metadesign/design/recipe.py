"""Design recipe (``layouts/*.toml``) -> validated :class:`DesignRecipe`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import ConfigError, Param, Section, load_toml, parse
from .discretize import Metric
from .phase import LensChannel, SupercellSpec

__all__ = ["DesignRecipe", "load_design_recipe", "design_recipe_from_dict", "SECTIONS"]

_PAPER_OFFSETS = [[-240.0, -192.0], [240.0, -192.0], [-240.0, 192.0], [240.0, 192.0]]


def _pol_section(name: str, focals: list[float]) -> Section:
    return Section(
        name,
        (
            Param("focal_lengths_mm", list, focals, lo=0, open_lo=True, hi=1e5),
            Param("offsets_um", list, _PAPER_OFFSETS, pairs=True, lo=-1e6, hi=1e6),
            # a diversity beyond each lens's defocus (co-design, issue #33): Noll indices and, per lens, a
            # row of coefficients (rad) over the aperture's inscribed disk
            Param("zernike_noll", list, None, lo=2, hi=66),
            Param("zernike_rad", list, None, rows=True, lo=-1000, hi=1000),
        ),
        optional=True,
    )


SECTIONS = (
    Section(
        "design",
        (
            Param("library", str, "../library/paper.npz"),
            Param("wavelength_nm", float, lo=0, open_lo=True, hi=1e5),
            Param("period_um", float, lo=0, open_lo=True, hi=100),
            Param("aperture_mm", float, lo=0, open_lo=True, hi=300),
            Param("clear_aperture", str, "square", choices=["square", "circle", "polygon"]),
            # clear_aperture = "polygon": vertices (um, aperture-centred) or a WKT / GeoJSON file (um)
            Param("aperture_polygon_um", list, None, pairs=True, lo=-1.5e5, hi=1.5e5),
            Param("aperture_file", str, None),
            Param("supercell", int, 2, lo=1, hi=8),
        ),
    ),
    _pol_section("x_pol", [48.8, 49.2, 49.6, 50.0]),
    _pol_section("y_pol", [50.4, 50.8, 51.2, 51.6]),
    Section(
        "discretizer",
        (
            Param("transmission_threshold", float, 0.7, lo=0, hi=1, open_hi=False),
            Param("bins", int, 16, lo=2, hi=64),
            Param("metric", str, "phase", choices=[m.value for m in Metric]),
            Param("optimise_offsets", bool, True),
            Param("tile_rows", int, 256, lo=2, hi=100000),
        ),
        optional=True,
    ),
)


@dataclass(frozen=True)
class DesignRecipe:
    name: str
    source: Path | None
    library_path: Path
    spec: SupercellSpec
    threshold: float
    bins: int
    metric: Metric
    optimise_offsets: bool
    tile_rows: int
    raw: dict  # the recipe as written (recipe units), embedded in outputs

    def default_output(self) -> Path:
        base = self.source.parent if self.source else Path.cwd()
        return base / self.name


def design_recipe_from_dict(data: dict, name: str = "design", source: Path | None = None) -> DesignRecipe:
    v = parse(data, SECTIONS, str(source) if source else "recipe")
    d, dz = v["design"], v["discretizer"]
    m = d["supercell"]
    if m != 2:
        raise ConfigError("design.supercell", f"expected 2 (four lenses per polarisation, one per sensor quadrant: "
                                              f"the layout, PSF and reconstruction stages need it), got {m}")
    n_cells = int(np.floor(d["aperture_mm"] / d["period_um"] + 1e-9))
    n_cells -= n_cells % m  # whole supercells
    if n_cells < m:
        raise ConfigError("design.aperture_mm",
                          f"{d['aperture_mm'] * 1e3:g} mm is smaller than one {m}x{m} supercell "
                          f"({m * d['period_um'] * 1e3:g} mm)")
    chans = {}
    for pol in ("x_pol", "y_pol"):
        f, o = v[pol]["focal_lengths_mm"], v[pol]["offsets_um"]
        for key, seq in (("focal_lengths_mm", f), ("offsets_um", o)):
            if len(seq) != m * m:
                raise ConfigError(f"{pol}.{key}", f"needs {m * m} entries for a {m}x{m} supercell, got {len(seq)}")
        zs = _zernike_rows(pol, v[pol]["zernike_noll"], v[pol]["zernike_rad"], m * m)
        chans[pol] = tuple(LensChannel(fk, ox, oy, z, 0.5 * n_cells * d["period_um"] if z else 0.0)
                           for fk, (ox, oy), z in zip(f, o, zs))
    wkt = _polygon_wkt(d, source, n_cells * d["period_um"])
    spec = SupercellSpec(
        wavelength=d["wavelength_nm"], period=d["period_um"], n_cells=n_cells, supercell=m,
        channels_x=chans["x_pol"], channels_y=chans["y_pol"], circular_aperture=d["clear_aperture"] == "circle",
        aperture_wkt=wkt,
    )
    lib = Path(d["library"])
    if not lib.is_absolute():
        lib = (source.parent if source else Path.cwd()) / lib
    return DesignRecipe(
        name=name, source=source, library_path=lib, spec=spec, threshold=dz["transmission_threshold"],
        bins=dz["bins"], metric=Metric(dz["metric"]), optimise_offsets=dz["optimise_offsets"],
        tile_rows=dz["tile_rows"], raw=data,
    )


def _zernike_rows(pol: str, noll, rows, n_lenses: int) -> list[tuple]:
    """Each lens's ((noll, rad), ...) from a section's zernike_noll / zernike_rad (both or neither)."""
    if noll is None and rows is None:
        return [()] * n_lenses
    if noll is None or rows is None:
        raise ConfigError(f"{pol}.zernike_noll", "zernike_noll and zernike_rad go together (give both or neither)")
    if any(float(j) != int(j) for j in noll) or len(set(noll)) != len(noll):
        raise ConfigError(f"{pol}.zernike_noll", f"expected distinct Noll indices (integers 2..66), got {list(noll)}")
    if len(rows) != n_lenses or any(len(r) != len(noll) for r in rows):
        raise ConfigError(f"{pol}.zernike_rad", f"expected {n_lenses} rows (one per lens) of {len(noll)} "
                                                "coefficients (one per zernike_noll)")
    return [tuple((int(j), float(a)) for j, a in zip(noll, r) if a != 0.0) for r in rows]


def _polygon_wkt(d: dict, source: Path | None, side: float) -> str | None:
    """The polygon clear aperture as WKT in metres (validated), or None."""
    import shapely

    kind, verts, file = d["clear_aperture"], d["aperture_polygon_um"], d["aperture_file"]
    if kind != "polygon":
        for key, v in (("aperture_polygon_um", verts), ("aperture_file", file)):
            if v is not None:
                raise ConfigError(f"design.{key}", f"only with clear_aperture = \"polygon\" (got {kind!r})")
        return None
    if (verts is None) == (file is None):
        raise ConfigError("design.clear_aperture", "\"polygon\" needs exactly one of aperture_polygon_um "
                                                   "(vertices in um) or aperture_file (WKT or GeoJSON, um)")
    where = "design.aperture_polygon_um" if verts is not None else "design.aperture_file"
    if verts is not None:
        if len(verts) < 3:
            raise ConfigError(where, f"expected >= 3 vertices, got {len(verts)}")
        geom = shapely.Polygon(verts)  # already in metres
    else:
        path = Path(file)
        if not path.is_absolute():
            path = (source.parent if source else Path.cwd()) / path
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(where, f"cannot read {path} ({exc.__class__.__name__})") from None
        try:
            if path.suffix.lower() in (".json", ".geojson"):
                import json

                obj = json.loads(text)
                if obj.get("type") == "FeatureCollection" and len(obj.get("features", ())) == 1:
                    obj = obj["features"][0]
                if obj.get("type") == "Feature":
                    obj = obj["geometry"]
                geom = shapely.from_geojson(json.dumps(obj))
            else:
                geom = shapely.from_wkt(text.strip())
        except (ValueError, TypeError, AttributeError, shapely.errors.GEOSException) as exc:
            raise ConfigError(where, f"{path} is not a WKT / GeoJSON polygon ({str(exc).splitlines()[0]})") \
                from None
        if geom.geom_type not in ("Polygon", "MultiPolygon"):
            raise ConfigError(where, f"{path}: expected a Polygon or MultiPolygon, got {geom.geom_type}")
        geom = shapely.transform(geom, lambda c: c * 1e-6)  # um -> m, once, here
    if not geom.is_valid or geom.is_empty or geom.area <= 0:
        raise ConfigError(where, "the polygon is empty or invalid (self-intersecting?)")
    square = shapely.box(-side / 2, -side / 2, side / 2, side / 2)
    if not geom.intersects(square) or geom.intersection(square).area < 1e-6 * side * side:
        raise ConfigError(where, f"the polygon does not overlap the {side * 1e3:g} mm aperture square")
    return shapely.to_wkt(geom, rounding_precision=-1, trim=True)


def load_design_recipe(path: str | Path) -> DesignRecipe:
    path = Path(path)
    return design_recipe_from_dict(load_toml(path), name=path.stem, source=path)

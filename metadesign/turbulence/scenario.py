"""The turbulence scenario recipe (TOML: [path], [grid], [receiver]; keys carry their unit) and its
loader: a :class:`~.path.Scenario` in SI units."""

from __future__ import annotations

from ..config import Param, Section, load_toml, parse
from .path import Scenario

__all__ = ["SECTIONS", "scenario_from_dict", "load_scenario"]

SECTIONS = (
    Section("path", (
        Param("wavelength_nm", float, 1550.0, lo=100, hi=20000),
        Param("length_m", float, 1000.0, lo=1, hi=1e6),
        Param("n_screens", int, 13, lo=3, hi=200),
        Param("rytov", float, 0.3, lo=0, open_lo=True, hi=5),
        Param("max_screen_rytov", float, 0.1, lo=0, open_lo=True, hi=1),
        Param("inner_scale_cm", float, 1.0, lo=0, open_lo=True, hi=100),
        Param("outer_scale_m", float, 100.0, lo=0, open_lo=True, hi=1e5),
    ), optional=True),
    Section("grid", (
        Param("n", int, 256, lo=32, hi=8192),
        Param("spacing_mm", float, 2.5, lo=0, open_lo=True, hi=1000),
        Param("absorber_order", int, 16, lo=2, hi=64),
        Param("subharmonics", bool, True),
    ), optional=True),
    Section("receiver", (
        Param("aperture_cm", float, 10.0, lo=0, open_lo=True, hi=1000),
        Param("metasurface_aperture_mm", float, 5.0, lo=0, open_lo=True, hi=1000),
        Param("roi_factor", float, 4.0, lo=1, hi=20),
    ), optional=True),
)


def scenario_from_dict(data: dict, source: str = "recipe") -> Scenario:
    v = parse(data, SECTIONS, source)
    p, g, r = v["path"], v["grid"], v["receiver"]
    return Scenario(wavelength=p["wavelength_nm"], length=p["length_m"], n_screens=p["n_screens"], rytov=p["rytov"],
                    max_screen_rytov=p["max_screen_rytov"], inner_scale=p["inner_scale_cm"],
                    outer_scale=p["outer_scale_m"], n_grid=g["n"], dx=g["spacing_mm"],
                    receiver_aperture=r["aperture_cm"], metasurface_aperture=r["metasurface_aperture_mm"],
                    roi_factor=r["roi_factor"], absorber_order=g["absorber_order"], subharmonics=g["subharmonics"])


def load_scenario(path) -> Scenario:
    return scenario_from_dict(load_toml(path), str(path))

"""The turbulence scenario recipe (TOML: [path], [grid], [receiver], optional [wind]; keys carry their
unit) and its loader: a :class:`~.path.Scenario` in SI units, and the path's :class:`~.temporal.Wind`
when the recipe has a ``[wind]`` section (:func:`wind_from_dict`, :func:`load_wind`)."""

from __future__ import annotations

from ..config import Param, Section, load_toml, parse
from .path import Scenario
from .temporal import wind_of

__all__ = ["SECTIONS", "scenario_from_dict", "load_scenario", "wind_from_dict", "load_wind"]

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
    # frozen-flow wind (m/s, deg; 0 deg blows towards +x): a speed at the source with an optional linear ramp
    # to end_speed_m_s at the receiver, or one speed (and direction) per screen; without [wind], nothing moves
    Section("wind", (
        Param("speed_m_s", float, None, lo=0, hi=200),
        Param("end_speed_m_s", float, None, lo=0, hi=200),
        Param("direction_deg", float, None, lo=-360, hi=360),
        Param("speeds_m_s", list, None, lo=0, hi=200),
        Param("directions_deg", list, None, lo=-360, hi=360),
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


def wind_from_dict(data: dict, sc: Scenario | None = None, source: str = "recipe"):
    """The recipe's :class:`~.temporal.Wind` (one velocity per screen of ``sc``, default: the recipe's own
    scenario), or None without a ``[wind]`` section."""
    if "wind" not in data:
        return None
    sc = sc or scenario_from_dict(data, source)
    return wind_of(sc, parse(data, SECTIONS, source)["wind"])


def load_wind(path, sc: Scenario | None = None):
    return wind_from_dict(load_toml(path), sc, str(path))

"""Unit-cell library recipe: TOML -> validated :class:`LibraryRecipe` (SI)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import ConfigError, Param, Section, load_toml, parse
from .rcwa import Factorization, SolverSettings, Stack, Truncation

__all__ = ["LibraryRecipe", "FabAxes", "load_recipe", "SECTIONS"]

SECTIONS = (
    Section(
        "stack",
        (
            Param("wavelength_nm", float, lo=0, open_lo=True, hi=1e5),
            Param("period_um", float, lo=0, open_lo=True, hi=100),
            Param("height_um", float, lo=0, open_lo=True, hi=100),
            Param("n_pillar", float, 3.48, lo=1, hi=10),
            Param("n_substrate", float, 1.444, lo=1, hi=10),
            Param("n_superstrate", float, 1.0, lo=1, hi=10),
        ),
    ),
    Section(
        "sweep",
        (
            Param("w_min_um", float, 0.10, lo=0, open_lo=True),
            Param("w_max_um", float, 0.50, lo=0, open_lo=True),
            Param("step_nm", float, 5.0, lo=0.1, hi=10.0),
        ),
        optional=True,
    ),
    Section(
        "solver",
        (
            Param("n_harmonics", int, 200, lo=9, hi=2000),
            Param("truncation", str, "circular", choices=[t.value for t in Truncation]),
            Param("factorization", str, "li", choices=[f.value for f in Factorization]),
            Param("use_symmetry", bool, True),
        ),
        optional=True,
    ),
    Section(
        "convergence",
        (
            Param("tolerance_rad", float, 0.02, lo=0, open_lo=True, hi=3.14),
            Param("reference_n_harmonics", int, 400, lo=9, hi=4000),
            Param(
                "check_cells_um",
                list,
                [[0.30, 0.20], [0.20, 0.45], [0.45, 0.45], [0.12, 0.35], [0.40, 0.15]],
                lo=0,
                open_lo=True,
                pairs=True,
            ),
        ),
        optional=True,
    ),
    Section(
        "fab_axes",
        (
            Param("heights_um", list, None, lo=0, open_lo=True, hi=100,
                  help="pillar heights of the sweep (must include the stack's height)"),
            Param("sidewall_deg", list, [90.0], lo=60, hi=90, help="sidewall angles (must include 90)"),
            Param("slices", int, 8, lo=1, hi=200, help="slices of a tapered pillar"),
            Param("reference_slices", int, 24, lo=2, hi=1000, help="slice count of the convergence reference"),
        ),
        optional=True,
    ),
)


@dataclass(frozen=True)
class FabAxes:
    """Optional height and sidewall-angle axes of a library (SI: m, degrees)."""

    heights: tuple[float, ...]
    sidewalls: tuple[float, ...]
    slices: int
    reference_slices: int

    def to_dict(self) -> dict:
        return {"heights_um": [h * 1e6 for h in self.heights], "sidewall_deg": list(self.sidewalls),
                "slices": self.slices, "reference_slices": self.reference_slices}


@dataclass(frozen=True)
class LibraryRecipe:
    name: str
    stack: Stack
    widths: np.ndarray  # sweep grid (m), shared by wx and wy
    settings: SolverSettings
    tolerance: float  # rad
    reference_n_harmonics: int
    check_cells: tuple[tuple[float, float], ...]  # (wx, wy) in m
    fab_axes: FabAxes | None = None  # optional height / sidewall axes (None: the 2-D library)

    def to_dict(self) -> dict:
        s = self.stack
        d = {
            "name": self.name,
            "stack": {
                "wavelength_nm": s.wavelength * 1e9,
                "period_um": s.period * 1e6,
                "height_um": s.height * 1e6,
                "n_pillar": s.n_pillar,
                "n_substrate": s.n_substrate,
                "n_superstrate": s.n_superstrate,
            },
            "sweep": {
                "w_min_um": float(self.widths[0] * 1e6),
                "w_max_um": float(self.widths[-1] * 1e6),
                "step_nm": float(np.round((self.widths[1] - self.widths[0]) * 1e9, 6))
                if len(self.widths) > 1 else 0.0,
                "n_widths": int(len(self.widths)),
            },
            "solver": {
                "n_harmonics": self.settings.n_harmonics,
                "truncation": self.settings.truncation.value,
                "factorization": self.settings.factorization.value,
                "use_symmetry": self.settings.use_symmetry,
            },
            "convergence": {
                "tolerance_rad": self.tolerance,
                "reference_n_harmonics": self.reference_n_harmonics,
                "check_cells_um": [[wx * 1e6, wy * 1e6] for wx, wy in self.check_cells],
            },
        }
        if self.fab_axes is not None:  # absent for 2-D libraries: their recipe record (and bytes) are unchanged
            d["fab_axes"] = self.fab_axes.to_dict()
        return d


def recipe_from_dict(data: dict, name: str = "recipe", source: str = "recipe") -> LibraryRecipe:
    v = parse(data, SECTIONS, source)
    st, sw, so, cv = v["stack"], v["sweep"], v["solver"], v["convergence"]
    fa = v.get("fab_axes") if "fab_axes" in data else None
    stack = Stack(
        wavelength=st["wavelength_nm"],
        period=st["period_um"],
        height=st["height_um"],
        n_pillar=st["n_pillar"],
        n_substrate=st["n_substrate"],
        n_superstrate=st["n_superstrate"],
    )
    p_um = stack.period * 1e6
    if sw["w_max_um"] >= stack.period:
        raise ConfigError("sweep.w_max_um", f"must be < the period ({p_um:g} um), got {sw['w_max_um']*1e6:g}")
    if sw["w_min_um"] >= sw["w_max_um"]:
        raise ConfigError("sweep.w_min_um", f"must be < sweep.w_max_um ({sw['w_max_um']*1e6:g} um)")
    n = int(np.floor((sw["w_max_um"] - sw["w_min_um"]) / sw["step_nm"] + 1e-6)) + 1
    if n < 2:
        raise ConfigError("sweep.step_nm", f"gives {n} width (the library needs >= 2 per axis): "
                                           "lower the step or widen [w_min_um, w_max_um]")
    if not cv["check_cells_um"]:
        raise ConfigError("convergence.check_cells_um", "expected at least one [wx, wy] pair (um)")
    # integer nanometre grid (0.1 nm resolution) so widths are exactly representable in layouts
    widths = np.round((sw["w_min_um"] + sw["step_nm"] * np.arange(n)) * 1e10) / 1e10
    for i, (wx, wy) in enumerate(cv["check_cells_um"]):
        if not (0 < wx < stack.period and 0 < wy < stack.period):
            raise ConfigError(f"convergence.check_cells_um[{i}]", f"widths must be in (0, {p_um:g}) um")
    if cv["reference_n_harmonics"] <= so["n_harmonics"]:
        raise ConfigError(
            "convergence.reference_n_harmonics",
            f"must exceed solver.n_harmonics ({so['n_harmonics']})",
        )
    settings = SolverSettings(
        n_harmonics=so["n_harmonics"],
        truncation=Truncation(so["truncation"]),
        factorization=Factorization(so["factorization"]),
        use_symmetry=so["use_symmetry"],
    )
    axes = None
    if fa is not None:
        if not fa["heights_um"]:
            raise ConfigError("fab_axes.heights_um", "missing; expected a list of pillar heights (um)")
        hs = sorted(float(h) for h in fa["heights_um"])
        if not any(abs(h - stack.height) < 1e-12 for h in hs):
            raise ConfigError("fab_axes.heights_um", f"must include the stack's height ({stack.height * 1e6:g} um)")
        angs = sorted(float(a) for a in fa["sidewall_deg"])
        if 90.0 not in angs:
            raise ConfigError("fab_axes.sidewall_deg", "must include 90 (the vertical pillar)")
        if len(set(hs)) != len(hs) or len(set(angs)) != len(angs):
            raise ConfigError("fab_axes", "heights and sidewall angles must be distinct")
        if fa["reference_slices"] <= fa["slices"]:
            raise ConfigError("fab_axes.reference_slices", f"must exceed fab_axes.slices ({fa['slices']})")
        # the widest pillar, tapered to the smallest angle at the tallest height, must stay inside the period
        grow = max(hs) / np.tan(np.deg2rad(min(angs)))
        if widths[-1] + grow >= stack.period or widths[0] - grow <= 0:
            raise ConfigError("fab_axes.sidewall_deg", f"a {min(angs):g} deg wall over {max(hs) * 1e6:g} um changes "
                              f"the width by +-{grow * 1e9:.0f} nm: the sweep's pillars leave (0, period)")
        axes = FabAxes(tuple(hs), tuple(angs), fa["slices"], fa["reference_slices"])
    return LibraryRecipe(
        name=name,
        stack=stack,
        widths=widths,
        settings=settings,
        tolerance=cv["tolerance_rad"],
        reference_n_harmonics=cv["reference_n_harmonics"],
        check_cells=tuple(cv["check_cells_um"]),
        fab_axes=axes,
    )


def load_recipe(path: str | Path) -> LibraryRecipe:
    path = Path(path)
    return recipe_from_dict(load_toml(path), name=path.stem, source=str(path))

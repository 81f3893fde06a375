"""The loop map (issue #50, section 4; ``metadesign loop-map RECIPE``): the closed loop of every method of a
loop recipe over a grid of loop rate (or reconstruction latency) x Greenwood frequency x Rytov number, and
the region of the grid where each sensor keeps its loop good enough.

The recipe is a loop recipe (:mod:`metadesign.studies.loop_recipe`) and a ``[map]`` section:

.. code-block:: toml

    [map]
    rates_hz = [1000, 2000, 4000]      # the rate axis (or latency_ms: a latency axis at [loop] rate_hz)
    greenwood_hz = [50, 100, 200]      # target plane-wave Greenwood frequencies (the wind scaled to each)
    rytov = [0.3, 0.5]                 # replaces [loop] rytov
    steps = 200                        # frames per run (default: [loop] steps)
    # latency_ms = [0, 0.25, 0.5, 1]   # instead of rates_hz: the declared latency of latency_methods
    # latency_methods = ["realtime"]   # the methods the latency axis applies to (default: the metasurface's)
    scan_latency_ms = [0, 0.25, 0.5, 1, 2]  # the verdict's latency scan (default: these, or the latency axis)
    verdict_rytov = 0.5                # the verdict's point (the issue's: Rytov 0.5, f_G 100 Hz, 2 kHz)
    verdict_greenwood_hz = 100.0
    verdict_rate_hz = 2000.0

**The wind of a point.**  The Greenwood frequency scales linearly with the wind speed
(``f_G = 2.31 lambda^(-6/5) [sum_i Cn2_i dz_i |v_i|^(5/3)]^(3/5)``), so the recipe's ``[wind]`` (speeds and
directions per screen, any of its forms) is multiplied by ``f_G / f_G(recipe's wind)`` at the point's Rytov
number: the plane-wave f_G (:func:`metadesign.turbulence.temporal.greenwood_frequency`, ``w_i = 1``, the loop
study's f_G) equals the target; the spherical-wave value is reported beside it.

**The runs.**  Each grid point is a loop study (the same device, mirror, sensors and seeds) at that rate,
wind and Rytov number; each run (point x method x seed) is one task of one task set
(:meth:`metadesign.execution.Execution.run`, on ``-j`` local workers or a Dask scheduler), kept in
``OUT.partial`` as it finishes: a killed map resumes, and ``map.json``, computed from the tasks' series in a
fixed order, has the same bytes on any worker count.

**The gain.**  ``[loop] gain`` a number: every closed loop at every point runs at it.  ``"optimise"``: each
run of a closed loop (point x method, and each latency of a latency axis or of the verdict's scan) runs at
its own gain, chosen by the loop study's search (:mod:`metadesign.studies.loop_study`) at that point: the
mean NPiB of ``gain_steps`` frames of the first realisation at each gain of
:data:`~metadesign.studies.loop_study.GAIN_GRID`, then at
:data:`~metadesign.studies.loop_study.GAIN_REFINE` around the grid's best, the best of all the trials
winning (the lowest gain on a tie).  The trials are tasks of the same folder (resumable, the same bytes on
any worker count); ``map.json`` records each run's gain (``points[].methods[m].gain``) and every search
(``gain.searches``), and the figure writes the chosen gains in each cell.  A table (``gain = { realtime =
0.4, ideal = "optimise", ... }``, naming every closed loop): each loop at its given gain at every point, the
ones marked ``"optimise"`` searched per point (``gain.given`` records the others).

**The Shack-Hartmann** (``[loop] sh_lenslets``): a count is the same at every point; ``"auto"`` is resolved
at each Rytov number of the map (:func:`~metadesign.studies.loop_study.sh_lenslets_for`: ``ceil(D / r0)`` at
that Rytov number's r0), a sensor built per count, its latency measured per count unless declared;
each point records its count and why (``points[].shack_hartmann``).  The latencies (declared in
``[loop] latency_ms``, else measured once on this machine) are the loop study's; on a latency axis the
``latency_methods`` take the axis's value instead.  A run a point shares with another (the ideal loop of the
verdict's scan) is computed once.

**The region** of a method: the points where its mean NPiB is at least :data:`REGION_VS_IDEAL` of the
ideal-phase loop's at the same point and its fade probability (NPiB more than ``[loop] threshold_db`` under
its own mean, as the loop study counts fades) at most :data:`REGION_FADE_PROBABILITY`
(:func:`in_region`).

**The verdict** at (``verdict_rytov``, ``verdict_greenwood_hz``, ``verdict_rate_hz``; a point added to the
runs when it is not on the grid), with every latency as declared or measured: the best metasurface loop's
mean NPiB against the ideal-phase loop's (goal :data:`GOAL_VS_IDEAL`) and the Shack-Hartmann loop's (goal
:data:`GOAL_VS_SHACK_HARTMANN`), and which latency would get it there: every metasurface method rerun at
``scan_latency_ms`` (declared), the largest scanned latency up to which it keeps each goal
(:func:`latency_reaching`)."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Param, Section, load_toml, parse
from ..execution import SERIAL, Execution, scratch_path
from ..io import atomic_write_text
from ..plotting import pyplot, save_figure
from ..reconstruction.losses import PiB
from ..tasks import TaskFolder, content_key, file_key
from ..turbulence.path import check_sampling, solve_path
from ..turbulence.scenario import load_scenario, wind_from_dict
from ..turbulence.temporal import greenwood_frequency, temporal_summary
from ..validation import ConfigError
from .loop import ORACLES, LoopTiming
from .loop_recipe import AUTO, OPTIMISE, LoopRecipe, loop_recipe_of
from .loop_recipe import METASURFACE as LOOP_METASURFACE
from .loop_study import (GAIN_GRID, GAIN_REFINE, LABELS, LoopContext, build_loop, _latency, gain_search,
                         _measure_latencies, _pooled_fades, _sensors, sh_lenslets_for)

__all__ = ["MapRecipe", "load_map_recipe", "run_loop_map", "in_region", "regions", "latency_reaching",
           "map_verdict", "scaled_wind", "MAP_SECTION", "METASURFACE", "REGION_VS_IDEAL",
           "REGION_FADE_PROBABILITY", "GOAL_VS_IDEAL", "GOAL_VS_SHACK_HARTMANN", "DEFAULT_SCAN_MS", "LETTERS"]

#: the metasurface sensor's loops a map runs (the best of them is the verdict's): the loop study's, less the
#: ones whose cost depends on a budget or a warm start
METASURFACE = tuple(m for m in LOOP_METASURFACE if m not in ("retrieval", "refine_warm"))
#: the region: mean NPiB at least this fraction of the ideal-phase loop's ...
REGION_VS_IDEAL = 0.8
#: ... and a fade probability at most this
REGION_FADE_PROBABILITY = 1e-2
#: the issue's goal at the verdict's point: >= 0.8 of the ideal-phase loop's mean NPiB, >= 2x the Shack-Hartmann's
GOAL_VS_IDEAL = 0.8
GOAL_VS_SHACK_HARTMANN = 2.0
#: the verdict's latency scan (ms) of a map on a rate axis that names none
DEFAULT_SCAN_MS = (0.0, 0.25, 0.5, 1.0, 2.0)
#: one letter per method (the text summary's region tables, the figure's gains)
LETTERS = {"ideal": "I", "shack_hartmann": "S", "realtime": "R", "linear": "L", "unet": "U", "refine": "F",
           "fitted": "D", "conjugate": "C", "open": "O", "realtime_tt": "T", "realtime_peak": "P",
           "retrieval": "B", "refine_warm": "W"}
#: the wind keys the map scales (m/s); directions stay
_SPEEDS = ("speed_m_s", "end_speed_m_s", "speeds_m_s")

MAP_SECTION = Section("map", (
    Param("rates_hz", list, None, lo=1, hi=1e6, help="the rate axis (loop rates)"),
    Param("latency_ms", list, None, lo=0, hi=1e5,
          help="a latency axis instead (at [loop] rate_hz): the declared latency of latency_methods"),
    Param("greenwood_hz", list, lo=0, open_lo=True, hi=1e5, help="target plane-wave Greenwood frequencies"),
    Param("rytov", list, lo=0, open_lo=True, hi=5, help="Rytov numbers (replace [loop] rytov)"),
    Param("steps", int, None, lo=2, hi=10_000_000, help="frames per run (default: [loop] steps)"),
    Param("scan_latency_ms", list, None, lo=0, hi=1e5, help="the verdict's latency scan of the metasurface loops"),
    Param("verdict_rytov", float, 0.5, lo=0, open_lo=True, hi=5),
    Param("verdict_greenwood_hz", float, 100.0, lo=0, open_lo=True, hi=1e5),
    Param("verdict_rate_hz", float, 2000.0, lo=1, hi=1e6),
))


@dataclass(frozen=True)
class MapRecipe:
    """A loop map: the loop recipe (its ``loop.steps`` the map's) and the grid.  ``axis``: ``"rate_hz"`` or
    ``"latency_ms"``; ``scenes[(rytov, f_G)]``: the scaled wind (recipe units) and its temporal summary."""

    name: str
    source: Path
    loop: LoopRecipe
    axis: str
    rates_hz: tuple
    latency_ms: tuple
    greenwood_hz: tuple
    rytov: tuple
    latency_methods: tuple
    scan_latency_ms: tuple
    verdict: tuple  # (rytov, f_G, rate)
    base_greenwood_hz: dict = field(default_factory=dict)  # rytov -> f_G of the recipe's own wind
    scenes: dict = field(default_factory=dict)

    @property
    def xs(self) -> tuple:
        """The values of the map's x axis (rates in Hz, or latencies in ms)."""
        return self.rates_hz if self.axis == "rate_hz" else self.latency_ms

    def cell(self, rytov: float, greenwood: float, x: float) -> tuple:
        """``(rytov, f_G, rate, latency_ms or None)`` of a grid point."""
        if self.axis == "rate_hz":
            return (rytov, greenwood, x, None)
        return (rytov, greenwood, self.loop.loop.rate_hz, x)


def _axis(v: dict, key: str) -> tuple:
    vals = v[key]
    if vals is None:
        return ()
    if not vals:
        raise ConfigError(f"map.{key}", "expected at least one value, got []")
    if len(set(vals)) != len(vals):
        raise ConfigError(f"map.{key}", f"expected distinct values, got {list(vals)}")
    return tuple(sorted(float(x) for x in vals))


def scaled_wind(wind: dict, scale: float) -> dict:
    """The recipe's ``[wind]`` (recipe units) with every speed multiplied by ``scale`` (directions kept)."""
    out = dict(wind)
    for k in _SPEEDS:
        if k in out:
            out[k] = [float(s) * scale for s in out[k]] if isinstance(out[k], list) else float(out[k]) * scale
    return out


def load_map_recipe(path: str | Path) -> MapRecipe:
    """The loop-map recipe at ``path``, validated (one line naming the field on the first problem)."""
    path = Path(path)
    raw = load_toml(path)
    m = raw.pop("map", None)
    if m is None:
        raise ConfigError("[map]", f"missing section in {path} (a loop map is a loop recipe with a [map] section)")
    if not isinstance(m, dict):
        raise ConfigError("map", "expected a table")
    m = dict(m)
    lat_methods = m.pop("latency_methods", None)
    rec = loop_recipe_of(raw, path)
    v = parse({"map": m}, (MAP_SECTION,), str(path))["map"]
    lp = rec.loop
    if "ideal" not in lp.methods:
        raise ConfigError("loop.methods", f"a map needs \"ideal\" (its regions' reference), got {list(lp.methods)}")
    rates, lats = _axis(v, "rates_hz"), _axis(v, "latency_ms")
    if rates and lats:
        raise ConfigError("map.latency_ms", "give either rates_hz (a rate axis) or latency_ms (a latency axis at "
                          "loop.rate_hz), not both")
    if not rates and not lats:
        raise ConfigError("map.rates_hz", "missing; give rates_hz (a rate axis) or latency_ms (a latency axis)")
    greenwood, rytov = _axis(v, "greenwood_hz"), _axis(v, "rytov")
    metasurface = tuple(x for x in lp.methods if x in METASURFACE)
    if lat_methods is not None:
        if not lats:
            raise ConfigError("map.latency_methods", "only with a latency axis (map.latency_ms)")
        closed = [x for x in lp.methods if x not in ORACLES]
        if (not isinstance(lat_methods, list) or not lat_methods or len(set(lat_methods)) != len(lat_methods)
                or not all(isinstance(x, str) and x in closed for x in lat_methods)):
            raise ConfigError("map.latency_methods", f"expected distinct closed-loop methods of loop.methods "
                              f"({', '.join(closed)}), got {lat_methods!r}")
        lat_methods = tuple(lat_methods)
    else:
        lat_methods = metasurface if lats else ()
    if lats and not lat_methods:
        raise ConfigError("map.latency_methods", "the latency axis applies to none of loop.methods (name some, or "
                          "add a metasurface method)")
    scan = v["scan_latency_ms"]
    scan = tuple(sorted({float(x) for x in scan})) if scan is not None else (lats or DEFAULT_SCAN_MS)
    steps = v["steps"] if v["steps"] is not None else lp.steps
    if lp.optimise_gain and lp.gain_steps > steps:
        raise ConfigError("loop.gain_steps", f"expected at most the map's steps ({steps} frames a run; "
                          f"gain = \"{OPTIMISE}\" tries each gain on the first gain_steps), got {lp.gain_steps}")
    vr, vg, vf = v["verdict_rytov"], v["verdict_greenwood_hz"], v["verdict_rate_hz"]
    if lats and vf != lp.rate_hz:
        raise ConfigError("map.verdict_rate_hz", f"on a latency axis the map runs at loop.rate_hz ({lp.rate_hz:g}); "
                          f"got {vf:g}")
    sc0 = load_scenario(rec.turbulence)
    base, scenes = {}, {}
    for r in sorted(set(rytov) | {vr}):
        sc = replace(sc0, rytov=r)
        samp = check_sampling(sc, solve_path(sc))
        if not samp.ok:
            where = "map.rytov" if r in rytov else "map.verdict_rytov"
            raise ConfigError(where, f"{r:g}: infeasible turbulence sampling ({'; '.join(samp.failures)})")
        fg0 = greenwood_frequency(sc, wind_from_dict({"wind": rec.wind}, sc, str(path)))
        if not fg0 > 0:
            raise ConfigError("wind", "the map scales the recipe's wind to each Greenwood frequency: give a "
                              "non-zero wind")
        base[r] = fg0
        for g in sorted(set(greenwood) | ({vg} if r == vr else set())):
            s = g / fg0
            wd = scaled_wind(rec.wind, s)
            try:
                wind = wind_from_dict({"wind": wd}, sc, str(path))
            except ConfigError as exc:
                where = "map.greenwood_hz" if g in greenwood else "map.verdict_greenwood_hz"
                raise ConfigError(where, f"{g:g} Hz at Rytov {r:g} needs the recipe's wind x {s:.4g} ({exc})") from None
            scenes[(r, g)] = {"wind": wd, "scale": s, **temporal_summary(sc, wind)}
    rec = replace(rec, loop=replace(lp, steps=steps))
    return MapRecipe(path.stem, path, rec, "rate_hz" if rates else "latency_ms", rates, lats, greenwood, rytov,
                     lat_methods, scan if metasurface else (), (vr, vg, vf), base, scenes)


# -- the region and the verdict (pure functions of the numbers) ----------------------------------------------

def in_region(npib_mean: float, ideal_npib_mean: float, fade_probability: float) -> bool:
    """The region criterion: mean NPiB >= :data:`REGION_VS_IDEAL` x the ideal-phase loop's and fade
    probability <= :data:`REGION_FADE_PROBABILITY`."""
    return bool(npib_mean >= REGION_VS_IDEAL * ideal_npib_mean and fade_probability <= REGION_FADE_PROBABILITY)


def regions(points: list, x_key: str) -> dict:
    """Each method's region: ``{method: [{"rytov", "greenwood_hz", x_key}, ...]}`` of the ``points`` (each
    ``{"rytov", "greenwood_hz", x_key, "methods": {m: {"npib_mean", "fade_probability"}}}``, the ideal
    loop among the methods) where :func:`in_region` holds."""
    out: dict = {}
    for p in points:
        ideal = p["methods"]["ideal"]["npib_mean"]
        for m, r in p["methods"].items():
            out.setdefault(m, [])
            if in_region(r["npib_mean"], ideal, r["fade_probability"]):
                out[m].append({"rytov": p["rytov"], "greenwood_hz": p["greenwood_hz"], x_key: p[x_key]})
    return out


def latency_reaching(latency_ms, values, level: float) -> dict:
    """Which latency keeps ``values`` (one per scanned latency) at or above ``level``: ``latency_ms``, the
    largest scanned latency up to which every scanned value reaches it (None: not even the smallest does);
    ``interpolated_ms``, where the line between that latency and the next (which fails) crosses ``level``
    (None when every scanned latency reaches it: the answer lies beyond the scan)."""
    L = np.asarray(latency_ms, float)
    v = np.asarray(values, float)
    o = np.argsort(L, kind="stable")
    L, v = L[o], v[o]
    ok = v >= level
    if not len(L) or not ok[0]:
        return {"latency_ms": None, "interpolated_ms": None}
    k = int(np.argmin(ok)) if not ok.all() else len(L)
    if k == len(L):
        return {"latency_ms": float(L[-1]), "interpolated_ms": None}
    a, b = v[k - 1], v[k]
    x = L[k - 1] + (a - level) / (a - b) * (L[k] - L[k - 1])
    return {"latency_ms": float(L[k - 1]), "interpolated_ms": float(x)}


def _fmt_reach(r: dict, scan: list) -> str:
    if r["latency_ms"] is None:
        return f"reached at no scanned latency, not even {min(scan):g} ms (latency alone does not get it there)"
    if r["interpolated_ms"] is None:
        return f"reached at every scanned latency (up to {r['latency_ms']:g} ms at least)"
    return f"reached up to {r['latency_ms']:g} ms (interpolated {r['interpolated_ms']:.3g} ms)"


def map_verdict(cell: dict | None, scan: dict, where: dict, optimised: bool | frozenset = False) -> dict:
    """The issue's verdict at one point.  ``cell``: that point's ``{"methods": {m: {"npib_mean", "latency_ms",
    "delay_frames"}}}`` (every latency as declared or measured), or None; ``scan``: ``{m: {"latency_ms":
    [...], "npib_mean": [...]}}``, each metasurface method at declared latencies there; ``where``: the
    point (``rytov``, ``greenwood_hz``, ``rate_hz``).  Returns the best metasurface loop's ratios to the
    ideal-phase and the Shack-Hartmann loops, whether each goal is met, the latencies that keep each goal
    (:func:`latency_reaching`) and a plain statement (with the best loop's ``gain`` where it was chosen per
    point: ``optimised`` True, or the set of the searched methods)."""
    out: dict = {**where, "goal_vs_ideal": GOAL_VS_IDEAL, "goal_vs_shack_hartmann": GOAL_VS_SHACK_HARTMANN}
    ms = (cell or {}).get("methods", {})
    best = max((m for m in METASURFACE if m in ms), key=lambda m: ms[m]["npib_mean"], default=None)
    head = (f"At Rytov {where['rytov']:g}, f_G {where['greenwood_hz']:g} Hz, {where['rate_hz']:g} Hz")
    out["best_metasurface"] = best
    if best is None:
        out["statement"] = f"{head}: no metasurface loop in the recipe; no verdict."
        return out
    v = ms[best]["npib_mean"]
    ideal = ms["ideal"]["npib_mean"] if "ideal" in ms else None
    sh = ms["shack_hartmann"]["npib_mean"] if "shack_hartmann" in ms else None
    out.update(npib_mean=v, latency_ms=ms[best]["latency_ms"], delay_frames=ms[best]["delay_frames"],
               gain=ms[best].get("gain"),
               ideal_npib_mean=ideal, shack_hartmann_npib_mean=sh,
               vs_ideal=v / ideal if ideal else None, vs_shack_hartmann=v / sh if sh else None)
    out["meets_ideal"] = None if out["vs_ideal"] is None else bool(out["vs_ideal"] >= GOAL_VS_IDEAL)
    out["meets_shack_hartmann"] = (None if out["vs_shack_hartmann"] is None else
                                   bool(out["vs_shack_hartmann"] >= GOAL_VS_SHACK_HARTMANN))
    met = [x for x in (out["meets_ideal"], out["meets_shack_hartmann"]) if x is not None]
    out["met"] = bool(met) and all(met)
    searched = best in optimised if isinstance(optimised, frozenset) else bool(optimised)
    gain = f", gain {ms[best]['gain']:.3g} (optimised)" if searched and ms[best].get("gain") is not None else ""
    parts = [f"{head}: {LABELS[best]} ({ms[best]['latency_ms']:.3g} ms latency, {ms[best]['delay_frames']:.2f} "
             f"frames of delay{gain}) keeps mean NPiB {v:.3f}"]
    if out["vs_ideal"] is not None:
        parts.append(f"{out['vs_ideal']:.2f} of the ideal-phase loop's (goal >= {GOAL_VS_IDEAL:g}: "
                     f"{'met' if out['meets_ideal'] else 'NOT met'})")
    if out["vs_shack_hartmann"] is not None:
        parts.append(f"{out['vs_shack_hartmann']:.2f}x the Shack-Hartmann loop's (goal >= "
                     f"{GOAL_VS_SHACK_HARTMANN:g}x: {'met' if out['meets_shack_hartmann'] else 'NOT met'})")
    text = ", ".join(parts) + "."
    s = scan.get(best)
    if s and s["latency_ms"]:
        lat, vals = s["latency_ms"], np.asarray(s["npib_mean"], float)
        reach = {}
        if ideal:
            reach["ideal"] = latency_reaching(lat, vals, GOAL_VS_IDEAL * ideal)
        if sh:
            reach["shack_hartmann"] = latency_reaching(lat, vals, GOAL_VS_SHACK_HARTMANN * sh)
        if ideal and sh:
            both = np.minimum(vals / (GOAL_VS_IDEAL * ideal), vals / (GOAL_VS_SHACK_HARTMANN * sh))
            reach["both"] = latency_reaching(lat, both, 1.0)
        out["latency_scan"] = {"method": best, "latency_ms": list(lat), "npib_mean": vals.tolist()}
        out["latency_for"] = reach
        names = {"ideal": f"{GOAL_VS_IDEAL:g} of the ideal", "shack_hartmann": f"{GOAL_VS_SHACK_HARTMANN:g}x the "
                 "Shack-Hartmann", "both": "both goals"}
        text += (f" Which latency would get it there (the same loop with its latency declared, scanned at "
                 f"{', '.join(format(x, 'g') for x in lat)} ms): "
                 + "; ".join(f"{names[k]}: {_fmt_reach(r, lat)}" for k, r in reach.items()) + ".")
    out["statement"] = text
    return out


# -- the runs ------------------------------------------------------------------------------------------------

@dataclass
class MapContext:
    """What every task of a map shares (sent to each worker once): the loop study's context of the first
    Rytov number (device, mirror, sensors, measured latencies), the turbulence and bucket at each Rytov
    number, each (Rytov, f_G)'s wind, and per Rytov number what differs from the first's (``sensors``,
    ``latency``, ``sh``: the Shack-Hartmann of ``sh_lenslets = "auto"``, its latency and count).
    :meth:`context` is a point's :class:`LoopContext` (the last one kept in the process, its drawn flow with
    it)."""

    base: LoopContext
    turbulence: dict  # rytov -> (Turbulence, PiB)
    winds: dict  # (rytov, f_G) -> [wind] (recipe units)
    sensors: dict = field(default_factory=dict)  # rytov -> {method: sensor} replacing the base's
    latency: dict = field(default_factory=dict)  # rytov -> {method: seconds} replacing the base's
    sh: dict = field(default_factory=dict)  # rytov -> the Shack-Hartmann's count and why (sh_lenslets_for)
    _cache: dict = field(default_factory=dict, repr=False)

    def __getstate__(self):
        return {**self.__dict__, "_cache": {}}

    def context(self, point: tuple, method: str, latency_ms: float | None) -> LoopContext:
        """The loop study's context at ``point`` (``(rytov, f_G, rate)``), ``method``'s latency declared
        ``latency_ms`` (None: as the study measured or the recipe declared it)."""
        if self._cache.get("point") != point:
            r, g, rate = point
            tb, pib = self.turbulence[r]
            b = self.base
            rec = replace(b.rec, loop=replace(b.rec.loop, rate_hz=rate, rytov=r), wind=self.winds[(r, g)])
            wind = wind_from_dict({"wind": rec.wind}, tb.sc, str(rec.source))
            self._cache = {"point": point, "ctx": replace(
                b, rec=rec, tb=tb, wind=wind, pib=pib, sensors={**b.sensors, **self.sensors.get(r, {})},
                latency=self.latency_at(r), sh=self.sh.get(r, b.sh), _cache={})}
        ctx = self._cache["ctx"]
        if latency_ms is not None:
            ctx = replace(ctx, latency={**ctx.latency, method: latency_ms * 1e-3})  # the drawn flow shared
        return ctx

    def latency_at(self, rytov: float) -> dict:
        """Each closed loop's latency (s) at ``rytov`` (declared or measured; no latency axis applied)."""
        return {**self.base.latency, **self.latency.get(rytov, {})}


def _map_task(mctx: MapContext, task: tuple) -> tuple[str, dict]:
    """One run of a map: ``(name, point, method, latency_ms, realisation, gain, steps)`` -> ``(name, series)``."""
    name, point, m, lat, r, gain, steps = task
    return name, mctx.context(point, m, lat).run(m, r, gain, steps, modal=False)


def _trial_name(key: tuple, g: float) -> str:
    ry, fg, rate, m, lat = key
    return f"gain-ry{ry!r}-fg{fg!r}-rate{rate!r}-lat{'m' if lat is None else repr(lat)}-{m}-{g:.4f}"


def _search_gains(mctx: MapContext, keys: list, steps: int, folder: TaskFolder, run: Execution) -> dict:
    """``gain = "optimise"`` on a map: for each run ``key`` (point, closed loop, declared latency or None) the
    loop study's search at that point (:func:`metadesign.studies.loop_study.gain_search`: the mean NPiB of
    ``steps`` frames of realisation 0 at each gain of ``GAIN_GRID``, then at ``GAIN_REFINE`` around the
    grid's best, the best of all winning, the lowest gain on a tie), every key's trials of a stage one task
    set; ``{key: {"gain", "gains", "npib_mean"}}`` (the trials in increasing gain)."""
    def run_stage(trials: list) -> dict:
        tasks = {_trial_name(k, g): (_trial_name(k, g), k[:3], k[3], k[4], 0, float(g), steps) for k, g in trials}
        res, _ = run.run(_map_task, tasks, folder, shared=mctx, weight=lambda n: steps, unit="step")
        return {((*point, m, lat), g): float(np.mean(res[n]["npib"]))
                for n, (_, point, m, lat, _, g, _) in tasks.items()}

    return gain_search(keys, run_stage)


def _run_key(point: tuple, m: str, lat: float | None) -> tuple:
    return (*point, m, lat if m not in ORACLES else None)


def _name(key: tuple, r: int) -> str:
    ry, g, rate, m, lat = key
    return f"ry{ry!r}-fg{g!r}-rate{rate!r}-lat{'m' if lat is None else repr(lat)}-seed{r:05d}-{m}"


def _map_key(mrec: MapRecipe) -> str:
    """The content key of a map's tasks (what shapes their series; never where the files lie)."""
    rec = mrec.loop
    files = {k: file_key(p) for k, p in (("design", rec.design), ("sensor", rec.sensor),
                                         ("turbulence", rec.turbulence), ("model", rec.model),
                                         ("realtime", rec.realtime)) if p is not None}
    lp = {**rec.loop.__dict__, "methods": list(rec.loop.methods)}
    grid = {"axis": mrec.axis, "rates_hz": mrec.rates_hz, "latency_ms": mrec.latency_ms,
            "greenwood_hz": mrec.greenwood_hz, "rytov": mrec.rytov, "latency_methods": mrec.latency_methods,
            "scan": mrec.scan_latency_ms, "verdict": mrec.verdict}
    doc = {"format": "metadesign.loop-map-tasks/1", "loop": lp, "dm": rec.dm.__dict__, "wind": rec.wind,
           "files": files, "map": grid}
    if rec.loop.sh_lenslets == AUTO and "shack_hartmann" in rec.loop.methods:
        doc["sh_lenslets"] = "per Rytov number"  # (the key of a map that resolved it at its first only differs)
    return content_key(doc)


def _plan(mrec: MapRecipe) -> tuple[list, list, dict]:
    """The grid's cells ``(rytov, f_G, x, (rytov, f_G, rate, latency))``, the verdict's scan runs and every
    distinct run ``{key: None}`` in a fixed order (point by point)."""
    lp = mrec.loop.loop
    cells, runs = [], {}
    for r in mrec.rytov:
        for g in mrec.greenwood_hz:
            for x in mrec.xs:
                c = mrec.cell(r, g, x)
                cells.append((r, g, x, c))
                for m in lp.methods:
                    runs[_run_key(c[:3], m, c[3] if m in mrec.latency_methods else None)] = None
    vpoint = mrec.verdict
    for m in lp.methods:
        runs[_run_key(vpoint, m, None)] = None
    scan = []
    for m in lp.methods:
        if m in METASURFACE:
            for lat in mrec.scan_latency_ms:
                k = _run_key(vpoint, m, lat)
                scan.append(k)
                runs[k] = None
    order = sorted(runs, key=lambda k: (k[:3], lp.methods.index(k[3]), -1 if k[4] is None else k[4]))
    return cells, scan, {k: None for k in order}


def _summary(key: tuple, series: list, mrec: MapRecipe, latency: dict, gain: float | None) -> dict:
    """One run's numbers (pooled over the seeds): mean and 1 % NPiB, fade probability and rate, the latency,
    the loop's delay and its gain (None: an oracle)."""
    lp = mrec.loop.loop
    _, _, rate, m, lat = key
    closed = m not in ORACLES
    lat_s = (lat * 1e-3 if lat is not None else latency.get(m, 0.0)) if closed else 0.0
    npib = np.concatenate([s["npib"] for s in series])
    fades = _pooled_fades(series, 1.0 / rate, lp.threshold_db)
    timing = LoopTiming(rate, lp.substeps, lp.readout_frames, lat_s, lp.dm_frames)
    return {"npib_mean": float(np.mean(npib)), "npib_p01": float(np.percentile(npib, 1)),
            "fade_probability": fades["probability"], "fades_per_s": fades["fades_per_s"],
            "latency_ms": lat_s * 1e3, "latency_declared": bool(closed and (lat is not None or m in lp.latency_ms or m == "ideal")),
            "delay_frames": timing.delay_frames if closed else 0.0, "gain": gain,
            "seconds": float(sum(float(s["seconds"]) for s in series))}


def run_loop_map(mrec: MapRecipe, out: Path, run: Execution = SERIAL) -> dict:
    """Every run of the map ``mrec`` into ``out`` (``map.json``, ``map.png``, the designed device in
    ``out/design``); the runs resumable in ``OUT.partial`` (removed at the end)."""
    t_start = time.perf_counter()
    rec = mrec.loop
    lp = rec.loop
    ctx0, device, _ = build_loop(replace(rec, loop=replace(lp, rytov=mrec.rytov[0])), out, lambda s: None)
    cells, scan_keys, runs = _plan(mrec)
    xs = ", ".join(format(x, "g") for x in mrec.xs)
    run.log(f"loop map: {mrec.name}: {'rates' if mrec.axis == 'rate_hz' else 'latencies'} {xs} "
            f"{'Hz' if mrec.axis == 'rate_hz' else 'ms'} x f_G {', '.join(format(g, 'g') for g in mrec.greenwood_hz)} "
            f"Hz x Rytov {', '.join(format(r, 'g') for r in mrec.rytov)}; {len(runs)} runs x {lp.seeds} seed"
            f"{'s' if lp.seeds > 1 else ''} x {lp.steps} steps; methods {', '.join(lp.methods)}")
    folder = TaskFolder(scratch_path(out), _map_key(mrec), log=run.log, what="loop map")
    ctx0.latency = _measure_latencies(ctx0, folder)
    turbulence = {}
    for r in sorted({k[0] for k in runs}):
        tb = ctx0.tb.at_rytov(r)
        turbulence[r] = (tb, PiB(tb.sc, ctx0.c0, ctx0.a))
    sensors, latency, sh = _shack_hartmann_per_rytov(ctx0, device, turbulence, folder, run.log)
    ctx0._cache.clear()
    mctx = MapContext(ctx0, turbulence, {k: v["wind"] for k, v in mrec.scenes.items()}, sensors, latency, sh)
    search = {}
    if lp.optimise_gain:
        searched = set(lp.searched(sorted({k[3] for k in runs if k[3] not in ORACLES})))
        closed = [k for k in runs if k[3] in searched]
        run.log(f"  gains: the loop study's search at each of {len(closed)} closed-loop runs ({lp.gain_steps} steps "
                "of the first seed a trial)")
        search = _search_gains(mctx, closed, lp.gain_steps, folder, run)
        for k, v in search.items():
            run.log(f"  gain {_where(k)} {LABELS[k[3]]}: {v['gain']:.3f} ({len(v['gains'])} trials)")
    gains = {k: None if k[3] in ORACLES else search[k]["gain"] if k in search else lp.given(k[3]) for k in runs}
    tasks = {}
    for k in runs:
        for r in range(lp.seeds):
            n = _name(k, r)
            tasks[n] = (n, k[:3], k[3], k[4], r, 0.0 if gains[k] is None else gains[k], lp.steps)
    res, _ = run.run(_map_task, tasks, folder, shared=mctx, weight=lambda n: lp.steps, unit="step")
    summ = {k: _summary(k, [res[_name(k, r)] for r in range(lp.seeds)], mrec, mctx.latency_at(k[0]), gains[k])
            for k in runs}
    points = []
    for r, g, x, c in cells:
        ms = {m: summ[_run_key(c[:3], m, c[3] if m in mrec.latency_methods else None)] for m in lp.methods}
        points.append(_point(r, g, x, mrec, ms, sh.get(r)))
    vr, vg, vf = mrec.verdict
    vcell = {"methods": {m: summ[_run_key(mrec.verdict, m, None)] for m in lp.methods}}
    scan: dict = {}
    for k in scan_keys:
        s = scan.setdefault(k[3], {"latency_ms": [], "npib_mean": [], "fade_probability": [],
                                   "delay_frames": [], **({"gain": []} if lp.optimise_gain else {})})
        for f in s:
            s[f].append(summ[k][f])
    where = {"rytov": vr, "greenwood_hz": vg, "rate_hz": vf}
    verdict = map_verdict(vcell, scan, where, optimised=frozenset(lp.searched(list(lp.methods))))
    verdict["methods"] = {m: _pick(v) for m, v in vcell["methods"].items()}
    verdict["scans"] = scan
    on_grid = any(c[:3] == mrec.verdict and c[3] is None for *_, c in cells)
    verdict["on_grid"] = on_grid
    rep = {"format": "metadesign.loop-map/1", "recipe": str(mrec.source), "axis": mrec.axis,
           "map": {"rytov": list(mrec.rytov), "greenwood_hz": list(mrec.greenwood_hz),
                   "rates_hz": list(mrec.rates_hz), "latency_ms": list(mrec.latency_ms), "steps": lp.steps,
                   "latency_methods": list(mrec.latency_methods), "scan_latency_ms": list(mrec.scan_latency_ms),
                   "verdict": where},
           "loop": {**lp.__dict__, "methods": list(lp.methods),
                    "latency_ms": {m: s * 1e3 for m, s in lp.latency_ms.items()}},
           "dm": rec.dm.__dict__,
           "criterion": {"npib_vs_ideal": REGION_VS_IDEAL, "fade_probability": REGION_FADE_PROBABILITY,
                         "threshold_db": lp.threshold_db,
                         "fade": "NPiB below its own mean (pooled over the seeds) by threshold_db"},
           "greenwood": {"weighting": "plane wave (w_i = 1, the loop study's f_G); the spherical-wave f_G beside it",
                         "base_wind": rec.wind,
                         "base_greenwood_hz": [{"rytov": r, "greenwood_hz": g} for r, g in
                                               sorted(mrec.base_greenwood_hz.items())],
                         "scenes": [{"rytov": r, "greenwood_hz": g, **s} for (r, g), s in sorted(mrec.scenes.items())]},
           "latencies_ms": {m: s * 1e3 for m, s in sorted(ctx0.latency.items())},
           "gain": _gain_record(lp, search),
           "points": points, "regions": regions(points, mrec.axis), "verdict": verdict}
    if sh:
        rep["shack_hartmann"] = [{"rytov": r, **v, "latency_ms": mctx.latency_at(r)["shack_hartmann"] * 1e3}
                                 for r, v in sorted(sh.items())]
    rep["seconds"] = time.perf_counter() - t_start
    rep["figures"] = [str(p) for p in _plot(rep, out)]
    atomic_write_text(out / "map.json", json.dumps(rep, indent=1, default=float))
    folder.remove()
    return rep


def _where(k: tuple) -> str:
    ry, fg, rate, _, lat = k
    return f"Rytov {ry:g}, f_G {fg:g} Hz, {rate:g} Hz{'' if lat is None else f', {lat:g} ms'}"


def _shack_hartmann_per_rytov(ctx0: LoopContext, device, turbulence: dict, folder: TaskFolder, log) -> tuple:
    """The Shack-Hartmann at each Rytov number of the map: ``(sensors, latency, sh)``, each ``{rytov: ...}``:
    the sensor and its latency (s) where its count differs from the first Rytov number's (``ctx0``'s:
    ``sh_lenslets = "auto"``), and every Rytov number's count and why (:func:`sh_lenslets_for`).  A latency
    not declared is measured once per count on the first Rytov number's first frame (the reconstruction's
    time, kept in the resume folder like the others)."""
    lp = ctx0.rec.loop
    if "shack_hartmann" not in lp.methods:
        return {}, {}, {}
    sh = {r: sh_lenslets_for(tb.sc, lp.sh_lenslets) for r, (tb, _) in sorted(turbulence.items())}
    sensors, latency, built = {}, {}, {}
    for r, v in sh.items():
        n = v["lenslets"]
        if n == ctx0.sh["lenslets"]:
            continue
        if n not in built:
            one = replace(ctx0.rec, model=None, realtime=None, loop=replace(lp, methods=("shack_hartmann",)))
            s = _sensors(one, device, n)["shack_hartmann"]
            if "shack_hartmann" in lp.latency_ms:
                lat = float(lp.latency_ms["shack_hartmann"])
            else:
                got, _ = folder.step(f"latency-shack-hartmann-{n}", folder.key,
                                     lambda: {"seconds": _latency(s, ctx0.world(0))})
                lat = float(got["seconds"])
            built[n] = (s, lat)
        sensors[r] = {"shack_hartmann": built[n][0]}
        latency[r] = {"shack_hartmann": built[n][1]}
    for r, v in sh.items():
        log(f"  Shack-Hartmann at Rytov {r:g}: {v['lenslets']} lenslets across, d/r0 {v['d_over_r0']:.2f} ({v['why']})")
    return sensors, latency, sh


def _gain_record(lp, search: dict) -> dict:
    """How the gains were set: fixed, or the search (its rule and every run's trials)."""
    if not lp.optimise_gain:
        return {"rule": "fixed", "gain": lp.gain}
    given = {m: g for m, g in lp.gain.items() if g != OPTIMISE} if isinstance(lp.gain, dict) else {}
    return {"rule": "optimise", **({"given": given} if given else {}), "grid": list(GAIN_GRID),
            "refine": list(GAIN_REFINE), "steps": lp.gain_steps, "realisation": 0,
            "criterion": "the highest mean NPiB over the first gain_steps frames of the first realisation (the "
                         "lowest gain on a tie): the grid, then the refinement around its best",
            "searches": [{"rytov": k[0], "greenwood_hz": k[1], "rate_hz": k[2], "method": k[3],
                          "latency_ms": k[4], **v} for k, v in search.items()]}


def _pick(s: dict) -> dict:
    return {k: s[k] for k in ("npib_mean", "npib_p01", "fade_probability", "fades_per_s", "latency_ms",
                              "latency_declared", "delay_frames", "gain", "seconds")}


def _point(r: float, g: float, x: float, mrec: MapRecipe, ms: dict, sh: dict | None = None) -> dict:
    ideal = ms["ideal"]["npib_mean"]
    methods = {}
    for m, s in ms.items():
        methods[m] = {**_pick(s), "vs_ideal": s["npib_mean"] / ideal if ideal > 0 else None,
                      "in_region": in_region(s["npib_mean"], ideal, s["fade_probability"])}
    p: dict[str, Any] = {"rytov": r, "greenwood_hz": g, mrec.axis: x}
    if mrec.axis == "latency_ms":
        p["rate_hz"] = mrec.loop.loop.rate_hz
    p["methods"] = methods
    if sh:
        p["shack_hartmann"] = sh
    best = max((m for m in METASURFACE if m in ms), key=lambda m: ms[m]["npib_mean"], default=None)
    p["best_metasurface"] = best
    if best is not None and "shack_hartmann" in ms and ms["shack_hartmann"]["npib_mean"] > 0:
        p["metasurface_vs_shack_hartmann"] = ms[best]["npib_mean"] / ms["shack_hartmann"]["npib_mean"]
    return p


# -- the figure ------------------------------------------------------------------------------------------------

MARKERS = {"ideal": ("^", "tab:green"), "shack_hartmann": ("s", "tab:orange"), "realtime": ("o", "tab:blue"),
           "linear": ("D", "tab:purple"), "unet": ("o", "tab:cyan"), "refine": ("P", "tab:red"),
           "fitted": ("*", "tab:olive"), "conjugate": ("X", "tab:brown"), "open": ("v", "tab:gray"),
           "realtime_tt": ("h", "tab:pink"),
           "realtime_peak": ("H", "tab:blue"), "retrieval": ("d", "black"), "refine_warm": ("p", "gold")}


def _plot(rep: dict, out: Path) -> list[Path]:
    """One panel per Rytov number (x: rate or latency, y: f_G, a cell per point): each method's marker filled
    where the point is in its region, hollow where not; the cell shaded by the best metasurface loop's NPiB
    over the ideal loop's, its ratio to the Shack-Hartmann loop's written in it; the verdict's point framed;
    with ``gain = "optimise"`` each closed loop's chosen gain written at the top of its cell (and beside each
    scanned latency), with ``sh_lenslets = "auto"`` the Shack-Hartmann's count in the panel's title.  A last
    panel: the verdict's latency scan."""
    plt = pyplot()
    mp, axis = rep["map"], rep["axis"]
    xs, gs, rys = mp["rates_hz"] if axis == "rate_hz" else mp["latency_ms"], mp["greenwood_hz"], mp["rytov"]
    methods = [m for m in rep["loop"]["methods"] if m in MARKERS]
    v = rep["verdict"]
    scan = v.get("scans") or {}
    n = len(rys) + (1 if scan else 0)
    fig, axs = plt.subplots(1, n, figsize=(n * (2.4 + 1.0 * max(len(xs), 3)), 2.9 + 0.8 * len(gs)),
                            layout="constrained", squeeze=False)
    axs = axs[0]
    xlabel = "loop rate (Hz)" if axis == "rate_hz" else f"latency of {', '.join(mp['latency_methods'])} (ms)"
    shown, im = set(), None
    optimised = rep.get("gain", {}).get("rule") == "optimise"
    lenslets = ({s["rytov"]: s["lenslets"] for s in rep.get("shack_hartmann", [])}
                if rep["loop"].get("sh_lenslets") == "auto" else {})
    for ax, ry in zip(axs, rys):
        pts = {(p["greenwood_hz"], p[axis]): p for p in rep["points"] if p["rytov"] == ry}
        shade = np.full((len(gs), len(xs)), np.nan)
        for i, g in enumerate(gs):
            for j, x in enumerate(xs):
                p = pts[(g, x)]
                if p["best_metasurface"]:
                    shade[i, j] = p["methods"][p["best_metasurface"]]["vs_ideal"] or 0.0
                for k, m in enumerate(methods):
                    mk, col = MARKERS[m]
                    dx = (k - (len(methods) - 1) / 2) * min(0.16, 0.8 / max(len(methods), 1))
                    inside = p["methods"][m]["in_region"]
                    ax.plot(j + dx, i + 0.15, mk, ms=8, color=col, mfc=col if inside else "none", mew=1.3,
                            label=LABELS[m] if m not in shown else None)
                    shown.add(m)
                words = [f"{shade[i, j]:.2f} x ideal"] if np.isfinite(shade[i, j]) else []
                if "metasurface_vs_shack_hartmann" in p:
                    words.append(f"{p['metasurface_vs_shack_hartmann']:.2f} x SH")
                if words:
                    ax.text(j, i - 0.22, "\n".join(words), ha="center", va="center", fontsize=7)
                if optimised:
                    gains = " ".join(f"{LETTERS[m]} {p['methods'][m]['gain']:.3g}" for m in methods
                                     if p["methods"][m].get("gain") is not None)
                    ax.text(j, i + 0.40, f"gain {gains}", ha="center", va="center", fontsize=6)
        if np.isfinite(shade).any():
            im = ax.imshow(shade, origin="lower", cmap="Greys", vmin=0, vmax=1.25, alpha=0.45, aspect="auto",
                           extent=(-0.5, len(xs) - 0.5, -0.5, len(gs) - 0.5))
        vx = v["rate_hz"] if axis == "rate_hz" else None
        if ry == v["rytov"] and v["greenwood_hz"] in gs and v.get("on_grid") and vx in xs:
            i, j = gs.index(v["greenwood_hz"]), xs.index(vx)
            ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=2, ec="crimson"))
        ax.set_xticks(range(len(xs)), [format(x, "g") for x in xs])
        ax.set_yticks(range(len(gs)), [format(g, "g") for g in gs])
        ax.set_xlim(-0.5, len(xs) - 0.5)
        ax.set_ylim(-0.5, len(gs) - 0.5)
        ax.set(xlabel=xlabel, ylabel="f_G (Hz, plane wave)",
               title=f"Rytov {ry:g}{f' (SH {lenslets[ry]} lenslets)' if ry in lenslets else ''}: filled = "
                     f"in region\n(NPiB >= {REGION_VS_IDEAL:g} x ideal, "
                     f"P(fade {rep['criterion']['threshold_db']:g} dB) <= {REGION_FADE_PROBABILITY:g})")
        ax.title.set_fontsize(9)
    if im is not None:
        fig.colorbar(im, ax=list(axs[:len(rys)]), shrink=0.8, label="shade: best metasurface NPiB / ideal's")
    handles, labels = axs[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(len(labels), 5), fontsize=8, frameon=False)
    if scan:
        ax = axs[-1]
        for m, s in scan.items():
            mk, col = MARKERS[m]
            ax.plot(s["latency_ms"], s["npib_mean"], mk + "-", color=col, label=LABELS[m])
            for lat, y, g in zip(s["latency_ms"], s["npib_mean"], s.get("gain", ())):
                ax.annotate(f"gain {g:.2f}", (lat, y), textcoords="offset points", xytext=(3, 4), fontsize=6)
        ms = v.get("methods", {})
        if "ideal" in ms:
            ax.axhline(GOAL_VS_IDEAL * ms["ideal"]["npib_mean"], color="tab:green", ls="--", lw=1,
                       label=f"{GOAL_VS_IDEAL:g} x ideal loop")
        if "shack_hartmann" in ms:
            ax.axhline(GOAL_VS_SHACK_HARTMANN * ms["shack_hartmann"]["npib_mean"], color="tab:orange", ls="--",
                       lw=1, label=f"{GOAL_VS_SHACK_HARTMANN:g} x Shack-Hartmann loop")
        if v.get("best_metasurface"):
            ax.axvline(v["latency_ms"], color="crimson", lw=1, ls=":",
                       label=f"its latency ({v['latency_ms']:.3g} ms)")
        ax.set(xlabel="declared latency (ms)", ylabel="mean NPiB",
               title=f"verdict point: Rytov {v['rytov']:g}, f_G {v['greenwood_hz']:g} Hz, {v['rate_hz']:g} Hz")
        ax.title.set_fontsize(9)
        ax.legend(fontsize=7)
    return [save_figure(fig, out / "map.png")]

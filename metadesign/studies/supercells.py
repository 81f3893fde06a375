"""The supercell table of a design (``library/paper-supercells.toml``): which supercells to solve, and the
resumable build.

Rows are drawn from what the design actually uses and around it, each row from its own generator
(``SeedSequence(seed, spawn_key=(k,))``), so the first ``n`` rows of a larger table are the rows of the
smaller one (a table grows without re-solving what it has) and the held-out rows (every
``test_every``-th) are the same whatever the size:

* ``design``: a supercell of the main design at a random place (its four atoms, as the layout places them);
* ``extra_design``: the same on a second design (the demo);
* ``atom_tuples``: four atoms of the main design's table drawn independently (the compensating
  discretizer's search space);
* ``jittered_atoms``: four atoms, each width moved by a uniform draw in ``+-jitter_nm`` (the fab studies'
  perturbed widths), kept inside the library's width range.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..config import ConfigError, Param, Section, load_toml, parse
from ..design.recipe import load_design_recipe
from ..design.store import Design, design_file, load_design, run_design
from ..library.coupling import CouplingConfig, lpa_t, relative_error
from ..library.coupling_net import coupling_t, fit_coupling
from ..library.locate import file_sha256
from ..library.peds import PedsModel, certified_t, fit_peds, low_fidelity_couplings, patch_windows, peds_t, ring_couplings
from ..library.store import interpolate_t, load_library
from ..library.supercell import solve_patch, solve_supercell
from ..library.supercells import (
    SupercellTable,
    matched_harmonics,
    matched_unit_harmonics,
    unit_cells,
    remove_partial,
    save_table,
    solve_table,
)
from ..plotting import pyplot, save_figure
from ..tasks import TaskFolder, content_key, run_resumable
from ..outputs import Need, temporary

__all__ = ["SupercellRecipe", "load_supercell_recipe", "sample_rows", "build_table", "pool_widths", "convergence_ladder",
           "patch_study", "design_source", "SOURCES", "certify_coupling",
           "plot_coupling", "certify_peds", "plot_peds", "select_levels", "design_patches", "solve_patches",
           "plot_patches"]

SOURCES = ("design", "extra_design", "atom_tuples", "jittered_atoms")

SUPERCELL_SECTIONS = (
    Section("table", (
        Param("library", str, help="the unit-cell library (relative to the recipe)"),
        Param("design", str, help="the main design: a design recipe (.toml) or store (relative to the recipe)"),
        Param("extra_design", str, None, help="a second design sampled too (optional)"),
        Param("supercells", int, 1000, lo=1, hi=10_000_000),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
        Param("test_every", int, 5, lo=2, hi=1000, help="every k-th row is held out of every fit"),
        Param("n_harmonics", int, 800, lo=20, hi=5000, help="requested supercell harmonics (matched to the library)"),
        Param("chunk", int, 8, lo=1, hi=10000),
    )),
    Section("mix", (
        Param("design", float, 0.5, lo=0, hi=1),
        Param("extra_design", float, 0.1, lo=0, hi=1),
        Param("atom_tuples", float, 0.2, lo=0, hi=1),
        Param("jittered_atoms", float, 0.2, lo=0, hi=1),
        Param("jitter_nm", float, 15.0, lo=0, hi=100),
    )),
)


@dataclass(frozen=True)
class SupercellRecipe:
    source: Path
    library: Path
    design: Path
    extra_design: Path | None
    supercells: int
    seed: int
    test_every: int
    n_harmonics: int
    chunk: int
    mix: tuple[float, float, float, float]
    jitter: float  # m

    def default_output(self) -> Path:
        return self.source.with_suffix(".npz")


def load_supercell_recipe(path: str | Path) -> SupercellRecipe:
    path = Path(path)
    v = parse(load_toml(path), SUPERCELL_SECTIONS, str(path))
    t, m = v["table"], v["mix"]
    mix = tuple(float(m[k]) for k in SOURCES)
    if abs(sum(mix) - 1) > 1e-9:
        raise ConfigError("mix", f"the four fractions must add up to 1, got {sum(mix):g}")
    if t["extra_design"] is None and mix[1] > 0:
        raise ConfigError("mix.extra_design", "must be 0 without table.extra_design")
    base = path.parent
    return SupercellRecipe(path, base / t["library"], base / t["design"],
                           None if t["extra_design"] is None else base / t["extra_design"], t["supercells"],
                           t["seed"], t["test_every"], t["n_harmonics"], t["chunk"], mix, m["jitter_nm"])


def design_source(path: Path, log) -> tuple[Design, str]:
    """A design from a store, or from a recipe: its store if one is beside it, else built in a temporary
    folder."""
    if path.suffix == ".toml":
        rec = load_design_recipe(path)
        store = rec.default_output()
        if (store / "design.npz").exists():
            return load_design(store), file_sha256(store / "design.npz")
        log(f"  designing {path.name} (no store at {store}) ...")
        with temporary() as tmp:
            d, out = run_design(rec, tmp / "d")
            return d, file_sha256(design_file(out))
    return load_design(path), file_sha256(design_file(path))


def _design_widths(d: Design) -> tuple[np.ndarray, np.ndarray]:
    return np.stack([d.atoms.wx, d.atoms.wy], 1), d.index_map


def sample_rows(n: int, seed: int, mix, main: tuple, extra: tuple | None, w_range: tuple[float, float],
                jitter: float, test_every: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(widths (n, 2, 2, 2) m, source (n,), test (n,))``; ``main``/``extra`` = (atom widths (m, 2), index map
    [iy, ix] with the no-pillar sentinel outside the atom range)."""
    aw, im = main
    cdf = np.cumsum(mix)
    widths = np.empty((n, 2, 2, 2))
    source = np.empty(n, np.int8)
    for k in range(n):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(k,)))
        s = int(np.searchsorted(cdf, rng.random(), side="right"))
        s = min(s, 3)
        if s in (0, 1):
            w_atoms, imap = (aw, im) if s == 0 else extra
            H, W = imap.shape[0] // 2, imap.shape[1] // 2
            for _ in range(100000):
                I, J = int(rng.integers(H)), int(rng.integers(W))
                blk = imap[2 * I:2 * I + 2, 2 * J:2 * J + 2].astype(np.int64)
                if (blk < len(w_atoms)).all():
                    break
            else:
                raise ValueError("no supercell with four pillars found in the design")
            widths[k] = w_atoms[blk]
        else:
            a = rng.integers(len(aw), size=(2, 2))
            w = aw[a]
            if s == 3:
                w = np.clip(w + rng.uniform(-jitter, jitter, size=w.shape), *w_range)
            widths[k] = w
        source[k] = s
    test = (np.arange(n) % test_every) == test_every - 1
    return widths, source, test


#: the candidate pool of active learning draws from another stream than the table's rows
POOL_SEED_OFFSET = 2**32


def pool_widths(recipe: SupercellRecipe, n: int, log=lambda s: None) -> np.ndarray:
    """(n, 2, 2, 2) candidate supercells drawn like the recipe's rows (the same mix, designs and jitter)
    from another stream: the active-learning pool."""
    lib = load_library(recipe.library)
    main = _design_widths(design_source(recipe.design, log)[0])
    extra = None if recipe.extra_design is None else _design_widths(design_source(recipe.extra_design, log)[0])
    w_range = (float(lib.wx.min()), float(lib.wx.max()))
    return sample_rows(n, recipe.seed + POOL_SEED_OFFSET, recipe.mix, main, extra, w_range, recipe.jitter,
                       recipe.test_every)[0]


def supercell_need(n: int, n_harmonics: int, workers: int) -> Need:
    """A supercell table's peak: the rows on disk twice (chunks + the table) and, per worker, the RCWA
    solve's matrices (about 30 complex (2 nG)^2 arrays)."""
    return Need(disk=2 * n * 256.0, memory=workers * 30 * 16.0 * (2 * n_harmonics) ** 2,
                what="fewer -j workers or a lower table.n_harmonics")


def build_table(recipe: SupercellRecipe, output: Path, *, supercells: int | None = None, workers: int = 1,
                scheduler: str | None = None, progress: Callable[[int, int], None] | None = None,
                log: Callable[[str], None] = lambda s: None, _stop_after_chunks: int | None = None) -> dict:
    """Solve (or resume, or extend) the table of ``recipe`` into ``output`` (written atomically at the end;
    the solved chunks stay in ``<output>.partial/`` until then)."""
    n = int(supercells or recipe.supercells)
    lib = load_library(recipe.library)
    stack = lib.stack
    ns, nu = matched_unit_harmonics(recipe.n_harmonics, stack)
    lib_nG = lib.meta.get("solver", {}).get("n_harmonics")
    # at the library's own truncation the library is the matched unit cell; at any other the table solves
    # each row's four unit cells too (the coupling at that truncation: SupercellTable.labels)
    unit = None if lib_nG is not None and nu - 1 == lib_nG else nu
    d_main, sha_main = design_source(recipe.design, log)
    main = _design_widths(d_main)
    extra, sha_extra = (None, None)
    if recipe.extra_design is not None:
        d_x, sha_extra = design_source(recipe.extra_design, log)
        extra = _design_widths(d_x)
    w_range = (float(lib.wx.min()), float(lib.wx.max()))
    widths, source, test = sample_rows(n, recipe.seed, recipe.mix, main, extra, w_range, recipe.jitter,
                                       recipe.test_every)
    partial = output.parent / (output.name + ".partial")
    log(f"solving {n} supercells (nG {ns - 1}, matched to " + ("the library's" if unit is None else
        "unit cells solved at") + f" {nu - 1}) -> {output}")
    t, nG, seconds, t_unit = solve_table(widths, stack, ns, partial, workers=workers, scheduler=scheduler,
                                         chunk_size=recipe.chunk, unit_harmonics=unit, progress=progress, log=log,
                                         _stop_after_chunks=_stop_after_chunks)
    meta = {
        "version": __version__, "recipe": str(recipe.source.name), "seed": recipe.seed, "supercells": n,
        "test_every": recipe.test_every, "n_harmonics": nG, "unit_n_harmonics": nu - 1,
        "sources": list(SOURCES), "mix": dict(zip(SOURCES, recipe.mix)), "jitter_m": recipe.jitter,
        "library": {"path": recipe.library.name, "sha256": file_sha256(recipe.library)},
        "design": {"path": recipe.design.name, "sha256": sha_main},
        "extra_design": None if recipe.extra_design is None else {"path": recipe.extra_design.name,
                                                                  "sha256": sha_extra},
        "stack": lib.meta["stack"], "solver": "grcwa, 2 x 2 supercell, two mirror-symmetry sectors, Li's staircase rule",
        "labels": "t itself (the library is the matched unit cell)" if unit is None else
                  "LPA + (t - mean of t_unit): the coupling at this truncation on the library's LPA",
        "layout": "widths_m[k, r, c] = (wx, wy) of the pillar at x = c p, y = r p; t[k] = (t_x, t_y)",
        "convention": lib.meta.get("convention", {}),
    }
    save_table(output, SupercellTable(widths, t, source, test, meta, t_unit))
    remove_partial(partial)
    return {"output": str(output), "supercells": n, "held_out": int(test.sum()), "n_harmonics": nG,
            "solve_seconds": seconds, "workers": workers,
            "seconds_per_supercell_core": seconds * max(1, workers) / max(1, n)}


def convergence_ladder(table: SupercellTable, lib, rows: np.ndarray, harmonics, partial: Path, *, workers: int = 1,
                       scheduler: str | None = None, progress=None, log=lambda s: None) -> dict:
    """Rows ``rows`` of ``table`` re-solved at each requested truncation of ``harmonics`` (ascending), each
    with its unit cells at the matched truncation; per level the label in the library's frame (LPA + the
    coupling measured there, :meth:`SupercellTable.labels`), and between consecutive levels its change in
    units of the pillars' rms ``|t|`` (the convergence of a label: the goal is <= 0.01), beside the change of
    the raw supercell ``t``.  Chunks under ``partial/level-<nG>`` (resumable)."""
    rows = np.asarray(rows)
    w = table.widths[rows]
    tu = interpolate_t(lib, w[..., 0], w[..., 1])[0]
    lpa = lpa_t(tu)
    levels = []
    for h in sorted(int(v) for v in harmonics):
        ns, nu = matched_unit_harmonics(h, lib.stack)
        t0 = time.perf_counter()
        t, nG, _, t_unit = solve_table(w, lib.stack, ns, Path(partial) / f"level-{ns - 1}", workers=workers,
                                       scheduler=scheduler, chunk_size=1, unit_harmonics=nu, progress=progress, log=log)
        levels.append({"n_harmonics": nG, "unit_n_harmonics": nu - 1, "t": t, "t_unit": t_unit,
                       "label": lpa + t - t_unit.mean((1, 2)), "seconds": time.perf_counter() - t0})
        log(f"  nG {nG}: {len(rows)} supercells in {levels[-1]['seconds']:.0f} s")
    steps = []
    for a, b in zip(levels[:-1], levels[1:]):
        d_label = relative_error(b["label"], a["label"], tu)
        d_raw = relative_error(b["t"], a["t"], tu)
        steps.append({"from": a["n_harmonics"], "to": b["n_harmonics"], "label_change": _stats(d_label),
                      "raw_t_change": _stats(d_raw), "label_change_max_both": float(d_label.max()),
                      "label_change_mean_both": float(d_label.mean()),
                      "label_change_per_row": d_label.max(1).tolist()})
    at_table = None
    nG_table = table.meta.get("n_harmonics")
    top = levels[-1]
    ref_labels = table.rows(rows).labels(lpa)
    at_table = {"n_harmonics": nG_table, "vs_top_level": _stats(relative_error(ref_labels, top["label"], tu))}
    return {"rows": rows.tolist(), "levels": [{k: v for k, v in lv.items() if k not in ("t", "t_unit", "label")}
                                              for lv in levels],
            "steps": steps, "table_labels": at_table,
            "_labels": np.stack([lv["label"] for lv in levels])}


def _patch_task(args) -> tuple[str, dict]:
    """One 4 x 4 patch: its own solve (period 4 p, full problem) and its four 2 x 2 supercells and sixteen
    unit cells at the truncations matched to it."""
    name, w, stack, n_patch, n_super, n_unit = args
    res = solve_patch(w, stack, n_patch)
    sc = np.array([solve_supercell(w[2 * i:2 * i + 2, 2 * j:2 * j + 2], stack, n_super).jones[[0, 1], [0, 1]]
                   for i in range(2) for j in range(2)])
    units = unit_cells(w, stack, n_unit)
    return name, {"t_patch": res.jones[[0, 1], [0, 1]], "cross": np.abs(res.jones[[0, 1], [1, 0]]),
                  "t_super": sc, "t_unit": units, "n_harmonics": np.array([res.n_harmonics])}


def design_patches(design: Design, patches: int, seed: int) -> np.ndarray:
    """(patches, 4, 4, 2) widths (m) of 4 x 4 patches cut from ``design``, aligned to its supercells, all
    sixteen pillars present, drawn with ``seed`` (the same patches for the same seed, whatever the count
    asked: the first ``k`` of a larger draw are the draw of ``k``)."""
    aw = np.stack([design.atoms.wx, design.atoms.wy], 1)
    im = design.index_map
    rng = np.random.default_rng(seed)
    H, W = im.shape[0] // 4, im.shape[1] // 4
    ws = []
    while len(ws) < patches:
        I, J = int(rng.integers(H)), int(rng.integers(W))
        blk = im[4 * I:4 * I + 4, 4 * J:4 * J + 4].astype(np.int64)
        if (blk < len(aw)).all():
            ws.append(aw[blk])
    return np.array(ws)


def solve_patches(ws: np.ndarray, stack, n_harmonics: int, partial: Path, *, workers: int = 1,
                  scheduler: str | None = None, progress=None, log=lambda s: None) -> tuple[list, int, int]:
    """Each patch of ``ws`` solved periodically at ``n_harmonics`` (requested) with its four supercells and
    sixteen unit cells at the matched truncations (:func:`_patch_task`): ``(results in order, supercell
    request, unit request)``.  One task per patch under ``partial`` (content-keyed: resumable)."""
    ns_patch, ns_super = matched_harmonics(n_harmonics, stack, 4, 2)
    _, nu = matched_unit_harmonics(ns_super, stack)
    names = ["patch-" + content_key(np.ascontiguousarray(w, "<f8"), [ns_patch, ns_super, nu, stack.wavelength,
                                    stack.period, stack.height, stack.n_pillar, stack.n_substrate,
                                    stack.n_superstrate], __version__) for w in ws]
    jobs = {nm: (nm, w, stack, ns_patch, ns_super, nu) for nm, w in zip(names, ws)}
    done, _ = run_resumable(_patch_task, jobs, TaskFolder(partial), workers=workers, scheduler=scheduler,
                            dask_key="patches", progress=progress, log=log, unit="patch")
    return [done[nm] for nm in names], ns_super, nu


def patch_study(design: Design, lib, patches: int, seed: int, n_harmonics: int, partial: Path, *, workers: int = 1,
                scheduler: str | None = None, progress=None, log=lambda s: None, ring_levels=(), windows: bool = False,
                peds=None) -> dict:
    """Beyond the periodic 2 x 2 cell (issue #34 section 2): ``patches`` 4 x 4 patches cut from ``design``
    (aligned to its supercells, all sixteen pillars present, drawn with ``seed``), each solved as a
    periodic 4 x 4 cell (2.8 um at the paper's pitch: each supercell sees other supercells around it, as
    in the device) at ``n_harmonics`` (requested), against the mean of its four 2 x 2 supercells solved
    periodically at the matched truncation (the 2 x 2 picture every coupling model here assumes), beside
    the LPA at the unit cells' matched truncation.  Errors in units of the sixteen pillars' rms ``|t|``.
    Resumable: one task per patch under ``partial`` (content-keyed).

    ``ring_levels``: requested supercell truncations of a neighbour-ring low fidelity
    (:func:`~metadesign.library.peds.ring_couplings`: each patch and its four supercells solved again at
    matched low truncations): the report's ``ring`` section gives how far each level's ring term and their
    calibrated combination (one complex coefficient per level, both polarisations; fitted leaving each patch
    out in turn, so every patch's figure is held out) fall from the patch solve's, and the coefficients
    fitted on all patches.

    ``windows``: the overlapping-window ring (:func:`~metadesign.library.peds.window_ring`): each patch as the
    mean of its sixteen 2 x 2 windows (:func:`~metadesign.library.peds.patch_windows`), the twelve that
    straddle its supercells solved at the supercells' matched truncation (``windows_exact``: the idea
    itself) and all sixteen under the certified model ``peds`` (default: the library's; ``windows_peds``:
    what the device path uses); each how far its ring term falls from the patch solve's."""
    stack = lib.stack
    ws = design_patches(design, patches, seed)
    t0 = time.perf_counter()
    done, ns_super, nu = solve_patches(ws, stack, n_harmonics, partial, workers=workers, scheduler=scheduler,
                                       progress=progress, log=log)
    seconds = time.perf_counter() - t0
    tp = np.array([r["t_patch"] for r in done])  # (n, 2)
    tsc = np.array([r["t_super"] for r in done])  # (n, 4, 2)
    tu = np.array([r["t_unit"] for r in done])  # (n, 4, 4, 2)
    rms = np.sqrt((np.abs(tu) ** 2).mean((1, 2)))  # (n, 2)
    lpa = tu.mean((1, 2))
    two = tsc.mean(1)
    beyond = np.abs(tp - two) / rms
    ring = _ring_section(ws, tp - two, rms, stack, ring_levels, partial, workers, scheduler, progress, log) \
        if ring_levels else {}
    per_patch = {"beyond_2x2": beyond.tolist(), **ring.pop("per_patch", {})}
    if windows:
        ring.update(_window_section(ws, tsc, tp - two, rms, lib, ns_super, partial, peds, workers, scheduler,
                                    progress, log))
        per_patch.update(ring.pop("per_patch"))
    if ring:
        ring["per_patch"] = per_patch
    return {"patches": patches, "seed": seed, "n_harmonics": {"patch": int(done[0]["n_harmonics"][0]),
                                                              "supercell": ns_super - 1, "unit": nu - 1},
            "beyond_2x2": _stats(beyond), "beyond_2x2_mean_both": float(beyond.mean()),
            "beyond_2x2_p90_both": float(np.percentile(beyond, 90)),
            "lpa_vs_patch": _stats(np.abs(tp - lpa) / rms), "two_by_two_vs_lpa": _stats(np.abs(two - lpa) / rms),
            "cross_polarisation_max": float(np.array([r["cross"] for r in done]).max()),
            "solve_seconds": seconds, "workers": workers,
            "metric": "|t| differences over the sixteen pillars' rms |t| (matched unit cells), per polarisation",
            **ring}


def _ring_section(ws, target, rms, stack, levels, partial, workers, scheduler, progress, log) -> dict:
    """The neighbour-ring low fidelity at ``levels`` against the patches' own ring terms ``target`` (n, 2)."""
    t0 = time.perf_counter()
    c = ring_couplings(ws, stack, levels, Path(partial), workers=workers, scheduler=scheduler, progress=progress,
                       log=log)
    seconds = time.perf_counter() - t0
    n = len(ws)
    raw = {str(h): _stats(np.abs(target - c[k]) / rms) for k, h in enumerate(levels)}
    held = np.zeros_like(target)
    for i in range(n):  # leave one patch out: every residual is a held-out one
        keep = np.arange(n) != i
        held[i] = np.tensordot(fit_peds(c[:, keep], target[keep]), c[:, i], axes=1)
    e_held = np.abs(target - held) / rms
    coef = fit_peds(c, target)
    return {"per_patch": {"ring_low_fidelity": e_held.tolist()},
            "ring": {"levels": [int(h) for h in levels], "raw_per_level": raw, "calibrated_held_out": _stats(e_held),
                     "calibrated_held_out_mean_both": float(e_held.mean()),
                     "calibrated_held_out_p90_both": float(np.percentile(e_held, 90)),
                     "coefficients": [[float(a.real), float(a.imag)] for a in coef],
                     "seconds": seconds, "seconds_per_patch_core": seconds * max(1, workers) / max(1, n),
                     "metric": "|ring term (patch - mean of its 2 x 2 supercells), low fidelity calibrated - "
                               "the patch solve's| over the sixteen pillars' rms |t|"}}


ALIGNED = [0, 2, 8, 10]  # the supercells among a patch's sixteen windows (patch_windows), in _patch_task's order


def _window_section(ws, tsc, target, rms, lib, ns_super, partial, peds, workers, scheduler, progress, log) -> dict:
    """The overlapping-window ring of each patch against its patch solve's ``target`` (n, 2)."""
    n = len(ws)
    win = patch_windows(ws)  # (n, 16, 2, 2, 2)
    odd = [k for k in range(16) if k not in ALIGNED]
    t0 = time.perf_counter()
    log(f"  overlapping windows: {n * len(odd)} straddling windows at nG {ns_super - 1}, then all {16 * n} under "
        "the certified model ...")
    t_odd, _, _, _ = solve_table(win[:, odd].reshape(-1, 2, 2, 2), lib.stack, ns_super, Path(partial) / "windows",
                                 workers=workers, scheduler=scheduler, chunk_size=4, log=log)
    exact = (np.asarray(tsc).sum(1) + t_odd.reshape(n, len(odd), 2).sum(1)) / 16 - np.asarray(tsc).mean(1)
    t_exact = time.perf_counter() - t0
    t_p = certified_t(lib, win.reshape(-1, 2, 2, 2), Path(partial) / "peds-windows", peds, workers=workers,
                      scheduler=scheduler).reshape(n, 16, 2)
    ring_p = t_p.mean(1) - t_p[:, ALIGNED].mean(1)

    def stats(ring):
        e = np.abs(target - ring) / rms
        return {**_stats(e), "mean_both": float(e.mean()), "p90_both": float(np.percentile(e, 90))}

    def rel(z):  # (n, 2) complex -> [[re, im] per polarisation] per patch, in units of the pillars' rms |t|
        return np.stack([(z / rms).real, (z / rms).imag], -1).tolist()

    return {"per_patch": {"windows_exact": (np.abs(target - exact) / rms).tolist(),
                          "windows_peds": (np.abs(target - ring_p) / rms).tolist(),
                          "ring_term": rel(target), "ring_windows_peds": rel(ring_p)},
            "windows_exact": {**stats(exact), "seconds": t_exact, "supercell_n_harmonics": ns_super - 1},
            "windows_peds": {**stats(ring_p), "seconds": time.perf_counter() - t0 - t_exact},
            "windows_metric": "|ring term by overlapping windows (mean of the patch's sixteen 2 x 2 windows - mean "
                              "of its four supercells) - the patch solve's| over the sixteen pillars' rms |t|"}


PATCH_MODELS = {"beyond_2x2": ("every 2 x 2 model (no ring)", "C3"),
                "ring_low_fidelity": ("patch low fidelity, calibrated (held out)", "C2"),
                "windows_exact": ("overlapping windows, exact solves", "C0"),
                "windows_peds": ("overlapping windows, PEDS", "C1")}


def plot_patches(rep: dict, out: Path) -> Path:
    """The patch study at a glance: the distribution of what each way of seeing the neighbour ring leaves of
    it (per patch and polarisation, in units of the pillars' rms |t|; the goal's mean and p90 as lines),
    and the patch solve's ring term against the overlapping windows' under PEDS (real and imaginary parts)."""
    plt = pyplot()
    pp = rep.get("per_patch", {})
    two = "ring_term" in pp
    fig, axs = plt.subplots(1, 2 if two else 1, figsize=(11 if two else 6, 4.2), constrained_layout=True,
                            squeeze=False)
    ax = axs[0, 0]
    top = 0.0
    for k, (name, colour) in PATCH_MODELS.items():
        if k in pp:
            e = np.sort(np.ravel(pp[k]))
            top = max(top, e.max())
            ax.step(e, np.arange(1, len(e) + 1) / len(e), where="post", color=colour,
                    label=f"{name}: {e.mean():.3f} / {np.percentile(e, 90):.3f}")
    ax.axvline(0.05, color="0.5", ls=":", lw=1, label="goal: mean 0.05")
    ax.axvline(0.10, color="0.5", ls="--", lw=1, label="goal: p90 0.10 (where the curves cross 0.9)")
    ax.axhline(0.9, color="0.8", lw=0.8)
    ax.set(xlabel="|ring term left| / rms|t_i| (per patch and polarisation)", ylabel="fraction of patches",
           xlim=(0, 1.05 * top), ylim=(0, 1.02), title=f"{rep['patches']} patches: what each model leaves of the ring (mean / p90)")
    ax.legend(fontsize=7, loc="lower right")
    if two:
        ax = axs[0, 1]
        t, m = np.asarray(pp["ring_term"]), np.asarray(pp["ring_windows_peds"])  # (n, 2 pol, 2 re/im)
        for pol, marker in ((0, "o"), (1, "s")):
            for part, colour in ((0, "C0"), (1, "C1")):
                ax.plot(t[:, pol, part], m[:, pol, part], marker, ms=4, color=colour, alpha=0.7,
                        label=f"{'xy'[pol]}-pol, {('real', 'imaginary')[part]} part")
        lim = 1.1 * max(np.abs(t).max(), np.abs(m).max())
        ax.plot([-lim, lim], [-lim, lim], color="0.5", lw=0.8)
        ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel="ring term, patch solve (/ rms|t_i|)",
               ylabel="ring term, overlapping windows under PEDS", title="the ring, solved and modelled")
        ax.legend(fontsize=7)
    return save_figure(fig, out)


def _stats(e: np.ndarray) -> dict:
    """Mean, median, 90th percentile and max per polarisation of errors (n, 2)."""
    return {"mean": e.mean(0).tolist(), "median": np.median(e, 0).tolist(), "p90": np.percentile(e, 90, 0).tolist(),
            "max": e.max(0).tolist()}


def _by_source(source: np.ndarray, e: np.ndarray, e_lpa: np.ndarray) -> dict:
    """The held-out errors of a model and of the LPA per row source (:data:`SOURCES`)."""
    out = {}
    for s, name in enumerate(SOURCES):
        sel = source == s
        if sel.any():
            out[name] = {"n": int(sel.sum()), "model": _stats(e[sel]), "lpa": _stats(e_lpa[sel])}
    return out


def certify_coupling(table: SupercellTable, lib, sizes=(250, 500, 1000), cfg: CouplingConfig = CouplingConfig(),
                     steps: int = 4000, seed: int = 0, goal=(0.05, 0.1), weight_decay: float = 1e-3,
                     reference: SupercellTable | None = None, log=lambda s: None) -> tuple[object, dict]:
    """Fit the coupling model on the first ``n`` fitting rows of the table for each ``n`` in ``sizes``
    (a learning curve) and certify each fit on every held-out row of ``reference`` (default: the table's
    own; never fitted, never used to pick a step); returns the model of the largest size and the report.
    A table at another truncation than the library's is fitted on its labels (LPA + its coupling:
    :meth:`SupercellTable.labels`); the reference's labels are its own.  Error: ``|t - t_RCWA| / rms_i |t_i|``."""
    import torch

    torch.set_num_threads(1)
    ref = table if reference is None else reference
    fit_rows = np.flatnonzero(~table.test)
    test_rows = np.flatnonzero(ref.test)
    if not len(test_rows):
        raise ValueError("the reference table has no held-out rows")
    sizes = sorted({min(int(n), len(fit_rows)) for n in sizes})
    w_fit = table.widths[fit_rows]
    t_fit, _ = table.rows(fit_rows).lpa_labels(lib)
    w_te = ref.widths[test_rows]
    t_te, tu_te = ref.rows(test_rows).lpa_labels(lib)
    e_lpa = relative_error(lpa_t(tu_te), t_te, tu_te)
    curve, model = [], None
    for n in sizes:
        t0 = time.perf_counter()
        log(f"  fitting on {n} supercells ...")
        model, info = fit_coupling(lib, w_fit[:n], t_fit[:n], cfg, steps=steps, seed=seed,
                                   weight_decay=weight_decay, log=log)
        e = relative_error(coupling_t(model, w_te, tu_te), t_te, tu_te)
        curve.append({"supercells": n, "held_out": _stats(e), "fit_seconds": time.perf_counter() - t0,
                      "best_validation_error": info["best_validation_error"], "_e": e, "_info": info})
        log(f"    held-out |dt|/rms|t_i| mean {e.mean():.4f} (x {e[:, 0].mean():.4f}, y {e[:, 1].mean():.4f}), "
            f"p90 {np.percentile(e, 90):.4f}; LPA {e_lpa.mean():.4f}")
    last = curve[-1]
    e = last.pop("_e")
    info = last.pop("_info")
    for c in curve:
        c.pop("_e", None), c.pop("_info", None)
    by_source = _by_source(ref.source[test_rows], e, e_lpa)
    m, p90 = float(e.mean()), float(np.percentile(e, 90))
    report = {
        "metric": "|t_model - t_RCWA| / rms_i |t_i| (the four pillars' rms library |t|), per polarisation",
        "held_out_supercells": int(len(test_rows)), "fitted_supercells": int(sizes[-1]),
        "model": _stats(e), "lpa": _stats(e_lpa), "by_source": by_source,
        "goal": {"mean": goal[0], "p90": goal[1]},
        "passed": bool(m <= goal[0] and p90 <= goal[1]), "mean_both": m, "p90_both": p90,
        "lpa_mean_both": float(e_lpa.mean()), "lpa_p90_both": float(np.percentile(e_lpa, 90)),
        "learning_curve": curve, "fit": {k: v for k, v in info.items() if k != "history"},
        "table": {"supercells": len(table), "n_harmonics": table.meta.get("n_harmonics"),
                  "seed": table.meta.get("seed")},
        "reference": None if reference is None else {"supercells": len(ref), "n_harmonics": ref.meta.get("n_harmonics"),
                                                     "seed": ref.meta.get("seed")},
        "_e": e, "_e_lpa": e_lpa,
    }
    return model, report


def plot_coupling(rep: dict, out: Path) -> Path:
    """Learning curve (held-out mean and p90 vs supercells fitted, the LPA and the goal as lines) and the
    held-out error distributions of the model and the LPA."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    c = rep["learning_curve"]
    n = [r["supercells"] for r in c]
    for k, ls in (("mean", "o-"), ("p90", "s--")):
        axs[0].plot(n, [np.mean(r["held_out"][k]) for r in c], ls, color="C0", label=f"model, {k}")
        axs[0].axhline(np.mean(rep["lpa"][k]), color="C3", ls=ls[1:], label=f"LPA, {k}")
        axs[0].axhline(rep["goal"][k], color="0.5", ls=":", lw=1)
        axs[0].annotate(f"goal {k} {rep['goal'][k]:g}", (n[-1], rep["goal"][k]), fontsize=8, color="0.4",
                        ha="right", va="bottom")
    axs[0].set(xscale="log", yscale="log", xlabel="supercells fitted (RCWA solves)",
               ylabel="held-out |t - t_RCWA| / rms|t_i|",
               title=f"learning curve ({rep['held_out_supercells']} held-out supercells)")
    axs[0].set_xticks(n, [str(v) for v in n])
    axs[0].set_xticks([], minor=True)  # the log axis's own minor labels would overprint the sizes
    axs[0].legend(fontsize=8)
    e, el = rep["_e"].ravel(), rep["_e_lpa"].ravel()
    _error_histogram(axs[1], e, el, "coupling model", max(el.max(), e.max()))
    return save_figure(fig, out)


def _error_histogram(ax, e: np.ndarray, e_lpa: np.ndarray, name: str, top: float) -> None:
    """The held-out error distributions of a model and of the LPA on one axis (bins up to ``top``)."""
    bins = np.linspace(0, top, 40)
    ax.hist(e_lpa, bins, alpha=0.6, color="C3", label=f"LPA (mean {e_lpa.mean():.3f})")
    ax.hist(e, bins, alpha=0.6, color="C0", label=f"{name} (mean {e.mean():.3f})")
    ax.set(xlabel="|t - t_RCWA| / rms|t_i| (both polarisations)", ylabel="held-out supercells x pol",
           title="held-out error")
    ax.legend(fontsize=8)


def certify_peds(table: SupercellTable, lib, harmonics, sizes, partial: Path, *, workers: int = 1,
                 scheduler: str | None = None, goal=(0.05, 0.1), probe_rows: int = 4, probe_label: bool = True,
                 select: bool = False, progress=None, log=lambda s: None) -> tuple[object, dict]:
    """Calibrate the PEDS surrogate (:mod:`metadesign.library.peds`) on the table's converged labels: every row
    solved at the low truncations ``harmonics`` (resumable under ``partial``), the coefficients fitted on the
    first ``n`` fitting rows for each ``n`` of ``sizes`` (a learning curve; each fit certified on every
    held-out row, never fitted), each level alone (uncalibrated) beside it; returns the model of the largest
    size and the report (by source, cost per supercell and per million).  ``select``: the levels are
    candidates, and the model uses the subset that cross-validation on the fitting rows picks
    (:func:`select_levels`; the held-out rows play no part in the choice)."""
    harmonics = sorted({int(h) for h in harmonics})
    fit_rows, test_rows = np.flatnonzero(~table.test), np.flatnonzero(table.test)
    if not len(test_rows) or not len(fit_rows):
        raise ValueError("certification needs fitting and held-out rows")
    labels, tu = table.lpa_labels(lib)
    lpa = lpa_t(tu)
    log(f"PEDS levels nG {harmonics} on {len(table)} supercells ({len(test_rows)} held out)")
    c, nGs = low_fidelity_couplings(table.widths, lib.stack, harmonics, partial, workers=workers,
                                          scheduler=scheduler, progress=progress, log=log)
    te = test_rows
    e_lpa = relative_error(lpa[te], labels[te], tu[te])
    probe = table.widths[test_rows[:probe_rows]]  # the cost timed here, whatever the chunks held already
    levels = [{"requested": h, "n_harmonics": g, "seconds_per_supercell_core": _solve_seconds(probe, lib.stack, h),
               "alone": _stats(relative_error(lpa[te] + c[k][te], labels[te], tu[te]))}
              for k, (h, g) in enumerate(zip(harmonics, nGs))]
    label_h = table.meta.get("n_harmonics")
    label_cost = _solve_seconds(probe[:2], lib.stack, label_h + 1, units=False) if label_h and probe_label else None
    target = labels - lpa
    selection = None
    if select and len(harmonics) > 1:
        n_model = min(max(int(v) for v in sizes), len(fit_rows))  # the rows the model is fitted on, no more
        selection = select_levels(c, target, fit_rows[:n_model], tu, [float(g) ** 3 for g in nGs])
        keep = selection["chosen"]
        log("  levels chosen by cross-validation on the fitting rows: nG "
            + ", ".join(str(levels[k]["n_harmonics"]) for k in keep))
        for k, lv in enumerate(levels):
            lv["chosen"] = k in keep
        c, harmonics = c[keep], [harmonics[k] for k in keep]
    chosen = [lv for lv in levels if lv.get("chosen", True)]
    curve, coef = [], None
    for n in sorted({min(int(v), len(fit_rows)) for v in sizes}):
        rows = fit_rows[:n]
        coef = fit_peds(c[:, rows], target[rows])
        e = relative_error(peds_t(coef, c[:, te], lpa[te]), labels[te], tu[te])
        curve.append({"supercells": n, "held_out": _stats(e), "coef": [[a.real, a.imag] for a in coef]})
        log(f"  calibrated on {n}: held-out mean {e.mean():.4f}, p90 {np.percentile(e, 90):.4f}")
    used = fit_rows[:curve[-1]["supercells"]]
    e_fit = relative_error(peds_t(coef, c[:, used], lpa[used]), labels[used], tu[used])
    by_source = _by_source(table.source[test_rows], e, e_lpa)
    m, p90 = float(e.mean()), float(np.percentile(e, 90))
    per_sc = sum(lv["seconds_per_supercell_core"] for lv in chosen)
    report = {
        "metric": "|t_model - t_RCWA| / rms_i |t_i| (the four pillars' rms library |t|), per polarisation",
        "structure": "t = mean_i t_lib(w_i) + sum_k a_k [t_super(nG_k) - mean_i t_unit,i(nG_k)], a_k complex, "
                     "shared by both polarisations",
        "held_out_supercells": int(len(test_rows)), "fitted_supercells": curve[-1]["supercells"],
        "model": _stats(e), "fitted_rows": _stats(e_fit), "lpa": _stats(e_lpa), "by_source": by_source,
        "levels": levels, "selection": selection, "goal": {"mean": goal[0], "p90": goal[1]},
        "passed": bool(m <= goal[0] and p90 <= goal[1]), "mean_both": m, "p90_both": p90,
        "lpa_mean_both": float(e_lpa.mean()), "lpa_p90_both": float(np.percentile(e_lpa, 90)),
        "learning_curve": curve,
        "cost": {"seconds_per_supercell_core": per_sc, "core_hours_per_million": per_sc * 1e6 / 3600,
                 "label_seconds_per_supercell_core": label_cost,
                 "label_n_harmonics": label_h, "probe_supercells": int(len(probe))},
        "table": {"supercells": len(table), "n_harmonics": table.meta.get("n_harmonics"), "seed": table.meta.get("seed")},
        "_e": e, "_e_lpa": e_lpa,
    }
    return PedsModel(tuple(harmonics), tuple(complex(a) for a in coef), lib.identity), report


def select_levels(c: np.ndarray, target: np.ndarray, rows: np.ndarray, tu: np.ndarray, cost, folds: int = 5,
                  tolerance: float = 0.02, seed: int = 0) -> dict:
    """Every non-empty subset of the levels ``c`` (K, n, 2) scored by ``folds``-fold cross-validation of the
    calibration on ``rows`` only (mean error of the out-of-fold predictions against ``target`` = labels -
    LPA); the chosen subset is the cheapest (sum of the levels' ``cost``: a fixed proxy such as nG^3, so the
    choice does not depend on the machine's load) within ``tolerance`` (relative) of the best mean.  Returns
    ``{"chosen": level indices, "subsets": [{levels, cv mean, cv p90, cost}]}``."""
    parts = np.array_split(np.random.default_rng(seed).permutation(rows), folds)
    out = []
    for k in range(1, len(c) + 1):
        for sub in combinations(range(len(c)), k):
            cs = c[list(sub)]
            errs = []
            for f in range(folds):
                fit = np.concatenate([parts[g] for g in range(folds) if g != f])
                a = fit_peds(cs[:, fit], target[fit])
                va = parts[f]
                errs.append(relative_error(np.tensordot(a, cs[:, va], axes=1), target[va], tu[va]))
            e = np.concatenate(errs)
            out.append({"levels": list(sub), "cv_mean": float(e.mean()), "cv_p90": float(np.percentile(e, 90)),
                        "cost": float(sum(cost[j] for j in sub))})
    best = min(r["cv_mean"] for r in out)
    pick = min((r for r in out if r["cv_mean"] <= best * (1 + tolerance) + 1e-12),
               key=lambda r: (r["cost"], r["cv_mean"]))
    return {"chosen": pick["levels"], "folds": folds, "tolerance": tolerance, "rows": int(len(rows)),
            "cost": "sum of nG^3 of the levels", "subsets": out}


def _solve_seconds(widths: np.ndarray, stack, harmonics: int, units: bool = True) -> float:
    """Seconds per supercell on this core of a fresh solve at ``harmonics`` (requested), with its matched unit
    cells when ``units`` (a PEDS level; a converged label solves none), no cache."""
    ns, nu = matched_unit_harmonics(int(harmonics), stack)
    t0 = time.perf_counter()
    for w in widths:
        solve_supercell(w, stack, ns)
        if units:
            unit_cells(w[None], stack, nu)
    return (time.perf_counter() - t0) / max(1, len(widths))


def plot_peds(rep: dict, out: Path, networks: dict | None = None) -> Path:
    """Learning curve of the calibrated surrogate (held-out mean and p90 vs labels), each level alone, the LPA,
    the goal and (``networks``: name -> a coupling card's certification) the networks' curves; the held-out
    error distributions."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 2, figsize=(12, 5.6), constrained_layout=True)
    c = rep["learning_curve"]
    n = [r["supercells"] for r in c]
    ax = axs[0]
    for k, ls in (("mean", "o-"), ("p90", "s--")):
        ax.plot(n, [np.mean(r["held_out"][k]) for r in c], ls, color="C0", label=f"PEDS ({sum(lv.get('chosen', True) for lv in rep['levels'])} "
                f"levels, a coefficient each), {k}")
        ax.axhline(np.mean(rep["lpa"][k]), color="C3", ls=ls[1:], lw=1, label=f"LPA, {k}")
        ax.axhline(rep["goal"][k], color="0.5", ls=":", lw=1)
        ax.annotate(f"goal {k} {rep['goal'][k]:g}", (n[0], rep["goal"][k]), fontsize=8, color="0.4", va="bottom")
    for j, lv in enumerate(rep["levels"]):
        ax.axhline(np.mean(lv["alone"]["mean"]), color=("C1", "C5", "C7", "C8")[j % 4], ls="-.", lw=1,
                   label=f"nG {lv['n_harmonics']} alone, mean")
    for j, (name, cert) in enumerate((networks or {}).items()):
        cc = cert["learning_curve"]
        ax.plot([r["supercells"] for r in cc], [np.mean(r["held_out"]["mean"]) for r in cc], "^-",
                color=("C2", "C4", "C6", "C9")[j % 4],
                label=f"network alone ({name}), mean")
    ax.set(xscale="log", yscale="log", xlabel="labels fitted (RCWA solves)",
           ylabel="held-out |t - t_RCWA| / rms|t_i|",
           title=f"supercell surrogates ({rep['held_out_supercells']} held-out supercells)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    e, el = rep["_e"].ravel(), rep["_e_lpa"].ravel()
    _error_histogram(axs[1], e, el, "PEDS", np.percentile(el, 99))
    return save_figure(fig, out)

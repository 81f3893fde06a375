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

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..config import ConfigError, Param, Section, load_toml, parse
from ..design.recipe import load_design_recipe
from ..design.store import Design, design_file, load_design, run_design
from ..execution import SERIAL, Execution, scratch_path
from ..library.locate import file_sha256
from ..library.store import load_library
from ..library.supercells import (
    SupercellTable,
    matched_unit_harmonics,
    remove_partial,
    save_table,
    solve_table,
)
from ..outputs import Need, temporary

__all__ = ["SOURCES", "SupercellRecipe", "load_supercell_recipe", "design_source", "RowDraw", "sample_rows",
           "pool_widths", "supercell_need", "build_table"]



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


@dataclass(frozen=True)
class RowDraw:
    """How a table's rows are drawn: from ``seed``, the sources' ``mix`` (fractions of :data:`SOURCES`), the
    jittered atoms' ``jitter`` (m), every ``test_every``-th row held out."""

    seed: int
    mix: tuple
    jitter: float
    test_every: int


def sample_rows(n: int, draw: RowDraw, main: tuple, extra: tuple | None,
                w_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(widths (n, 2, 2, 2) m, source (n,), test (n,))`` drawn as ``draw`` says; ``main``/``extra`` = (atom
    widths (m, 2), index map [iy, ix] with the no-pillar sentinel outside the atom range)."""
    seed, mix, jitter, test_every = draw.seed, draw.mix, draw.jitter, draw.test_every
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
    draw = RowDraw(recipe.seed + POOL_SEED_OFFSET, recipe.mix, recipe.jitter, recipe.test_every)
    return sample_rows(n, draw, main, extra, w_range)[0]


def supercell_need(n: int, n_harmonics: int, workers: int) -> Need:
    """A supercell table's peak: the rows on disk twice (chunks + the table) and, per worker, the RCWA
    solve's matrices (about 30 complex (2 nG)^2 arrays)."""
    return Need(disk=2 * n * 256.0, memory=workers * 30 * 16.0 * (2 * n_harmonics) ** 2,
                what="fewer -j workers or a lower table.n_harmonics")


def build_table(recipe: SupercellRecipe, output: Path, supercells: int | None = None,
                run: Execution = SERIAL) -> dict:
    """Solve (or resume, or extend) the table of ``recipe`` (``supercells`` rows, default the recipe's) into
    ``output`` (written atomically at the end; the solved chunks stay in ``<output>.partial/`` until then), on
    ``run``'s workers or scheduler (``run.stop_after``: stop after that many chunks, for tests)."""
    workers, log = run.workers, run.log
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
    widths, source, test = sample_rows(n, RowDraw(recipe.seed, recipe.mix, recipe.jitter, recipe.test_every),
                                       main, extra, w_range)
    partial = scratch_path(output)
    log(f"solving {n} supercells (nG {ns - 1}, matched to " + ("the library's" if unit is None else
        "unit cells solved at") + f" {nu - 1}) -> {output}")
    t, nG, seconds, t_unit = solve_table(widths, stack, ns, partial, workers=workers, scheduler=run.scheduler,
                                         chunk_size=recipe.chunk, unit_harmonics=unit, progress=run.progress, log=log,
                                         _stop_after_chunks=run.stop_after)
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

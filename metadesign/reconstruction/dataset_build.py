"""Stage 6a, the dataset build: seeded, sharded datasets of 8-PSF frames from scintillated beacons
through the as-fabricated metasurface, made on a local process pool or a Dask cluster, resumable after
SIGKILL (the recipe: :mod:`.dataset_recipe`; the store written: :mod:`.dataset_store`).

A sample is made by :func:`make_sample` (what the recipe decides of it: :func:`~.dataset_recipe.sample_seed`,
:func:`~.dataset_recipe.sample_rytov`); big arrays are sharded (one shard file per block of ``shard_size``
samples, one inner chunk per sample, so a reader decodes only the sample it needs).  A shard is finished
when its marker ``OUT/.shards/NNNNNN`` exists (written atomically after its arrays); a re-run continues from
the unfinished shards; ``complete`` is set in the attributes at the end.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..execution import SERIAL, Execution
from ..design.recipe import load_design_recipe
from ..design.store import load_design, run_design
from ..outputs import Need, product
from ..layouts.make import make_layout
from ..tasks import TaskFolder, content_key, file_key, run_resumable
from ..parallel import dask_client
from ..paths import resolve_against
from ..optics.dm import DeformableMirror, phase_of
from ..optics.propagation import cexp
from ..sensing.device import Device, ReceiverCrop
from ..turbulence.system import build_system
from ..turbulence.chain import BeaconChain
from ..turbulence.path import check_sampling, solve_path
from ..turbulence.scenario import load_scenario
from ..validation import ValidationError
from .dataset_recipe import (DatasetRecipe, expected_sizes, received_crop, sample_loop_gain, sample_rytov,
                             sample_seed, split_labels)
from .losses import unwrap_ls
from .dataset_store import (DATASET_FORMAT, consolidate, create_store, mark_complete, open_dataset, open_store,
                            read_attrs, read_store_pupil, write_store_pupil)

__all__ = ["build_dataset", "ShardContext", "make_sample", "measured_rytov", "normalise_psf", "make_shard",
           "shard_folder", "shard_name", "run_shards", "ensure_layout", "execution_of", "recipe_parts"]

#: the execution keywords long jobs took before :class:`~metadesign.execution.Execution` (still accepted)
LEGACY_EXECUTION = ("workers", "scheduler", "client", "progress", "log")


def execution_of(run: Execution, legacy: dict, what: str) -> Execution:
    """``run`` with the execution keywords of the older signatures (``workers=``, ``scheduler=``, ``client=``,
    ``progress=``, ``log=``) that callers still pass; any other keyword is Python's TypeError."""
    bad = [k for k in legacy if k not in LEGACY_EXECUTION]
    if bad:
        raise TypeError(f"{what}() got an unexpected keyword argument {bad[0]!r}")
    return run.replace(**legacy) if legacy else run


@dataclass
class ShardContext:
    """Everything a worker needs to make a shard (no layout: the device is its coarse pupil)."""

    pupil: object  # CoarsePupil
    sensing: object  # SensingRecipe (tensor_size of the recipe)
    scenario: object  # Scenario
    aperture: float  # metasurface aperture (m)
    out: str
    root_seed: int
    n: int
    shard_size: int
    rytov_range: tuple
    rytov_values: tuple | None
    closed_loop: dict | None = None  # the recipe's [closed_loop] (None or {}: every beacon open loop)
    split: np.ndarray | None = None  # (n,) the split labels ([closed_loop] draws training samples only)
    _chain: object = None
    _loop: tuple | None = None
    kind = "shard"

    def make(self, shard: int) -> dict:
        return make_shard(self, shard)

    def chain(self):
        if self._chain is None:
            self._chain = BeaconChain(self.pupil, self.sensing, self.scenario, self.aperture)
        return self._chain

    def loop_parts(self) -> tuple:
        """(device fed from the received crop, the [closed_loop] mirror, the aperture on the crop): the closed
        loop's path (:mod:`metadesign.studies.loop` renders its frames the same way)."""
        if self._loop is None:
            tb = self.chain().turbulence
            c0, a = received_crop(tb.sc)
            crop = ReceiverCrop.of_scenario(tb.sc, c0, a)
            cl = self.closed_loop
            dm = DeformableMirror.for_crop(crop, n_act=cl["actuators"], coupling=cl["coupling"],
                                           regularisation=cl["regularisation"])
            self._loop = (Device(self.pupil, self.sensing.sensor, crop, camera=self.sensing.camera), dm,
                          tb.aperture[c0:c0 + a, c0:c0 + a])
        return self._loop

    def loop_gain(self, i: int) -> float:
        label = int(self.split[i]) if self.split is not None else 2
        return sample_loop_gain(self.root_seed, i, label, self.closed_loop)


def make_sample(ctx: ShardContext, i: int) -> dict:
    """Sample ``i`` of the dataset: arrays as stored, and the time spent per step."""
    t0 = time.perf_counter()
    chain = ctx.chain()
    seed = sample_seed(ctx.root_seed, i)
    rytov = sample_rytov(ctx.root_seed, i, ctx.rytov_range, ctx.rytov_values)
    gain = ctx.loop_gain(i)
    s = chain.sample(seed, rytov, render=gain == 0)  # a residual is rendered once, after its mirror
    t1 = time.perf_counter()
    c0, a = received_crop(chain.turbulence.sc)
    rec = s.received[c0:c0 + a, c0:c0 + a]
    tensor, mirror = s.tensor, np.zeros(rec.shape, np.float32)
    if gain > 0:  # a closed loop's residual: the mirror holds gain x its best fit of this beacon
        device, dm, mask = ctx.loop_parts()
        mirror = (gain * converged_mirror(dm, rec, mask) * mask).astype(np.float32)
        rec = rec * cexp(-mirror)
        tensor = device.render(device.pupil_field(rec)).psfs
    psf, power = normalise_psf(tensor)
    t2 = time.perf_counter()
    return {"psf": psf, "psf_power": power, "received": rec.astype(np.complex64), "rytov": rytov, "loop_gain": gain,
            "mirror_phase": mirror,
            "rytov_measured": measured_rytov(rec, chain.turbulence.aperture[c0:c0 + a, c0:c0 + a]), "seed": seed,
            "timings": {**s.timings, "other": (t2 - t1) + (t1 - t0) - sum(s.timings.values())}}


def converged_mirror(dm, field: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The mirror's phase a converged closed loop holds for ``field``: its least-squares fit of the field's
    least-squares unwrapped phase (:func:`~.losses.unwrap_ls`).  Not the loop's iterated fit of the wrapped
    phase (:func:`metadesign.optics.dm.fitted_oracle`): at Rytov 0.5 a tilt of several radians wraps across
    the aperture and that fit stalls (measured on sensing/dataset-demo: its surface 1.5 rad rms on beacons
    of 3 rad, leaving them as they were, where this one leaves 0.1-0.7 rad)."""
    return dm.surface(dm.fit(unwrap_ls(phase_of(field * mask)[None], mask)[0], mask))


def measured_rytov(received: np.ndarray, aperture: np.ndarray) -> float:
    """A sample's own Rytov number: the variance of the log-amplitude of its received field over the
    receiver aperture (its crop)."""
    return float(np.var(np.log(np.maximum(np.abs(received[aperture]), 1e-30))))


def normalise_psf(tensor: np.ndarray) -> tuple[np.ndarray, float]:
    """The network's input normalisation: the 8 channels sum to 8 (each ~1); returns (psf, raw total)."""
    power = float(tensor.sum())
    return ((tensor * (8.0 / power)).astype(np.float32) if power > 0 else tensor.astype(np.float32)), power


def shard_folder(out: Path, kind: str = "shards") -> TaskFolder:
    """The task folder of a store's shards (``OUT/.shards/NNNNNN.json``: a shard's marker, written once its
    arrays are in the store)."""
    return TaskFolder(Path(out) / f".{kind}")


def shard_name(shard: int) -> str:
    return f"{shard:06d}"


def make_shard(ctx: ShardContext, shard: int) -> dict:
    """Compute shard ``shard`` and write it into the store (its marker follows: :func:`run_shards`).

    BLAS runs on one thread here whatever the process was started with: a multi-threaded complex matrix
    product sums in another order (~1e-6 relative), and the same seed must give the same bytes."""
    import zarr
    from threadpoolctl import threadpool_limits

    i0 = shard * ctx.shard_size
    i1 = min(ctx.n, i0 + ctx.shard_size)
    with threadpool_limits(limits=1):
        rows = [make_sample(ctx, i) for i in range(i0, i1)]
    t0 = time.perf_counter()
    g = open_store(ctx.out, "r+")
    g["psf"][i0:i1] = np.stack([r["psf"] for r in rows])
    g["received"][i0:i1] = np.stack([r["received"] for r in rows])
    if "mirror_phase" in g:  # a store with [closed_loop] samples
        g["mirror_phase"][i0:i1] = np.stack([r["mirror_phase"] for r in rows])
    for k, dt in (("psf_power", np.float32), ("rytov", np.float32), ("rytov_measured", np.float32),
                  ("seed", np.int64), ("loop_gain", np.float32)):
        if k in g:  # loop_gain: a store with [closed_loop] samples only
            g[k][i0:i1] = np.array([r[k] for r in rows], dt)
    t_store = time.perf_counter() - t0
    tim = {k: float(sum(r["timings"][k] for r in rows)) for k in rows[0]["timings"]}
    tim["storage"] = t_store
    return {"shard": shard, "samples": i1 - i0, "timings": tim}


# ------------------------------------------------------------ the builder


def ensure_layout(recipe: DatasetRecipe, log: Callable[[str], None]) -> Path:
    """The recipe's layout; built from its design recipe (design + OASIS + exact verify) if missing."""
    if recipe.layout is not None and recipe.layout.exists():
        return recipe.layout
    if recipe.design is None:
        raise ValidationError(f"dataset.layout: {recipe.layout}: no such layout (give dataset.design to build it)")

    dr = load_design_recipe(recipe.design)
    out = recipe.layout.parent if recipe.layout is not None else dr.default_output()
    target = recipe.layout or out / "layout.oas"
    log(f"building the layout {target} from {recipe.design} (design, OASIS, exact read-back)")
    with product(out, "design", {"dataset.design": recipe.design, "design.library": dr.library_path},
                 also=(target, target.with_name(target.name + ".json"))):
        _, folder = run_design(dr, out)
        made = make_layout(load_design(folder), target, drc=False)
    if not made.exact:
        raise ValidationError(f"{target}: the layout read back differs from the design: {made.verify['problems'][:2]}")
    return target


def _device_pupil(fab, sensing, pert, store: Path, layout_sha: str, progress=None):
    """The device's coarse pupil, kept in the dataset's store as the zarr group ``device`` (keyed by
    layout, library, perturbation, sensor: a resumed build reuses it)."""
    key = {"layout_sha256": layout_sha, "library_sha256": fab.lib.identity, "perturbation": pert.to_dict(),
           "distance_m": sensing.sensor.distance, "pupil_grid": sensing.pupil_grid}
    if fab.fab_lib is not None:
        key["fab_library_sha256"] = fab.fab_lib.identity
    try:
        cp, stored = read_store_pupil(store)
        if stored == key:
            return cp
    except ValidationError:
        pass
    cp = fab.pupil(sensing.sensor.distance, sensing.pupil_grid, pert, progress)
    write_store_pupil(store, cp, key)
    return cp



def _make_shard(ctx, i: int) -> tuple[str, dict]:
    return shard_name(i), ctx.make(i)


def run_shards(ctx, shards: dict[str, int], folder: TaskFolder, run: Execution = SERIAL, weight=lambda name: 1):
    """``ctx.make(i)`` for every shard not yet marked done in ``folder`` (a :class:`ShardContext` or the
    operators' context), on the resumable engine (:func:`metadesign.tasks.run_resumable`) under ``run``: the
    context goes to each worker once; returns ``(results by name, names computed now)``."""
    return run.run(_make_shard, shards, folder, store="marker", shared=ctx,
                   dask_key=f"metadesign-{ctx.kind}-{ctx.out}", weight=weight, unit="sample")


def build_dataset(recipe: DatasetRecipe, out: Path | None = None, overwrite: bool = False,
                  run: Execution = SERIAL, **legacy) -> dict:
    """Build (or resume) the dataset of ``recipe`` into ``out``; returns a report.

    ``run``: a local pool of ``run.workers`` spawned processes, or ``run.scheduler`` (the address of a running
    Dask scheduler) or ``run.client`` (a ``dask.distributed.Client``); its progress and log.  The older
    keywords ``workers=``, ``scheduler=``, ``client=``, ``progress=``, ``log=`` are still accepted."""
    run = execution_of(run, legacy, "build_dataset")
    out = Path(out or recipe.default_output())
    if out.exists() and not out.is_dir():
        raise ValidationError(f"-o/--output {out}: exists and is not a folder")
    f = recipe.fabrication
    base = recipe.source.parent if recipe.source else Path.cwd()  # what the recipe's paths are relative to
    need = None
    if overwrite or not (out / "zarr.json").exists():  # a new store (a resumed one holds its arrays already)
        s, a = expected_sizes(recipe)  # the arrays uncompressed: an upper bound
        need = Need(disk=recipe.samples * (8 * s * s * 4 + a * a * 8 + 64),
                    what="fewer dataset.samples, a smaller tensor_size or another output")
    with product(out, "dataset", {"dataset.layout": recipe.layout, "dataset.design": recipe.design,
                                  "dataset.sensor": recipe.sensor, "dataset.turbulence": recipe.turbulence,
                                  "the recipe": recipe.source,
                                  "fabrication.coupling_model": resolve_against(base, f["coupling_model"]),
                                  "fabrication.fab_library": resolve_against(base, f["fab_library"])}, need=need):
        own = None
        if run.scheduler is not None and run.client is None:  # an unreachable scheduler fails before anything is written
            own = dask_client(run.scheduler)
            run = run.replace(client=own)
        try:
            return _build_dataset(recipe, out, overwrite, run)
        finally:
            if own is not None:
                own.close()


def recipe_parts(recipe: DatasetRecipe, system, layout_sha: str) -> dict:
    """What a dataset's recipe hash covers (``content_key`` of it): the recipe, the sensor, the pupil grid, the
    scenario, the layout's and library's sha256, the perturbation (and the fab library, coupling model and
    polarisation camera when there are): the dataset build's, and the export's check that a committed
    recipe is the one a model card names."""
    fab, sensing, pert = system.device, system.sensing, system.perturbation
    parts = {"format": DATASET_FORMAT, "recipe": recipe.raw, "sensor": sensing.sensor.to_dict(),
             "pupil_grid": sensing.pupil_grid, "scenario": system.scenario.to_dict(), "layout_sha256": layout_sha,
             "library_sha256": fab.lib.identity, "perturbation": pert.to_dict()}
    if fab.fab_lib is not None:
        parts["fab_library_sha256"] = fab.fab_lib.identity
    if fab.coupling_card is not None:  # absent for the LPA: those datasets keep their hash
        parts["coupling_model_sha256"] = fab.coupling_card["weights_sha256"]
    if sensing.camera is not None:  # a polarisation camera's frames (absent for the ideal camera: same hash)
        parts["camera"] = sensing.camera.to_dict()
    return parts


def _build_dataset(recipe: DatasetRecipe, out: Path, overwrite: bool, run: Execution) -> dict:
    log = run.log
    existing = read_attrs(out) if (out / "zarr.json").exists() else None  # (a foreign folder: refused already)
    scenario = load_scenario(recipe.turbulence)
    for r in ([*recipe.rytov_values] if recipe.rytov_values else list(recipe.rytov_range)):
        sc = replace(scenario, rytov=r)
        rep = check_sampling(sc, solve_path(sc))
        if not rep.ok:
            raise ValidationError(f"dataset: Rytov {r:g}: infeasible turbulence sampling: {rep.failures[0]}")
    layout = ensure_layout(recipe, log)
    layout_sha = file_key(layout)
    system = build_system(layout, recipe.sensor, scenario, recipe.fabrication,
                          recipe.source.parent if recipe.source else Path.cwd(), recipe.tensor_size)
    fab, sensing, pert = system.device, system.sensing, system.perturbation
    parts = recipe_parts(recipe, system, layout_sha)
    rhash = content_key(parts)  # what shapes the dataset's bytes (sha256 of json.dumps(parts, sort_keys=True))
    if existing is not None and existing.get("recipe_hash") != rhash:
        if not overwrite:
            raise ValidationError(f"{out}: holds a dataset built from a different recipe (or device); "
                                  "use --overwrite to replace it, or -o for another folder")
        log(f"--overwrite: removing the dataset in {out}")
        shutil.rmtree(out)
        existing = None
    n, shard = recipe.samples, recipe.shard_size
    n_shards = (n + shard - 1) // shard
    t_start = time.perf_counter()
    c0, a = received_crop(scenario)
    out.mkdir(exist_ok=True)
    if existing is None:
        attrs = {
            "format": DATASET_FORMAT, "version": __version__, "complete": False, "recipe_hash": rhash,
            "recipe_key": recipe.declared_key(), "name": recipe.name, "samples": n, "shard_size": shard, "n_shards": n_shards,
            "tensor_size": recipe.tensor_size, "root_seed": recipe.seed, "split_fractions": list(recipe.split),
            "rytov": {"range": list(recipe.rytov_range), "values": list(recipe.rytov_values or []) or None},
            "provenance": {**parts, "layout": str(layout), "design": fab.layout.provenance.get("design"),
                           "channels": fab.layout.provenance.get("channels")},
            "received_crop": {"start": c0, "size": a, "n_grid": scenario.n_grid, "dx_m": scenario.dx,
                              "centring": "FFT-centred grid: x = (i - n/2) dx; crop rows/cols start..start+size"},
            "normalisation": "psf: each sample's 8 channels sum to 8 (psf_power holds the raw total)",
            "seeds": "screens: Turbulence.at_rytov(rytov).screens(seed); seed_i = SeedSequence(root, "
                     "spawn_key=(0, i)) & (2^63-1); Rytov from SeedSequence(root, spawn_key=(1, i))",
            "split_labels": {"0": "train", "1": "val", "2": "test"},
        }
        if recipe.closed_loop:
            attrs["closed_loop"] = {**recipe.closed_loop, "gain": list(recipe.closed_loop["gain"]),
                                    "what": "loop_gain > 0: the received field times cexp(-mirror_phase), "
                                            "mirror_phase = loop_gain x converged_mirror(mirror, field) on the "
                                            "aperture (rad), rendered from the crop; training and validation "
                                            "splits only; draws SeedSequence(root, spawn_key=(3, i))"}
        create_store(out, attrs, split_labels(recipe.seed, n, recipe.split))
    cp = _device_pupil(fab, sensing, pert, out, layout_sha)  # after the store (mode "w")
    folder = shard_folder(out)
    shards = {shard_name(i): i for i in range(n_shards)}
    size = {shard_name(i): min(n, (i + 1) * shard) - i * shard for i in range(n_shards)}
    done = {nm for nm in shards if folder.marked(nm) is not None}
    ctx = ShardContext(cp, sensing, scenario, fab.n_cells * fab.period, str(out), recipe.seed, n, shard,
                       recipe.rytov_range, recipe.rytov_values, recipe.closed_loop,
                       split_labels(recipe.seed, n, recipe.split) if recipe.closed_loop else None)
    log(f"dataset {recipe.name}: {n} samples in {n_shards} shards ({len(done)} done), "
        f"tensor 8x{recipe.tensor_size}^2 -> {out}")
    timings: dict = {}
    t_sweep = time.perf_counter()
    results, computed_now = run_shards(ctx, shards, folder, run.replace(scheduler=None, log=lambda s: None),
                                       weight=size.__getitem__)
    for nm in computed_now:
        for k, v in results[nm]["timings"].items():
            timings[k] = timings.get(k, 0.0) + v
    sweep = time.perf_counter() - t_sweep
    mark_complete(out)
    folder.remove()
    consolidate(out)
    info = open_dataset(out)
    computed = sum(size[nm] for nm in computed_now)
    return {"output": str(out), "samples": n, "shards": n_shards, "resumed_shards": len(done),
            "computed_samples": computed, "seconds": time.perf_counter() - t_start, "sweep_seconds": sweep,
            "per_sample_seconds": {k: v / max(computed, 1) for k, v in timings.items()},
            "workers": "dask" if run.client is not None else run.workers, **info.summary()}



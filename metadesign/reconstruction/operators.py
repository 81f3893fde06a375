"""Stored bucket operators of the end-to-end loss (stage 6b).

The end-to-end PiB loss is a quadratic form: the back-propagation through a sample's fixed screens is
linear in the aperture correction ``u``, so its power in bucket is ``||A u||^2`` with ``A`` the bucket
pixels' rows of that operator on the receiver-aperture pixels (:meth:`PiB.bucket_operator`: one adjoint
split step per bucket pixel, ~0.3 s per sample on one core at the demo grid).  ``metadesign dataset
operators DATASET`` computes ``A`` once per sample of the chosen splits and stores it beside the samples
(array ``pib_operator``: ``(samples, bucket pixels, aperture pixels)`` complex64, one inner chunk per
sample, sharded like the dataset, samples of other splits not stored).  Training then loads ``A`` instead
of regenerating 13 screens, and its loss is a small matrix product instead of 12 FFT pairs forward and
back (``train.pib_operator``: ``auto`` uses stored operators when the training split has them).

Resumable like the build: a shard is finished when its marker ``DATASET/.operators/NNNNNN`` exists
(written atomically after its block); ``pib_operator.complete`` is set in the store's attributes at the end.
One torch thread per sample: the same bytes whatever the worker count or scheduler."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..execution import SERIAL, Execution
from ..outputs import Need, check_need, product
from ..validation import ValidationError, check_memory
from .data import PSFDataset
from .dataset_build import execution_of, run_shards, shard_folder, shard_name
from .dataset_store import OPERATOR_ARRAY as ARRAY
from .dataset_store import consolidate, has_operators, open_dataset, open_store, operator_info
from .losses import PiB

__all__ = ["OperatorContext", "build_operators", "operator_info", "has_operators"]

SPLITS = ("train", "val", "test")


@dataclass
class OperatorContext:
    """What a worker needs to compute the operators of one shard."""

    out: str
    shard_size: int
    n: int
    wanted: np.ndarray  # bool (n,): the samples of the chosen splits
    kind: str = "operators"
    _ds: object = None

    def dataset_and_pib(self):
        """The dataset (screens regenerated from its seeds) and the loss geometry, built once per worker."""
        if self._ds is None:
            ds = PSFDataset(self.out, "all")
            self._ds = (ds, PiB(ds.scenario(), *ds.crop()))
        return self._ds

    def __getstate__(self):  # workers build their own (a PiB holds the propagation kernels)
        return {**self.__dict__, "_ds": None}

    def make(self, shard: int) -> dict:
        import torch

        i0, i1 = shard * self.shard_size, min(self.n, (shard + 1) * self.shard_size)
        ds, pib = self.dataset_and_pib()
        g = open_store(self.out, "r+")
        arr = g[ARRAY]
        block = np.zeros((i1 - i0, *arr.shape[1:]), np.complex64)
        t0 = time.perf_counter()
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # FFT sums in one order: same bytes on any worker
        try:
            with torch.no_grad():
                for i in range(i0, i1):
                    if self.wanted[i]:
                        scr = torch.from_numpy(ds.screens_of(i)[None])
                        block[i - i0] = pib.bucket_operator(scr)[0].numpy()
        finally:
            torch.set_num_threads(threads)
        arr[i0:i1] = block
        return {"shard": shard, "samples": int(self.wanted[i0:i1].sum()),
                "timings": {"operator": time.perf_counter() - t0}}


def build_operators(path: str | Path, splits=("train",), overwrite: bool = False, run: Execution = SERIAL,
                    **legacy) -> dict:
    """Compute (or resume) the stored bucket operators of ``splits`` of the dataset at ``path`` under ``run``
    (local workers or Dask; its progress and log; the older keywords ``workers=``, ``scheduler=``,
    ``client=``, ``progress=``, ``log=`` are still accepted)."""
    run = execution_of(run, legacy, "build_operators")
    open_dataset(path)  # a missing or damaged dataset: one line, before the lock
    with product(path, "dataset"):  # the operators are written into the dataset itself
        return _build_operators(path, splits, overwrite, run)


def _build_operators(path, splits, overwrite: bool, run: Execution) -> dict:
    log = run.log
    splits = tuple(dict.fromkeys(splits))
    bad = [s for s in splits if s not in SPLITS]
    if bad or not splits:
        raise ValidationError(f"--splits: expected some of {', '.join(SPLITS)}, got {' '.join(splits) or 'none'}")
    info = open_dataset(path)
    out = Path(path)
    wanted = np.isin(info.split, [SPLITS.index(s) for s in splits])
    n, shard = info.n, int(info.attrs["shard_size"])
    ctx = OperatorContext(str(out), shard, n, wanted)
    pib = ctx.dataset_and_pib()[1]
    nb, n_ap = len(pib.bucket), int(pib.ap.sum())
    check_need(out, Need(disk=float(wanted.sum()) * nb * n_ap * 8, what="fewer --splits (train alone is usual)"))
    per_shard = np.add.reduceat(wanted.astype(int), np.arange(0, n, shard))  # wanted samples per shard
    want_attrs = {"splits": sorted(splits, key=SPLITS.index), "bucket_pixels": nb, "aperture_pixels": n_ap,
                  "dtype": "complex64",
                  "layout": "A[i] (bucket pixels x aperture pixels): rows in PiB.bucket order (row-major "
                            "beacon-plane pixels), columns the aperture pixels of the received crop, row-major",
                  "meaning": "bucket power of a unit-power aperture correction u is ||A u||^2; NPiB = that / "
                             "the ideal beam's bucket power (PiB.npib_quadratic)"}
    old = operator_info(info.attrs)
    g = open_store(out, "r+")
    if old is not None and {k: old.get(k) for k in want_attrs} != want_attrs:
        if not overwrite:
            raise ValidationError(f"{out}: holds operators of splits {'/'.join(old.get('splits', []))}; "
                                  "use --overwrite to recompute them for the splits asked")
        log(f"--overwrite: removing the stored operators of {out}")
        del g[ARRAY]
        del g.attrs[ARRAY]
        shard_folder(out, "operators").remove()
        old = None
    total = int(wanted.sum())
    t0 = time.perf_counter()

    def report(computed: int, resumed: int, seconds_computing: float) -> dict:
        on_disk = sum(p.stat().st_size for p in (out / ARRAY).rglob("*") if p.is_file())
        return {"output": str(out), "samples": total, "computed_samples": computed, "resumed_shards": resumed,
                "seconds": time.perf_counter() - t0,
                "per_sample_seconds": {"operator": seconds_computing / computed} if computed else {},
                "bytes_per_operator": nb * n_ap * 8, "bytes_on_disk": on_disk,
                "workers": run.workers if not run.distributed else "dask", **want_attrs}

    if old is not None and old.get("complete"):
        log(f"{out}: operators of {'/'.join(want_attrs['splits'])} are up to date")
        return report(0, 0, 0.0)
    if ARRAY not in g:
        check_memory("dataset operators (one shard)", shard * nb * n_ap * 8 * 2, "a smaller dataset shard_size")
        g.create_array(ARRAY, shape=(n, nb, n_ap), chunks=(1, nb, n_ap), shards=(shard, nb, n_ap),
                       dtype="complex64", fill_value=0j, compressors=None,
                       dimension_names=("sample", "bucket", "aperture"))
        g.attrs.update({ARRAY: {**want_attrs, "complete": False}})
    folder = shard_folder(out, "operators")
    shards = {shard_name(i): i for i, k in enumerate(per_shard) if k}
    done = [nm for nm in shards if folder.marked(nm) is not None]
    todo = int(sum(per_shard[shards[nm]] for nm in shards if nm not in done))
    log(f"operators of {out} ({'/'.join(want_attrs['splits'])}): {total} samples, "
        f"{nb} x {n_ap} complex64 each ({nb * n_ap * 8 / 1e3:.0f} kB); {len(shards) - len(done)} shards to compute")
    results, computed = run_shards(ctx, shards, folder, run.replace(log=lambda s: None),
                                   weight=lambda nm: int(per_shard[shards[nm]]))
    tim = sum(results[nm]["timings"]["operator"] for nm in computed)
    g = open_store(out, "r+")
    g.attrs.update({ARRAY: {**want_attrs, "complete": True}})
    folder.remove()
    consolidate(out)
    return report(todo, len(done), tim)

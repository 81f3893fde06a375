"""Same seed, same bytes: BLAS on one thread inside the kernels whose results are stored or regenerated.

A multi-threaded BLAS splits a matrix product differently from a single-threaded one, and the float32
sums then differ in the last bits (measured here: ~1e-6 relative in the sensor MFTs and the subharmonic
screens).  Datasets store PSFs and regenerate screens from seeds in other processes (DataLoader workers,
Dask workers, the trainer), so these kernels pin BLAS to one thread for their duration, whatever the
process was started with (~8 us per call with a cached threadpoolctl controller)."""

from __future__ import annotations

import contextlib

__all__ = ["single_thread_blas"]

_CONTROLLER = None


@contextlib.contextmanager
def single_thread_blas():
    global _CONTROLLER
    try:
        if _CONTROLLER is None:
            from threadpoolctl import ThreadpoolController

            _CONTROLLER = ThreadpoolController()
        ctx = _CONTROLLER.limit(limits=1, user_api="blas")
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        ctx = contextlib.nullcontext()
    with ctx:
        yield

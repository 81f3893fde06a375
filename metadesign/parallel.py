"""Worker processes the way every stage starts them: spawned (no fork of a process holding BLAS or torch
threads), one BLAS/OpenMP thread each, set in the environment before the child imports numpy."""

from __future__ import annotations

import multiprocessing as mp
import os

__all__ = ["THREAD_ENV", "spawn_pool", "single_thread_env"]

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def single_thread_env() -> None:
    os.environ.update({k: "1" for k in THREAD_ENV})


def spawn_pool(workers: int, initializer=None, initargs=()):
    """A spawned ``multiprocessing.Pool`` of single-threaded workers (the parent's environment restored)."""
    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    single_thread_env()  # spawned children read these before importing numpy
    try:
        return mp.get_context("spawn").Pool(workers, initializer=initializer, initargs=initargs)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

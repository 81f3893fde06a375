"""Worker processes the way every stage starts them: spawned (no fork of a process holding BLAS or torch
threads), one BLAS/OpenMP thread each, set in the environment before the child imports numpy."""

from __future__ import annotations

import multiprocessing as mp
import os

from .validation import ValidationError

__all__ = ["THREAD_ENV", "spawn_pool", "single_thread_env", "keep_freed_memory"]

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def single_thread_env() -> None:
    os.environ.update({k: "1" for k in THREAD_ENV})


_MALLOC_SET = False


def keep_freed_memory() -> bool:
    """Let glibc keep freed large blocks in this process (idempotent; a no-op off glibc).

    A Dask nanny starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which also freezes glibc's
    mmap threshold at its 128 kB default: every array of a sample (screens, FFT buffers, PSFs) is then
    a fresh ``mmap`` whose pages fault in and are unmapped again on free.  Measured on the dataset's
    sample (paper layout): 220 ms in such a worker against 110 ms in a plain process.  Raising the mmap
    and trim thresholds restores the plain-process speed; memory is returned when the worker exits."""
    global _MALLOC_SET
    if _MALLOC_SET:
        return True
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(-3, 64 << 20) == 1 and libc.mallopt(-1, 256 << 20) == 1  # M_MMAP_, M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        ok = False
    _MALLOC_SET = ok
    return ok


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


def dask_client(scheduler: str):
    """A ``dask.distributed.Client`` on ``scheduler``; an unreachable one is a one-line ValidationError."""
    from dask.distributed import Client

    try:
        return Client(scheduler, timeout="20s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise ValidationError(f"--scheduler {scheduler}: cannot reach a Dask scheduler "
                              f"({exc.__class__.__name__}: {str(exc).splitlines()[0][:120]})") from None

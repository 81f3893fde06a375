"""Worker processes the way every stage starts them: spawned (no fork of a process holding BLAS or torch
threads), one BLAS/OpenMP thread each, set in the environment before the child imports numpy.

One engine for every parallel build (library sweep, dataset shards, bucket operators, supercells,
comparisons): :class:`WorkerPool` (local spawned workers, or in-process for one) and :func:`run_tasks`
(the pool, or a Dask client), both calling ``fn(task)`` or, with a ``shared`` object (a device pupil, a
shard context: sent to each worker once, scattered on Dask), ``fn(shared, task)``.  Results come back as
they finish; callers that write them key them by the task, so the bytes never depend on the order,
the worker count or the scheduler."""

from __future__ import annotations

import multiprocessing as mp
import os

from .validation import ValidationError

__all__ = ["THREAD_ENV", "spawn_pool", "single_thread_env", "keep_freed_memory", "WorkerPool", "run_tasks",
           "dask_client"]

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

    _probe(scheduler)
    try:
        return Client(scheduler, timeout="20s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise ValidationError(f"--scheduler {scheduler}: cannot reach a Dask scheduler "
                              f"({exc.__class__.__name__}: {str(exc).splitlines()[0][:120]})") from None


#: the address schemes a Dask client connects to
_SCHEMES = ("tcp", "tls", "inproc", "ucx", "ws", "wss")


def check_scheduler(scheduler: str) -> None:
    """The up-front check of a ``--scheduler`` option (the CLI runs it before a command opens its output):
    an address a Dask client can reach; one line otherwise."""
    _probe(scheduler)


def _probe(scheduler: str) -> None:
    """Fail at once on an address that cannot name a scheduler (no scheme or port, an unknown scheme), on a
    host name that does not resolve, and when nothing listens at a ``tcp://host:port`` address (a refused
    connection), instead of after the client's 20 s of retries; a timeout goes to the client."""
    import socket
    from urllib.parse import urlsplit

    head = f"--scheduler {scheduler}: "
    scheme = scheduler.split("://", 1)[0] if "://" in scheduler else None
    if scheme is None or scheme not in _SCHEMES:
        raise ValidationError(head + "expected a Dask scheduler address such as tcp://host:8786 "
                              f"(schemes: {', '.join(_SCHEMES)})")
    if scheme != "tcp":
        return
    try:
        u = urlsplit(scheduler)
        host, port = u.hostname, u.port
    except ValueError as exc:
        raise ValidationError(head + f"not an address ({exc})") from None
    if not host or port is None:
        raise ValidationError(head + "expected tcp://host:port")
    try:
        socket.create_connection((host, port), timeout=5).close()
    except ConnectionRefusedError as exc:
        raise ValidationError(head + f"cannot reach a Dask scheduler (nothing listens there: {exc.strerror})") from None
    except socket.gaierror as exc:
        raise ValidationError(head + f"cannot resolve host {host!r} ({exc.strerror})") from None
    except OSError:
        return  # a timeout: the client says it with its own retries


_SHARED = None  # a worker's shared object (set once by the pool's initializer)


def _init_shared(shared) -> None:
    global _SHARED
    single_thread_env()
    _SHARED = shared


class _Call:
    """``fn(task)`` or ``fn(shared, task)`` in a pool worker (picklable: ``fn`` is a module-level function)."""

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, task):
        return self.fn(task) if _SHARED is None else self.fn(_SHARED, task)


class WorkerPool:
    """Spawned single-threaded worker processes, or in-process for ``workers <= 1``; keep one open to
    reuse its workers across several maps (the library's convergence check and sweep)."""

    def __init__(self, workers: int = 1, shared=None):
        self.workers, self.shared = int(workers), shared
        self.pool = spawn_pool(self.workers, _init_shared, (shared,)) if self.workers > 1 else None

    def map(self, fn, tasks, ordered: bool = False):
        """Results of ``fn`` over ``tasks``, as they finish (``ordered``: in task order)."""
        if self.pool is None:
            return (fn(t) if self.shared is None else fn(self.shared, t) for t in tasks)
        return (self.pool.imap if ordered else self.pool.imap_unordered)(_Call(fn), tasks)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.terminate()
            self.pool.join()
            self.pool = None

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _dask_call(fn, shared, task):
    single_thread_env()
    keep_freed_memory()  # the nanny's MALLOC_TRIM_THRESHOLD_ doubles a sample's cost otherwise
    return fn(task) if shared is None else fn(shared, task)


def run_tasks(fn, tasks, workers: int = 1, shared=None, client=None, scheduler: str | None = None,
              key: str | None = None):
    """Results of ``fn`` over ``tasks`` as they finish: on a Dask ``client`` (or a ``scheduler`` address,
    connected and closed here), else on a local :class:`WorkerPool` of ``workers``.  ``key``: a prefix of
    the Dask task keys (task i gets ``key-i``)."""
    tasks = list(tasks)
    if not tasks:
        return
    if client is not None or scheduler is not None:
        from dask.distributed import as_completed

        own = client is None
        if own:
            client = dask_client(scheduler)
        try:
            sf = client.scatter(shared, broadcast=True) if shared is not None else None
            futures = [client.submit(_dask_call, fn, sf, t, pure=False,
                                     **({"key": f"{key}-{t if isinstance(t, int) else i}"} if key else {}))
                       for i, t in enumerate(tasks)]
            for fut in as_completed(futures):
                yield fut.result()
        finally:
            if own:
                client.close()
        return
    with WorkerPool(min(workers, len(tasks)), shared) as pool:
        yield from pool.map(fn, tasks)



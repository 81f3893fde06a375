"""One execution context for long jobs: how a job runs, apart from what it computes.

A long job (a library build, a supercell table, a dataset, a study over many cases) takes its physics
inputs as arguments and *how it runs* as one :class:`Execution`: the worker count or the Dask scheduler
(or an open client or worker pool to reuse), the progress callback, the log, and the test hook that stops
it after a number of tasks.  Functions pass it on whole instead of six keyword arguments each::

    run = Execution(workers=2, progress=bar, log=print)
    table = solve_table(widths, stack, n_harmonics, scratch_path(out), run=run)

Scratch folders follow one convention (:func:`scratch_path`): the resume folder of an output ``OUT`` is
``OUT.partial`` beside it, a job's sub-steps are folders inside it, and the product layer
(:func:`metadesign.outputs.check_output`) takes an existing one as a resume folder only when metadesign made
it (it carries the task manifest, :data:`metadesign.tasks.SCRATCH_MARK`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from .parallel import run_tasks
from .scratch import (SCRATCH_FORMAT, SCRATCH_MARK, SCRATCH_SUFFIX, fresh_scratch, is_scratch,  # noqa: F401
                      make_scratch, publish_scratch, remove_scratch, scratch_manifest, scratch_path)
from .tasks import run_resumable

__all__ = ["Execution", "SERIAL", "scratch_path"]


def _quiet(msg: str) -> None:
    pass


@dataclass(frozen=True)
class Execution:
    """How a long job runs (never what it computes: the same seed gives the same bytes under any
    :class:`Execution`).

    ``workers``: local worker processes (one thread each); ``scheduler``: a Dask scheduler address instead; ``client`` / ``pool``: an open Dask client or
    :class:`~metadesign.parallel.WorkerPool` to reuse; ``progress(done, total)``; ``log(line)``;
    ``stop_after``: raise KeyboardInterrupt after that many new tasks (tests of resumption)."""

    workers: int = 1
    scheduler: str | None = None
    client: Any = None
    pool: Any = None
    progress: Callable[[int, int], None] | None = None
    log: Callable[[str], None] = _quiet
    stop_after: int | None = None

    def replace(self, **changes) -> "Execution":
        return dataclasses.replace(self, **changes)

    @property
    def distributed(self) -> bool:
        return self.client is not None or self.scheduler is not None

    def run(self, fn, tasks: Mapping[str, object], folder, **options):
        """:func:`metadesign.tasks.run_resumable` of ``fn`` over ``tasks`` in ``folder`` under this context
        (``options``: ``store``, ``compress``, ``keep``, ``shared``, ``dask_key``, ``weight``, ``unit``)."""
        return run_resumable(fn, tasks, folder, workers=self.workers, client=self.client, scheduler=self.scheduler,
                             pool=self.pool, progress=self.progress, log=self.log, stop_after=self.stop_after,
                             **options)

    def map(self, fn, tasks, shared=None, key: str | None = None):
        """Results of ``fn`` over ``tasks`` as they finish (:func:`metadesign.parallel.run_tasks`), on the open
        pool when there is one."""
        if self.pool is not None and not self.distributed and shared is None:
            return self.pool.map(fn, list(tasks))
        return run_tasks(fn, tasks, workers=self.workers, shared=shared, client=self.client,
                         scheduler=self.scheduler, key=key)


#: one process, no progress, no log
SERIAL = Execution()

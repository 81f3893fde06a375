"""One resumable-task engine and one content key for every long job.

* :func:`content_key` is the one cache key: the full sha256 of the canonical JSON of what shapes a result
  (sorted keys; numpy arrays by dtype, shape and bytes; a :class:`pathlib.Path` is refused, so no key ever
  depends on where a file lies: hash its content with :func:`file_key`).
* :class:`TaskFolder` keeps a job's finished tasks, each written atomically (a ``NAME.npz`` of arrays or a
  ``NAME.json`` marker of a task whose result lives elsewhere, e.g. a zarr shard): a task is done exactly
  when its file exists and reads back.  The folder carries the scratch marker :data:`SCRATCH_MARK` (its
  manifest, ``{"format": "metadesign.scratch/1", ...}``), written before anything else, so a folder
  metadesign made is told from a user's (:func:`metadesign.outputs.check_output` refuses a user's folder
  where a resume folder goes; only a marked folder is ever removed).  The folder records the job's key: a
  folder left by another job (other recipe, other version) is emptied before use, never mixed in.
* :func:`run_resumable` runs the tasks not yet done through :func:`metadesign.parallel.run_tasks` (a local
  pool or Dask), keeps each result as it arrives, reports progress, and returns every task's result.  A
  job killed at any point (SIGKILL included) loses at most the tasks in flight; the rerun computes only
  those, and since results are keyed by task (never by arrival order), the bytes are the same whatever
  the worker count or scheduler.
* :meth:`TaskFolder.step` is the sequential form (a pipeline stage, a tolerance case, a transfer run): a
  step reruns exactly when its content key changed or its outputs are gone.

Scratch folders follow one convention (:func:`metadesign.execution.scratch_path`): an output's resume
folder is ``OUT.partial`` beside it, a step's a folder inside it.  Used by the library build
(``OUT.partial/``), the supercell table (``OUT.partial/``, its PEDS levels ``OUT.partial/nG-N/``), the tiled layout
(``OUT/.tiled-partial-KEY/``), the dataset's shards (``DATASET/.shards/``) and its bucket operators
(``DATASET/.operators/``); steps by the pipeline (``OUT/.steps/``), the tolerance study's cases and the
transfer study's stages (``OUT/.steps/``).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Callable, Iterable, Mapping

import numpy as np

from .cliutil import plural
from .scratch import SCRATCH_FORMAT, SCRATCH_MARK, is_scratch, make_scratch, remove_scratch
from .io import atomic_write_text, read_npz, write_npz
from .parallel import run_tasks
from .validation import InputError, ValidationError

__all__ = ["content_key", "file_key", "path_key", "TaskFolder", "run_resumable", "SCRATCH_MARK", "SCRATCH_FORMAT",
           "is_scratch"]


def _canonical(obj):
    if isinstance(obj, Path):
        raise TypeError(f"content_key: a path ({obj}) is not content (hash the file with file_key)")
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        return {"__array__": [a.dtype.str, list(a.shape), hashlib.sha256(a.tobytes()).hexdigest()]}
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, dict):
        return {str(k): _canonical(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    return obj


def content_key(*parts) -> str:
    """Full sha256 (64 hex digits) of the canonical JSON of ``parts`` (one part: of that part alone; the
    canonical JSON is ``json.dumps(..., sort_keys=True)``, so a dataset's recipe hash keeps its value)."""
    obj = _canonical(parts[0] if len(parts) == 1 else list(parts))
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=_refuse).encode()).hexdigest()


def _refuse(obj):
    raise TypeError(f"content_key: {type(obj).__name__} is not JSON content ({obj!r:.60})")


def path_key(path: str | Path) -> dict:
    """A path named as an input, by content: its file's key, or its name where it does not exist (never
    where it lies)."""
    p = Path(path)
    return {"file": file_key(p)} if p.is_file() else {"missing": p.name}


def file_key(path: str | Path) -> str:
    """A file's content key: its bytes' sha256."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class TaskFolder:
    """The finished tasks of one job (see the module's docstring).  ``key``: the job's content key (None:
    the task names carry the content themselves, e.g. a supercell chunk named by its rows' hash, so
    results of several jobs may share the folder)."""

    MANIFEST = SCRATCH_MARK

    def __init__(self, root: str | Path, key: str | None = None, log: Callable[[str], None] = lambda s: None,
                 **manifest):
        self.root = Path(root)
        self.key = key
        if key is not None and self.root.is_dir() and self.manifest().get("key") != key:
            if not is_scratch(self.root):  # never remove what metadesign did not make
                raise InputError(f"{self.root}: exists and metadesign did not make it (refusing to use or remove "
                                 "it: move it)")
            log(f"discarding {self.root} (made by another job: other inputs or version)")
            shutil.rmtree(self.root)
        # the marker first (a folder of an earlier version without one is used as it is, never removed)
        make_scratch(self.root, **({} if key is None else {"key": key, **manifest}))

    def manifest(self) -> dict:
        try:
            m = json.loads((self.root / self.MANIFEST).read_text())
        except (OSError, ValueError):
            return {}
        return m if isinstance(m, dict) else {}

    def _file(self, name: str, kind: str) -> Path:
        return self.root / f"{name}.{kind}"

    def has(self, name: str) -> bool:
        """Whether task ``name``'s arrays are kept (without reading them back)."""
        return self._file(name, "npz").exists()

    def load(self, name: str) -> dict | None:
        """A finished task's arrays, or None (not done; a damaged file is removed: it is computed again)."""
        f = self._file(name, "npz")
        if not f.exists():
            return None
        try:
            return read_npz(f, "task result")
        except ValidationError:
            f.unlink()
            return None

    def save(self, name: str, arrays: Mapping, compress: bool = True) -> None:
        write_npz(self._file(name, "npz"), arrays, compress=compress)

    def marked(self, name: str) -> dict | None:
        """A finished task's marker (a task whose result lives elsewhere), or None."""
        f = self._file(name, "json")
        try:
            return json.loads(f.read_text())
        except (OSError, ValueError):
            return None

    def mark(self, name: str, info: Mapping | None = None) -> None:
        atomic_write_text(self._file(name, "json"), json.dumps(dict(info or {}), sort_keys=True, default=float))

    def remove(self) -> None:
        """Remove the folder (only if it carries the marker: a folder metadesign did not make stays)."""
        remove_scratch(self.root)

    def step(self, name: str, key: str, fn: Callable[[], dict], outputs: Iterable[Path] = (),
             clear: Iterable[Path] = ()) -> tuple[dict, bool]:
        """One step of a sequential study (a pipeline stage, a tolerance case, a transfer run): its result
        (a JSON-able dict) if the marker ``name`` holds the same ``key`` and every path of ``outputs``
        exists, else ``fn()`` run afresh (after removing ``clear``: the step's partial work of another
        key) and marked.  Returns ``(result, skipped)``."""
        m = self.marked(name)
        if m is not None and m.get("key") == key and all(Path(o).exists() for o in outputs):
            return m["result"], True
        if m is not None and m.get("key") != key:
            for c in clear:
                c = Path(c)
                if c.is_dir():
                    shutil.rmtree(c)
                elif c.exists():
                    c.unlink()
        res = fn()
        self.mark(name, {"key": key, "result": res})
        return res, False


def run_resumable(fn, tasks: Mapping[str, object], folder: TaskFolder, *, store: str = "npz",
                  compress: bool = True, keep: bool = True, workers: int = 1, shared=None, client=None, scheduler: str | None = None,
                  dask_key: str | None = None, pool=None, weight: Callable[[str], int] = lambda name: 1,
                  progress: Callable[[int, int], None] | None = None, log: Callable[[str], None] = lambda s: None,
                  stop_after: int | None = None, unit: str = "item") -> tuple[dict, list[str]]:
    """Run ``fn`` (``fn(task)`` or ``fn(shared, task)``; it returns ``(name, result)``) over the ``tasks``
    (name -> task) not yet done in ``folder``; returns ``(results by name, names computed now)``.

    ``store``: ``"npz"`` keeps each result (a mapping of arrays) as ``NAME.npz``; ``"marker"`` keeps a
    JSON marker of it (the task wrote its own output); a task may also save its own ``NAME.npz`` in the
    folder (atomically) and return None as its result (a local worker: nothing crosses the pipe).  ``weight``: a task's size for progress (cells,
    samples).  ``keep``: False leaves the results on disk (the returned mapping holds empty entries; the caller reads
    each back when it needs it: memory stays one task's).  ``stop_after``: raise KeyboardInterrupt after that many new tasks (tests of resumption).  ``pool``: an
    open :class:`~metadesign.parallel.WorkerPool` to reuse (local runs)."""
    results: dict = {}
    for name in tasks:
        if store == "npz" and not keep:  # large results stay on disk (read back when assembled)
            r = {} if folder.has(name) else None
        else:
            r = folder.load(name) if store == "npz" else folder.marked(name)
        if r is not None:
            results[name] = r
    todo = [n for n in tasks if n not in results]
    total = sum(weight(n) for n in tasks)
    done_w = total - sum(weight(n) for n in todo)
    if results:
        log(f"resuming: {len(results)}/{len(tasks)} tasks ({done_w}/{total} {plural(unit)}) kept from an interrupted "
            f"run in {folder.root}")
    if progress:
        progress(done_w, total)
    computed: list[str] = []
    it: Iterable = (pool.map(fn, [tasks[n] for n in todo]) if pool is not None and scheduler is None
                    and client is None else
                    run_tasks(fn, [tasks[n] for n in todo], workers=workers, shared=shared, client=client,
                              scheduler=scheduler, key=dask_key))
    for count, (name, res) in enumerate(it, 1):
        if store == "npz":
            if res is not None:  # None: the task saved NAME.npz in the folder itself (a local worker)
                folder.save(name, res, compress=compress)
            elif not folder.has(name):
                raise RuntimeError(f"task {name} returned no result and saved none in {folder.root}")
        else:
            folder.mark(name, res)
        if keep and res is None and store == "npz":
            res = folder.load(name)
            if res is None:
                raise RuntimeError(f"task {name}: its saved result in {folder.root} does not read back")
        results[name] = res if keep else {}
        computed.append(name)
        done_w += weight(name)
        if progress:
            progress(done_w, total)
        if stop_after is not None and count >= stop_after:
            raise KeyboardInterrupt("simulated kill")
    return results, computed

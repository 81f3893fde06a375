"""Atomic, reproducible file output and safe array input.

* :func:`atomic_path` yields a temporary path beside the target and renames
  it over the target only if the block finished: a killed or failed job never
  leaves a half-written product.
* :func:`write_npz` writes a ``.npz`` with fixed zip timestamps, so the same
  arrays give the same bytes.
* :func:`read_npz` never unpickles (``allow_pickle=False``) and turns corrupt
  or truncated files into one-line :class:`~metadesign.config.InputError`.
* :func:`output_lock` keeps a second process from writing the same output while
  one is (an advisory ``flock`` the kernel releases when a writer dies, even by
  SIGKILL).  What may be written where is :mod:`metadesign.outputs`'s (the product layer).
"""

from __future__ import annotations

import contextlib
import fcntl
import glob
import io
import json
import os
import tempfile
import zipfile
from pathlib import Path
from dataclasses import dataclass
from typing import Iterable, Iterator, Mapping

import numpy as np

from .config import InputError
from .deflate import DeflatedArray, write_zip

__all__ = ["atomic_path", "remove_stale_temps", "atomic_write_text", "write_npz", "StreamedArray", "DeflatedArray", "NpzRows", "iter_npz_rows", "read_npz",
           "read_product", "json_array", "from_json_array", "output_lock",
           "lock_path", "claim", "enforce_claims", "claimed"]

_EPOCH = (1980, 1, 1, 0, 0, 0)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(target: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Context manager: write to the yielded temp path; renamed on success."""
    target = Path(target)
    _check_claimed(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{target.name}.", suffix=suffix if suffix is not None else target.suffix + ".tmp",
        dir=target.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual mode
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def remove_stale_temps(target: str | Path, suffix: str | None = None) -> list[Path]:
    """Remove the temporary files :func:`atomic_path` left for ``target`` when its writer was killed
    (SIGKILL runs no cleanup): ``.NAME.<random>SUFFIX`` beside it.  Call it only while no other process
    writes ``target`` (a job holding the output's lock); returns what was removed."""
    target = Path(target)
    suffix = suffix if suffix is not None else target.suffix + ".tmp"
    gone = []
    if target.parent.is_dir():
        for p in target.parent.glob(f".{glob.escape(target.name)}.*{glob.escape(suffix)}"):
            if p.is_file() and not p.is_symlink():
                p.unlink(missing_ok=True)
                gone.append(p)
    return gone


#: outputs opened by the product layer (metadesign.outputs.product) in this process, and whether writes
#: outside them are refused (the CLI turns this on: no command writes around the product layer)
_CLAIMS: list[Path] = []
_ENFORCE = [False]


def enforce_claims(on: bool = True) -> None:
    """Refuse (RuntimeError: a programming error, not a user's) any :func:`atomic_path` target outside the
    outputs the product layer has open."""
    _ENFORCE[0] = bool(on)


def claimed(target: str | Path) -> bool:
    t = Path(target).resolve()
    return any(t == c or c in t.parents for c in _CLAIMS)


def _check_claimed(target: Path) -> None:
    if _ENFORCE[0] and not claimed(target):
        raise RuntimeError(f"{target}: written outside any declared output (every output goes through "
                           "metadesign.outputs.product)")


@contextlib.contextmanager
def claim(*paths: str | Path) -> Iterator[None]:
    """Mark ``paths`` as declared outputs while the block runs (the product layer's use)."""
    ps = [Path(p).resolve() for p in paths]
    _CLAIMS.extend(ps)
    try:
        yield
    finally:
        for p in ps:
            _CLAIMS.remove(p)


def atomic_write_text(target: str | Path, text: str) -> None:
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def json_array(obj) -> np.ndarray:
    """Metadata as a 0-d unicode array (storable without pickle)."""
    return np.array(json.dumps(obj, sort_keys=True, indent=1))


def from_json_array(arr: np.ndarray):
    if arr.size != 1 or arr.dtype.kind != "U":
        raise ValueError("metadata is not a single string")
    return json.loads(str(arr.reshape(-1)[0]))


@dataclass(frozen=True)
class StreamedArray:
    """An array :func:`write_npz` writes from ``chunks`` (C-order blocks along axis 0, in order) without
    holding it: the same bytes as the whole array (the zip entry's sizes are planned from ``shape``)."""

    shape: tuple
    dtype: object
    chunks: Iterable


def write_npz(target: str | Path, arrays: Mapping[str, object], compress: bool = True) -> None:
    """Atomically write ``arrays`` as a byte-reproducible ``.npz``.  A value may be a
    :class:`StreamedArray` (written block by block), a :class:`DeflatedArray` (pieces compressed by workers,
    concatenated: :mod:`metadesign.deflate`) or a callable returning the array (called when its turn comes,
    in name order: metadata made while an earlier array streams)."""
    if any(isinstance(a, DeflatedArray) for a in arrays.values()):
        if not compress:
            raise ValueError("an array deflated in pieces needs compress=True")
        with atomic_path(target) as tmp, open(tmp, "wb") as fh:
            write_zip(fh, ((f"{name}.npy", _npz_entry(name, arrays[name])) for name in sorted(arrays)))
        return
    comp = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_path(target) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=comp) as zf:
            for name in sorted(arrays):
                arr = arrays[name]
                info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
                info.compress_type = comp
                info.external_attr = 0o644 << 16
                if isinstance(arr, StreamedArray):
                    _write_streamed(zf, info, arr)
                    continue
                arr = np.asarray(arr() if callable(arr) else arr)
                if arr.dtype == object:
                    raise TypeError(f"array {name!r} has dtype object (would need pickle)")
                buf = io.BytesIO()
                if not arr.flags.c_contiguous:  # (ascontiguousarray would make 0-d arrays 1-d)
                    arr = np.ascontiguousarray(arr)
                np.lib.format.write_array(buf, arr, allow_pickle=False)
                zf.writestr(info, buf.getvalue())


def _npy_header(shape: tuple, dt: np.dtype) -> bytes:
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": np.lib.format.dtype_to_descr(dt),
                                                "fortran_order": False, "shape": tuple(shape)})
    return head.getvalue()


def _npz_entry(name: str, arr):
    """What :func:`metadesign.deflate.write_zip` takes for one array: its ``.npy`` bytes, or for a
    :class:`DeflatedArray` its header and pieces (their total size checked as they pass)."""
    if isinstance(arr, DeflatedArray):
        dt = np.dtype(arr.dtype)
        total = int(np.prod(arr.shape, dtype=np.int64)) * dt.itemsize

        def pieces():
            n = 0
            for p in arr.pieces:
                n += p.size
                yield p
            if n != total:
                raise ValueError(f"{name}.npy: pieces hold {n} bytes of {total}")

        return _npy_header(arr.shape, dt), pieces()
    if isinstance(arr, StreamedArray):
        raise ValueError(f"{name}: a streamed array beside one deflated in pieces")
    arr = np.asarray(arr() if callable(arr) else arr)
    if arr.dtype == object:
        raise TypeError(f"array {name!r} has dtype object (would need pickle)")
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(arr) if not arr.flags.c_contiguous else arr,
                              allow_pickle=False)
    return buf.getvalue()


def _write_streamed(zf: zipfile.ZipFile, info: zipfile.ZipInfo, sa: StreamedArray) -> None:
    dt = np.dtype(sa.dtype)
    head = _npy_header(sa.shape, dt)
    total = int(np.prod(sa.shape, dtype=np.int64)) * dt.itemsize
    info.file_size = len(head) + total  # what writestr sets: the same zip64 choice, same bytes
    written = 0
    with zf.open(info, "w") as dest:
        dest.write(head)
        for blk in sa.chunks:
            b = np.ascontiguousarray(blk, dtype=dt)
            if b.shape[1:] != tuple(sa.shape[1:]):
                raise ValueError(f"{info.filename}: block of shape {b.shape} in an array of shape {sa.shape}")
            dest.write(b.tobytes())
            written += b.nbytes
    if written != total:
        raise ValueError(f"{info.filename}: streamed {written} bytes of {total}")


class NpzRows:
    """Read-only row access to array ``name`` of a ``.npz`` without loading it: ``rows[r0:r1]`` reads
    forward from the current position (a sequential consumer reads the entry once; going back reopens
    it), so memory is one request, whatever the array's size."""

    def __init__(self, path: str | Path, name: str):
        self.path, self.name = Path(path), name
        with zipfile.ZipFile(self.path) as zf, zf.open(f"{name}.npy") as fh:
            self.shape, self.dtype = self._header(fh)
        self._fh = self._zf = None
        self._pos = 0

    def _header(self, fh):
        version = np.lib.format.read_magic(fh)
        reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran, dtype = reader(fh)
        if fortran or dtype.hasobject or not shape:
            raise InputError(f"{self.path}: {self.name} is not a C-order numeric array")
        return tuple(shape), dtype

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def _open(self) -> None:
        self.close()
        self._zf = zipfile.ZipFile(self.path)
        self._fh = self._zf.open(f"{self.name}.npy")
        self._header(self._fh)
        self._pos = 0

    def __getitem__(self, key) -> np.ndarray:
        if not isinstance(key, slice) or key.step not in (None, 1):
            raise TypeError("NpzRows supports row slices rows[r0:r1] only")
        r0, r1, _ = key.indices(self.shape[0])
        r1 = max(r0, r1)
        if self._fh is None or r0 < self._pos:
            self._open()
        row = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        if r0 > self._pos:
            skip = (r0 - self._pos) * row
            while skip:
                got = len(self._fh.read(min(skip, 1 << 26)))
                if not got:
                    raise InputError(f"{self.path}: {self.name} is truncated")
                skip -= got
        buf = self._fh.read((r1 - r0) * row)
        if len(buf) != (r1 - r0) * row:
            raise InputError(f"{self.path}: {self.name} is truncated")
        self._pos = r1
        return np.frombuffer(buf, self.dtype).reshape((r1 - r0, *self.shape[1:]))

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._zf.close()
        self._fh = self._zf = None

    def __getstate__(self):  # picklable (a worker reopens the file)
        return {"path": self.path, "name": self.name, "shape": self.shape, "dtype": self.dtype}

    def __setstate__(self, d):
        self.__dict__.update(d)
        self._fh = self._zf = None
        self._pos = 0


def iter_npz_rows(path: str | Path, name: str, rows: int) -> Iterator[tuple[int, np.ndarray]]:
    """``(row0, block)`` of array ``name`` of a ``.npz``, ``rows`` rows at a time, read sequentially
    (memory: one block, whatever the array's size; never unpickles)."""
    r = NpzRows(path, name)
    try:
        for r0 in range(0, r.shape[0], rows):
            yield r0, r[r0:r0 + rows]
    finally:
        r.close()


def read_npz(path: str | Path, what: str = "file") -> dict[str, np.ndarray]:
    """Load every array of a ``.npz`` (never unpickles); errors are one line."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such {what}")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, expected a {what} (.npz)")
    if not zipfile.is_zipfile(path):
        with open(path, "rb") as fh:
            head = fh.read(6)
        if head[:2] == b"PK":
            raise InputError(f"{path}: not a readable {what} (corrupt or truncated .npz)")
        raise InputError(f"{path}: not a {what} (expected a .npz archive of named arrays"
                         + (", got a single .npy array)" if head == b"\x93NUMPY" else ")"))
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except ValueError as exc:
        if "allow_pickle" in str(exc) or "pickle" in str(exc).lower():
            raise InputError(f"{path}: not a {what}: it holds Python objects (pickled data is never loaded)") \
                from None
        raise InputError(f"{path}: not a readable {what} (corrupt or truncated: {exc})") from None
    except (zipfile.BadZipFile, OSError, EOFError, KeyError) as exc:
        raise InputError(f"{path}: not a readable {what} (corrupt or truncated: {exc})") from None


def read_product(path: str | Path, what: str, need: tuple[str, ...], fmt: str) -> tuple[dict, dict]:
    """Read a metadesign ``.npz`` product: its arrays and its JSON ``meta``,
    checking the required arrays and the format tag (one-line InputError)."""
    path = Path(path)
    z = read_npz(path, what)
    missing = [k for k in (*need, "meta") if k not in z]
    if missing:
        raise InputError(f"{path}: not a {what} (missing {', '.join(missing)})")
    try:
        meta = from_json_array(z["meta"])
    except (ValueError, TypeError) as exc:
        raise InputError(f"{path}: {what} metadata unreadable ({exc})") from None
    if meta.get("format") != fmt:
        raise InputError(f"{path}: unsupported {what} format {meta.get('format')!r} (expected {fmt})")
    return z, meta


#: locks this process holds (resolved lock paths): output_lock is re-entrant within a process
_HELD: set[str] = set()


def lock_path(out: str | Path) -> Path:
    """The lock file of an output: a hidden file beside it (inside, it would be removed with the output)."""
    out = Path(out)
    return out.parent / f".{out.name}.lock"


@contextlib.contextmanager
def output_lock(out: str | Path, what: str = "output") -> Iterator[None]:
    """Hold an exclusive lock on ``out`` while writing it; a second writer gets a one-line InputError.

    An advisory ``flock`` on ``.NAME.lock`` beside ``out``: the kernel drops it when the holder exits, so
    a writer killed by SIGKILL leaves no stale lock (only the empty file, reused by the next writer)."""
    out = Path(out)
    lock = lock_path(out)
    key = str(lock.resolve())
    if key in _HELD:  # this process holds it already (an outer command writing the same output)
        yield
        return
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(f"{out}: cannot create the lock {lock} ({exc.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise InputError(f"{out}: another metadesign process is writing this {what}; wait for it to finish "
                             "or choose another output") from None
        try:  # the holder before us may have removed the file between our open and our lock
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        _HELD.add(key)
        yield
    finally:
        _HELD.discard(key)
        with contextlib.suppress(OSError):
            os.unlink(lock)
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


#: public names of two of the writer's helpers (the scratch folders' maker uses them)
check_claimed = _check_claimed
current_umask = _umask

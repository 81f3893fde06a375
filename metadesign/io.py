"""Atomic, reproducible file output and safe array input.

* :func:`atomic_path` yields a temporary path beside the target and renames
  it over the target only if the block finished: a killed or failed job never
  leaves a half-written product.
* :func:`write_npz` writes a ``.npz`` with fixed zip timestamps, so the same
  arrays give the same bytes.
* :func:`read_npz` never unpickles (``allow_pickle=False``) and turns corrupt
  or truncated files into one-line :class:`~metadesign.config.InputError`.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from .config import InputError

__all__ = ["atomic_path", "atomic_write_text", "write_npz", "read_npz", "read_product", "json_array",
           "from_json_array"]

_EPOCH = (1980, 1, 1, 0, 0, 0)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(target: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Context manager: write to the yielded temp path; renamed on success."""
    target = Path(target)
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


def write_npz(target: str | Path, arrays: Mapping[str, np.ndarray], compress: bool = True) -> None:
    """Atomically write ``arrays`` as a byte-reproducible ``.npz``."""
    comp = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_path(target) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=comp) as zf:
            for name in sorted(arrays):
                arr = np.asarray(arrays[name])
                if arr.dtype == object:
                    raise TypeError(f"array {name!r} has dtype object (would need pickle)")
                buf = io.BytesIO()
                if not arr.flags.c_contiguous:  # (ascontiguousarray would make 0-d arrays 1-d)
                    arr = np.ascontiguousarray(arr)
                np.lib.format.write_array(buf, arr, allow_pickle=False)
                info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
                info.compress_type = comp
                info.external_attr = 0o644 << 16
                zf.writestr(info, buf.getvalue())


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

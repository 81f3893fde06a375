"""Find a product's unit-cell library: by its recorded path (relative to the
product file), then by its sha256 among the libraries a user keeps."""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..paths import repo_root
from ..tasks import file_key
from ..validation import ValidationError

__all__ = ["file_sha256", "find_library", "relative_to_product"]


def file_sha256(path: str | Path) -> str:
    """A file's sha256 (the one content key of a file: :func:`metadesign.tasks.file_key`)."""
    return file_key(path)


def relative_to_product(target: str | Path, product_dir: str | Path) -> str:
    """``target`` as a path relative to the folder holding the product (posix separators)."""
    try:
        return Path(os.path.relpath(Path(target).resolve(), Path(product_dir).resolve())).as_posix()
    except ValueError:  # another drive (Windows)
        return Path(target).resolve().as_posix()


def find_library(sha256: str | None, recorded: str | None, product_dir: str | Path) -> Path:
    """The library a product was made with.

    Tries the recorded path relative to ``product_dir`` (and as given), then
    every ``*.npz`` in the repository's ``library/`` folder, the product's
    folder and the working directory, accepting the first whose sha256 equals
    the recorded one (any existing file when no sha256 was recorded)."""
    product_dir = Path(product_dir)
    tried: list[Path] = []
    cands: list[Path] = []
    if recorded:
        r = Path(recorded)
        cands += [r] if r.is_absolute() else [product_dir / r, r]
    for folder in (repo_root() / "library", product_dir, Path.cwd()):
        if folder.is_dir():
            cands += sorted(folder.glob("*.npz"))
    seen = set()
    for c in cands:
        key = str(c.resolve()) if c.exists() else str(c)
        if key in seen:
            continue
        seen.add(key)
        tried.append(c)
        if c.is_file() and (sha256 is None or file_sha256(c) == sha256):
            return c
    raise ValidationError(f"no unit-cell library with sha256 {str(sha256)[:12]} found (recorded path {recorded!r}, "
                          f"searched {len(tried)} files); pass --library")


def find_fitted(identity: str, fmt: str, folders) -> tuple[Path, dict] | None:
    """``(file, record)`` of the first JSON record of format ``fmt`` fitted against the library of sha256
    ``identity`` among the ``*.json`` files of ``folders`` (in order, sorted by name), or None."""
    for folder in folders:
        for p in sorted(Path(folder).glob("*.json")) if Path(folder).is_dir() else []:
            try:
                rec = json.loads(p.read_text())
            except (OSError, ValueError):
                continue
            if isinstance(rec, dict) and rec.get("format") == fmt and \
                    (rec.get("library") or {}).get("sha256") == identity:
                return p, rec
    return None

"""Scratch (resume) folders, one convention: the resume folder of an output ``OUT`` is ``OUT.partial``
beside it (:func:`scratch_path`), a job's steps are folders inside it (``OUT.partial/STEP``), and every
scratch folder metadesign makes carries the marker :data:`SCRATCH_MARK` from its first moment
(:func:`make_scratch`), so a folder metadesign made is told from a user's: the product layer
(:func:`metadesign.outputs.check_output`) takes an existing one as a resume folder only when it is marked, and
only a marked folder is ever removed (:func:`remove_scratch`)."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

from .io import check_claimed, current_umask
from .validation import InputError

__all__ = ["scratch_path", "SCRATCH_SUFFIX", "SCRATCH_MARK", "SCRATCH_FORMAT", "is_scratch", "scratch_manifest",
           "make_scratch", "remove_scratch", "fresh_scratch", "publish_scratch"]

#: the suffix of an output's resume folder
SCRATCH_SUFFIX = ".partial"
#: the marker file every scratch folder metadesign makes carries, written before anything else in it (the
#: task manifest of :class:`metadesign.tasks.TaskFolder`)
SCRATCH_MARK = "manifest.json"
#: the format tag of that marker
SCRATCH_FORMAT = "metadesign.scratch/1"


def scratch_path(out: str | Path, step: str | None = None) -> Path:
    """The resume folder of output ``out`` (``OUT.partial``), or the folder of one of its job's steps inside
    it (``OUT.partial/STEP``)."""
    out = Path(out)
    root = out.with_name(out.name + SCRATCH_SUFFIX)
    return root if step is None else root / step


def scratch_manifest(folder: str | Path) -> dict | None:
    """The marker of a scratch folder metadesign made (its manifest), or None: not a folder, a symbolic link,
    or a folder without the marker (a user's, even an empty one).  A task manifest written before the marker
    had its format tag (a job's 64-hex content key) counts as one."""
    folder = Path(folder)
    if folder.is_symlink() or not folder.is_dir():
        return None
    try:
        m = json.loads((folder / SCRATCH_MARK).read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    if not isinstance(m, dict):
        return None
    if m.get("format") == SCRATCH_FORMAT:
        return m
    key = m.get("key")
    legacy = ("format" not in m and isinstance(key, str) and len(key) == 64
              and all(c in "0123456789abcdef" for c in key))
    return m if legacy else None


def is_scratch(folder: str | Path) -> bool:
    """Whether ``folder`` is a scratch folder metadesign made (it carries :data:`SCRATCH_MARK`)."""
    return scratch_manifest(folder) is not None


def _refuse_foreign(path: Path, what: str = "use or remove") -> None:
    raise InputError(f"{path}: exists and metadesign did not make it (refusing to {what} it: move it)")


def make_scratch(folder: str | Path, **manifest) -> Path:
    """Create the scratch folder ``folder`` (and each missing folder above it) carrying the marker from its
    first moment: each is made under a hidden temporary name, the marker written, then renamed into place,
    so a job killed at any point (SIGKILL included) leaves either no folder or a marked one.  A hidden
    folder (``OUT/.steps``, ``OUT/.shards``: a job's scratch inside its product folder) makes the folders
    above it plain (they are the product's).  ``manifest``:
    further fields of the marker (a job's ``key``...).  An existing folder is returned as it is (a folder
    that is not one is refused: InputError)."""
    folder = Path(folder)
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        _refuse_foreign(folder, "use or replace")
    if folder.is_dir():
        return folder
    if folder.name.startswith("."):  # a job's hidden scratch inside its product folder: that folder is the product's
        folder.parent.mkdir(parents=True, exist_ok=True)
    elif not folder.parent.is_dir():  # a step's folder inside a resume folder: the folders above are scratch too
        make_scratch(folder.parent)
    check_claimed(folder / SCRATCH_MARK)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    try:
        (tmp / SCRATCH_MARK).write_text(json.dumps({"format": SCRATCH_FORMAT, **manifest}, sort_keys=True),
                                        encoding="utf-8")
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes 0700; give the usual mode
        if not (folder.exists() or folder.is_symlink()):  # else made meanwhile (another process of this job)
            os.rename(tmp, folder)
    except OSError:
        if not (folder.exists() or folder.is_symlink()):
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if tmp.exists():  # not renamed: the folder was made meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
        if not is_scratch(folder):
            _refuse_foreign(folder, "use or replace")
    return folder


def remove_scratch(folder: str | Path) -> bool:
    """Remove the scratch folder ``folder`` if metadesign made it (it carries the marker); a folder without
    it (a user's) is never removed.  Returns whether it was removed."""
    if not is_scratch(folder):
        return False
    shutil.rmtree(folder, ignore_errors=True)
    return True


def fresh_scratch(out: str | Path, step: str | None = None) -> Path:
    """An empty scratch folder for output ``out`` (a job that does not resume: what an earlier, killed run
    left there is removed first; a folder there that metadesign did not make is refused): the path
    :func:`scratch_path` names, inside the freshly made (marked) ``OUT.partial``.  With ``step`` the path is
    not created: the job writes its product there (a zarr store, which empties its folder) and
    :func:`publish_scratch` moves it into place."""
    root = scratch_path(out)
    if root.exists() or root.is_symlink():
        if not remove_scratch(root):
            _refuse_foreign(root)
    make_scratch(root)
    return scratch_path(out, step)


def publish_scratch(src: str | Path, out: str | Path) -> Path:
    """Move the finished product ``src`` (made in ``out``'s scratch folder: ``OUT.partial`` itself or a step
    inside it) to ``out``, and remove the scratch folder: the scratch marker never becomes part of the
    product."""
    src, out = Path(src), Path(out)
    root = scratch_path(out)
    if src == root:
        (src / SCRATCH_MARK).unlink(missing_ok=True)
        os.rename(src, out)
    else:
        os.rename(src, out)
        remove_scratch(root)
    return out

"""The product layer (``metadesign.outputs``): every output metadesign writes goes through :func:`product`.

A command declares, before any work, its output, the output's *kind* and every input it reads::

    with product(out, "design", inputs={"recipe": recipe_path, "library": lib_path}, need=Need(disk=..)):
        ...  # write inside ``out`` (io.atomic_path / write_npz / save_figure ...)

and the layer refuses, with one line (:class:`~metadesign.validation.InputError`, exit 2 at the CLI),
nothing written:

* an output that is, contains or lies inside one of its inputs (a folder input declared with
  :class:`Input` ``members`` admits outputs beside its members: ``DATASET/evaluation``);
* an existing output that metadesign did not write (a user's file; a folder holding anything else,
  dot-files included) or that holds another kind of product (a unit-cell library where a supercell table
  is to be written);
* a folder at the output's resume-folder path (``OUT.partial``) that metadesign did not make (it carries no
  scratch marker, :data:`metadesign.tasks.SCRATCH_MARK`; an empty folder is a user's too): it would be
  taken for a resume folder and removed;
* a second writer of the same output while one works, whatever its recipe (an advisory ``flock`` the
  kernel drops when the writer dies, even by SIGKILL);
* a job whose estimated disk or memory (:class:`Need`) exceeds what the machine has free, with the
  estimate in the message.

Ownership is intrinsic, never a side list: a folder product carries the marker file ``.metadesign.json``
(its kind); a file product is recognised by the format tag it carries (the ``meta`` of a ``.npz``, the card
of a ``.safetensors``, the metadata of an ``.onnx``, the ``metadesign`` text chunk of a ``.png``, the
side-car of a layout, the header of a library CSV).  Folders written before the marker existed are
recognised by the format-tagged file they hold.

While a product is open its path is *claimed*: with :func:`io.enforce_claims` on (the CLI turns it on),
:func:`io.atomic_path`, the one low-level writer, refuses any target outside a claimed output, so a
command cannot write around this layer (the test suite runs every command so).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
import struct
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from .scratch import is_scratch, remove_scratch
from .io import atomic_write_text, claim, output_lock
from .plotting import PNG_KEY
from .validation import MEMORY_FRACTION, InputError, ValidationError, available_memory

__all__ = ["path_fields", "zarr_input", "temporary", "write_marker", "check_need", "MARKER", "KINDS", "Input", "Need", "product", "check_output", "identify", "kind_of_format",
           "PNG_KEY", "free_disk"]

#: marker file of a folder product (its kind, written first)
MARKER = ".metadesign.json"
MARKER_FORMAT = "metadesign.product/1"

#: every kind of product: name -> (what it is called in messages, folder?)
KINDS: dict[str, tuple[str, bool]] = {
    # files
    "unit-cell-library": ("unit-cell library", False),
    "supercells": ("supercell table", False),
    "coupling": ("coupling model", False),
    "ladder": ("convergence ladder", False),
    "active": ("active-learning report", False),
    "patches": ("patch study", False),
    "peds": ("PEDS supercell model", False),
    "unet": ("U-Net model", False),
    "refiner": ("refiner model", False),
    "onnx": ("ONNX model", False),
    "layout": ("layout", False),
    "figure": ("figure", False),
    "library-csv": ("library CSV", False),
    "design-file": ("design file", False),
    "psf-file": ("PSF file", False),
    "phasemap-file": ("phase-map file", False),
    "design-recipe": ("generated design recipe", False),
    # folders
    "design": ("design folder", True),
    "psf": ("PSF folder", True),
    "fab-study": ("fab-study folder", True),
    "phasemap": ("phase-map folder", True),
    "turbulence-validation": ("turbulence validation folder", True),
    "dataset": ("metadesign dataset", True),
    "training-run": ("training run", True),
    "evaluation": ("evaluation folder", True),
    "compare": ("comparison folder", True),
    "lpa-check": ("LPA check folder", True),
    "coupling-check": ("coupling check folder", True),
    "table-s2": ("Table S2 folder", True),
    "tolerance": ("tolerance study folder", True),
    "transfer": ("transfer study folder", True),
    "codesign": ("co-design report folder", True),
    "demo": ("demo folder", True),
    "pipeline": ("pipeline run folder", True),
    "loop": ("loop study folder", True),
    "loop-map": ("loop map folder", True),
    "polcam": ("polarisation-camera study folder", True),
    "captures": ("capture folder", True),
    "crosscheck": ("cross-check report folder", True),
}

#: folder kinds whose content identifies them (no marker file: a zarr store's ``zarr.json`` carries the
#: dataset's format, and a foreign file inside the store would confuse zarr and xarray)
INTRINSIC = {"dataset"}

#: format tags (``meta.format`` / card ``format``) -> kind
_FORMATS = {
    "metadesign.unit-cell-library": "unit-cell-library",
    "metadesign.supercells": "supercells",
    "metadesign.coupling": "coupling",
    "metadesign.ladder": "ladder",
    "metadesign.active": "active",
    "metadesign.patches": "patches",
    "metadesign.peds": "peds",
    "metadesign.unet": "unet",
    "metadesign.refiner": "refiner",
    "metadesign.onnx": "onnx",
    "metadesign.design": "design-file",
    "metadesign.psf": "psf-file",
    "metadesign.phasemap": "phasemap-file",
    "metadesign.dataset": "dataset",
    "metadesign.design-recipe": "design-recipe",
}

#: the first line of a recipe (TOML) that metadesign generated (a recipe a user wrote has none)
RECIPE_HEADER = "# format: metadesign.design-recipe/1"

#: folders written before the marker existed: kind -> (file inside, the kind that file must be); the file
#: must carry a metadesign format tag, or (for summaries without one) be JSON with the listed key
_LEGACY_FOLDERS: dict[str, tuple[tuple[str, str], ...]] = {
    "design": (("design.npz", "design-file"),),
    "psf": (("psf.npz", "psf-file"),),
    "phasemap": (("phasemap.npz", "phasemap-file"),),
    "dataset": (("zarr.json", "dataset"),),
    "training-run": (("model.safetensors", "unet"), ("model.safetensors", "refiner"),
                     ("checkpoint.pt", "torch-checkpoint")),
}

#: folders written before the marker existed whose summary carries no format tag: kind -> (the summary's
#: name, keys its top-level JSON object holds); a user's own file of that name would need all of them
_LEGACY_SUMMARIES: dict[str, tuple[str, set]] = {
    "demo": ("summary.json", {"output", "passed", "seconds", "stages"}),
    "evaluation": ("summary.json", {"n", "split", "noise", "npib", "captured_fraction"}),
    "compare": ("compare.json", {"settings", "summary", "wall_seconds"}),
    "loop": ("loop.json", {"format", "loop", "methods"}),
    "coupling-check": ("coupling-check.json", {"cases", "coupling_model_sha256"}),
    "lpa-check": ("lpa.json", {"lpa", "lpa_library", "n_harmonics_supercell"}),
    "tolerance": ("tolerance.json", {"model", "noise_percent", "rows"}),
    "transfer": ("transfer.json", {"fitted_alignment", "truth_alignment", "rows"}),
    "table-s2": ("table-s2.json", {"rows", "rytov", "epochs"}),
    "pipeline": ("pipeline-state.json", set()),
    "crosscheck": ("crosscheck.json", {"script", "arguments", "report"}),
}

#: the CSV header ``library export`` writes
LIBRARY_CSV_HEADER = ("wx_um,wy_um,t_x_re,t_x_im,t_y_re,t_y_im,phase_x_rad,phase_y_rad,t_xy_re,t_xy_im,t_yx_re,"
                      "t_yx_im,T0_x,T0_y,Ttot_x,Ttot_y,R_x,R_y")


def kind_of_format(fmt) -> str | None:
    """The kind a ``metadesign.<name>/<version>`` format tag names (None: not ours)."""
    if not isinstance(fmt, str) or "/" not in fmt:
        return None
    return _FORMATS.get(fmt.split("/", 1)[0])


def _what(kind: str) -> str:
    return KINDS[kind][0] if kind in KINDS else kind


# ------------------------------------------------------------------------------------------------ sniffing
def _npz_kind(path: Path) -> str | None:
    try:
        with zipfile.ZipFile(path) as zf, zf.open("meta.npy") as fh:
            arr = np.lib.format.read_array(fh, allow_pickle=False)
        return kind_of_format(json.loads(str(arr.reshape(-1)[0])).get("format"))
    except Exception:  # noqa: BLE001 - anything unreadable is not recognisably ours
        return None


def _json_format(path: Path) -> str | None:
    try:
        with open(path, encoding="utf-8") as fh:
            obj = json.load(fh)
    except Exception:  # noqa: BLE001
        return None
    if not isinstance(obj, dict):
        return None
    if "attributes" in obj and isinstance(obj["attributes"], dict):  # a zarr group
        return kind_of_format(obj["attributes"].get("format"))
    return kind_of_format(obj.get("format"))


def _safetensors_kind(path: Path) -> str | None:
    try:
        with open(path, "rb") as fh:
            n = struct.unpack("<Q", fh.read(8))[0]
            head = json.loads(fh.read(min(n, 1 << 24)))
        k = kind_of_format((head.get("__metadata__") or {}).get("format"))
    except Exception:  # noqa: BLE001
        k = None
    if k:
        return k
    for card in (path.with_name(path.name + ".json"), path.with_suffix(".json")):
        if card.is_file():
            k = _json_format(card)
            if k:
                return k
    return None


def _png_kind(path: Path) -> str | None:
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != b"\x89PNG\r\n\x1a\n":
                return None
            while True:
                head = fh.read(8)
                if len(head) < 8:
                    return None
                n, typ = struct.unpack(">I4s", head)
                if typ == b"IDAT" or typ == b"IEND":
                    return None
                data = fh.read(n)
                fh.read(4)
                if typ == b"tEXt" and data.split(b"\0", 1)[0] == PNG_KEY.encode():
                    return "figure"
    except OSError:
        return None


def _onnx_kind(path: Path) -> str | None:
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:  # metadata_props (field 14) follow the graph: the file's tail
            fh.seek(max(0, size - (1 << 20)))
            tail = fh.read()
    except OSError:
        return None
    return "onnx" if b"metadesign.onnx/" in tail else None


def _layout_kind(path: Path) -> str | None:
    side = path.with_name(path.name + ".json")
    try:
        obj = json.loads(side.read_text(encoding="utf-8"))
    except Exception:  # noqa: BLE001
        return None
    return "layout" if isinstance(obj, dict) and "provenance" in obj and "pillars" in obj else None


def _csv_kind(path: Path) -> str | None:
    try:
        with open(path, encoding="utf-8") as fh:
            first = fh.readline().strip()
    except (OSError, UnicodeDecodeError):
        return None
    return "library-csv" if first == LIBRARY_CSV_HEADER else None


def _checkpoint_kind(path: Path) -> str | None:
    """A torch checkpoint (``torch.save``: a zip holding ``*/data.pkl``), recognised without unpickling."""
    try:
        with zipfile.ZipFile(path) as zf:
            return "torch-checkpoint" if any(n.endswith("/data.pkl") for n in zf.namelist()) else None
    except (OSError, zipfile.BadZipFile):
        return None


def _toml_kind(path: Path) -> str | None:
    try:
        with open(path, encoding="utf-8") as fh:
            first = fh.readline().strip()
    except (OSError, UnicodeDecodeError):
        return None
    return kind_of_format(first.split(":", 1)[1].strip()) if first.startswith("# format:") else None


_FILE_SNIFFERS = {".pt": _checkpoint_kind, ".npz": _npz_kind, ".safetensors": _safetensors_kind, ".png": _png_kind,
                  ".onnx": _onnx_kind, ".oas": _layout_kind, ".gds": _layout_kind, ".csv": _csv_kind,
                  ".json": _json_format, ".toml": _toml_kind}


def _marker_kind(folder: Path) -> str | None:
    try:
        obj = json.loads((folder / MARKER).read_text(encoding="utf-8"))
    except Exception:  # noqa: BLE001
        return None
    if isinstance(obj, dict) and obj.get("format") == MARKER_FORMAT and obj.get("kind") in KINDS:
        return obj["kind"]
    return None


def identify(path: str | Path) -> str | None:
    """The kind of product at ``path`` if metadesign wrote it, else None."""
    path = Path(path)
    if path.is_symlink() or not path.exists():
        return None
    if path.is_dir():
        k = _marker_kind(path)
        if k:
            return k
        for kind, probes in _LEGACY_FOLDERS.items():
            for name, want in probes:
                f = path / name
                if f.is_file() and (_FILE_SNIFFERS.get(f.suffix, _json_format)(f)) == want:
                    return kind
        for kind, (name, keys) in _LEGACY_SUMMARIES.items():
            f = path / name
            if f.is_file():
                try:
                    obj = json.loads(f.read_text(encoding="utf-8"))
                except (OSError, ValueError, UnicodeDecodeError):
                    continue
                if isinstance(obj, dict) and keys <= set(obj):
                    return kind
        return None
    sniff = _FILE_SNIFFERS.get(path.suffix.lower())
    return sniff(path) if sniff else None


# ------------------------------------------------------------------------------------------------ inputs
@dataclass(frozen=True)
class Input:
    """A declared input.  ``members``: for a folder input, the names inside it that are read (an output
    elsewhere inside the folder is allowed, e.g. ``DATASET/evaluation``); None: the whole path."""

    path: str | Path
    members: tuple[str, ...] | None = None


def zarr_input(path: str | Path) -> Input:
    """A zarr store read as an input (a dataset): its members are the store's own nodes (``zarr.json`` and
    the folders holding one), so outputs beside them (``DATASET/evaluation``) are allowed."""
    p = Path(path)
    members = ["zarr.json"]
    if p.is_dir():
        members += [c.name for c in p.iterdir() if c.is_dir() and (c / "zarr.json").exists()]
    return Input(p, tuple(members))


def path_fields(obj, prefix: str = "", depth: int = 2) -> dict[str, Path]:
    """The paths a recipe object names (its ``Path`` fields, and those of nested dataclasses): what a study
    declares as its inputs."""
    out: dict[str, Path] = {}
    if not dataclasses.is_dataclass(obj) or depth < 0:
        return out
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name, None)
        name = f"{prefix}{f.name}"
        if isinstance(v, Path):
            out[name] = v
        elif isinstance(v, (list, tuple)) and v and all(isinstance(x, Path) for x in v):
            out.update({f"{name}[{i}]": x for i, x in enumerate(v)})
        elif dataclasses.is_dataclass(v):
            out.update(path_fields(v, name + ".", depth - 1))
    return out


def _overlaps(out: Path, inp: Input) -> bool:
    o = out.resolve()
    q = Path(inp.path).resolve()
    if o == q or o in q.parents:
        return True
    if q in o.parents:
        if inp.members is None:
            return True
        first = o.relative_to(q).parts[0]
        return first in inp.members
    return False


# ------------------------------------------------------------------------------------------------ resources
@dataclass(frozen=True)
class Need:
    """What a job will need at its peak: ``disk`` bytes in the output's file system, ``memory`` bytes of
    RAM; ``what`` says what to change to need less (appended to the refusal)."""

    disk: float = 0.0
    memory: float = 0.0
    what: str = ""


def free_disk(path: Path) -> float:
    p = Path(path).resolve()
    while not p.exists():
        p = p.parent
    return float(shutil.disk_usage(p).free)


def _gb(b: float) -> str:
    return f"{b / 1e9:.3g} GB" if b >= 1e8 else f"{b / 1e6:.3g} MB"


def check_need(out: Path, need: Need | None) -> None:
    if need is None:
        return
    msgs = []
    if need.disk > 0:
        free = free_disk(out.parent)
        if need.disk > free:
            msgs.append(f"about {_gb(need.disk)} of disk in {out.parent} ({_gb(free)} free)")
    if need.memory > 0:
        avail = available_memory() * MEMORY_FRACTION
        if need.memory > avail:
            msgs.append(f"about {_gb(need.memory)} of memory ({_gb(avail)} available)")
    if msgs:
        raise InputError(f"{out}: this job needs " + " and ".join(msgs)
                         + (f"; {need.what}" if need.what else "") + " (nothing written)")


# ------------------------------------------------------------------------------------------------ checks
def check_output(out: str | Path, kind: str, inputs: Mapping[str, str | Path | Input | None] | None = None,
                 also: tuple[str | Path, ...] = (), need: Need | None = None,
                 scratch: tuple[str | Path, ...] = ()) -> Path:
    """Every refusal of :func:`product`, done before any work (one-line InputError).  ``also``: further
    files the product writes beside a file output (a card, a figure): each must be absent or ours.
    ``scratch``: the product's resume folders beside it (``OUT.partial``): each absent or a folder metadesign
    made (it carries :data:`metadesign.tasks.SCRATCH_MARK`)."""
    if kind not in KINDS:
        raise ValueError(f"unknown product kind {kind!r}")
    out = Path(out)
    what, folder = KINDS[kind]
    for name, p in (inputs or {}).items():
        if p is None:
            continue
        inp = p if isinstance(p, Input) else Input(p)
        if _overlaps(out, inp):
            raise InputError(f"{out}: the output overlaps the input {name} {inp.path} "
                             "(an input is never its own output)")
    pkg = Path(__file__).resolve().parent
    if pkg == out.resolve() or pkg in out.resolve().parents:
        raise InputError(f"{out}: inside the installed metadesign package ({pkg}); outputs go to a folder of "
                         "yours (-o, or run the command from your working directory)")
    if not out.parent.resolve().is_dir():
        raise InputError(f"{out}: folder {out.parent} does not exist (create it first)")
    _check_existing(out, kind, what, folder)
    if not folder and not out.exists():  # an existing product vouches for its companions (card, figure)
        for extra in also:
            extra = Path(extra)
            if extra.exists() or extra.is_symlink():
                if extra.is_dir() or extra.is_symlink():
                    raise InputError(f"{extra}: exists and is not a file metadesign wrote (refusing to replace it)")
                if identify(extra) is None:
                    raise InputError(f"{extra}: exists and metadesign did not write it (refusing to replace it: "
                                     "move it or choose another output)")
    for sc in scratch:
        sc = Path(sc)
        if sc.is_symlink() or (sc.exists() and not sc.is_dir()):
            raise InputError(f"{sc}: exists and is not the resume folder metadesign keeps there (refusing to "
                             "replace it)")
        if sc.is_dir() and not is_scratch(sc):  # a user's folder, even an empty one: never resumed, never removed
            raise InputError(f"{sc}: exists and metadesign did not make it (it is where {out}'s resume folder "
                             "goes: move it)")
    check_need(out, need)
    return out


def _check_existing(out: Path, kind: str, what: str, folder: bool) -> None:
    """An existing output: replaceable only when it is metadesign's product of this kind."""
    if folder and (out.is_symlink() or (out.exists() and not out.is_dir())):
        raise InputError(f"{out}: exists and is not a folder (refusing to replace it; a {what} is a folder)")
    if not folder and out.is_dir():
        raise InputError(f"{out}: is a folder, expected a file path")
    if not folder and out.is_symlink():
        raise InputError(f"{out}: is a symbolic link (refusing to replace it)")
    if not out.exists() or (folder and not any(out.iterdir())):
        return
    have = identify(out)
    if have == kind:
        return
    if have is None and kind == "figure" and identify(out.parent) is not None:
        return  # a figure inside a metadesign product folder, drawn before figures carried their mark
    if have is not None:
        raise InputError(f"{out}: holds a {_what(have)}, not a {what} (refusing to "
                         f"{'write into' if folder else 'replace'} it: choose another output)")
    if folder:
        raise InputError(f"{out}: exists and is not a {what} (it holds files metadesign did not write; refusing to "
                         "write into or replace it: choose another output)")
    raise InputError(f"{out}: exists and metadesign did not write it (refusing to replace it: move it or choose "
                     "another output)")


def write_marker(folder: Path, kind: str) -> None:
    if kind in INTRINSIC:
        return
    atomic_write_text(folder / MARKER, json.dumps({"format": MARKER_FORMAT, "kind": kind}, sort_keys=True) + "\n")


@contextlib.contextmanager
def product(out: str | Path, kind: str, inputs: Mapping[str, str | Path | Input | None] | None = None,
            also: tuple[str | Path, ...] = (), need: Need | None = None,
            scratch: tuple[str | Path, ...] = ()) -> Iterator[Path]:
    """Open output ``out`` of ``kind`` for writing (see the module's docstring): checks, then the lock,
    then (a folder) the marker; the block writes inside ``out``, ``also`` and ``scratch``.  A folder this
    call created is removed again if the block fails before writing anything but the marker, and whatever it
    holds if the block ends in a refusal (a ValidationError: an input found bad after the work began leaves
    nothing behind); so are the scratch folders the call created (marked ones only).  An interruption keeps
    them (the job resumes)."""
    out = check_output(out, kind, inputs, also, need, scratch)
    folder = KINDS[kind][1]
    with output_lock(out, _what(kind)):
        check_output(out, kind, inputs, also, None, scratch)  # again under the lock: a writer may have finished
        created = False
        if folder:
            created = not out.exists()
            out.mkdir(exist_ok=True)
        new_scratch = [Path(s) for s in scratch if not (Path(s).exists() or Path(s).is_symlink())]
        with claim(out, *also, *scratch):
            ok = refused = False
            try:
                if folder and kind not in INTRINSIC and _marker_kind(out) != kind:
                    write_marker(out, kind)
                yield out
                ok = True
            except ValidationError:
                refused = True
                raise
            finally:
                if not ok and created and out.is_dir() and (refused or {p.name for p in out.iterdir()} <= {MARKER}):
                    shutil.rmtree(out, ignore_errors=True)
                if refused:
                    for s in new_scratch:
                        remove_scratch(s)


@contextlib.contextmanager
def temporary(prefix: str = "metadesign-") -> Iterator[Path]:
    """A temporary folder, claimed while the block runs and removed after it (intermediate products a
    command builds and throws away)."""
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp, claim(tmp):
        yield Path(tmp)

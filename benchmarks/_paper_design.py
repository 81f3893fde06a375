"""Shared by the benchmarks that run on the paper design folder (not a benchmark itself).

The cross-check scripts (``crosscheck_*.py``) write their report through the product layer
(:func:`metadesign.outputs.product`) with ``-o FOLDER``: the folder is checked before any work (a user's file
or folder there, an input as the output, a user's folder at ``FOLDER.partial``: refused in one line, exit 2,
nothing written), the solves go to its resume folder ``FOLDER.partial`` (content-keyed: a rerun after a kill
reuses the finished ones), the report is written atomically as ``FOLDER/crosscheck.json`` (the script, its
arguments, the report) and the resume folder removed.  Without ``-o`` they print only, the solves in a
temporary folder removed afterwards."""

import contextlib
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: the report file inside a cross-check's output folder
REPORT = "crosscheck.json"


def design_arguments(ap) -> None:
    """The design folder (default: the paper design), the worker count and ``--json``."""
    ap.add_argument("design", nargs="?", default=str(REPO / "layouts" / "paper-5mm"))
    ap.add_argument("-j", "--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true")


def output_arguments(ap) -> None:
    """``-o/--output FOLDER``: the report folder (default: print only)."""
    ap.add_argument("-o", "--output", metavar="FOLDER",
                    help=f"write the report to FOLDER/{REPORT} (the solves in FOLDER.partial: resumed after a kill, "
                    "removed once the report is written); default: print only")


def has_design(design) -> bool:
    """Whether the design folder holds a design; False after one line on stderr (the README's layout section
    makes it)."""
    if (Path(design) / "design.npz").exists():
        return True
    print(f"{design}: no design.npz (make it: metadesign design layouts/paper-5mm.toml)", file=sys.stderr)
    return False


def paper_device(design):
    """The design folder's as-fabricated device with torch at one thread, or None after one line on stderr
    when the folder has no design (the README's layout section makes it)."""
    if not has_design(design):
        return None
    import torch

    torch.set_num_threads(1)
    from metadesign.design.store import load_design
    from metadesign.sensing.model import AsFabricated

    return AsFabricated.from_design(load_design(design))


def patch_arguments(ap, patches: int) -> None:
    """The patch draw of `library patches` (count, seed) and a folder to keep the solves in."""
    ap.add_argument("--patches", type=int, default=patches)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--partial", help="folder of the solves (resumable, kept; default: the output's FOLDER.partial, "
                    "or a temporary one without -o)")


def paper_patches(a, partial=None):
    """``(library, patches (n, 4, 4, 2), partial folder)`` of the design folder ``a.design`` drawn as `library
    patches` draws them (``a.patches``, ``a.seed``), or None after one line on stderr without a design.  The
    partial folder: ``a.partial``, else ``partial``, else a new temporary one."""
    import tempfile

    if not has_design(a.design):
        return None
    from metadesign.design.store import design_library, load_design
    from metadesign.studies.supercells import design_patches

    d = load_design(a.design)
    if a.partial:
        partial = Path(a.partial)
    elif partial is None:
        partial = Path(tempfile.mkdtemp(prefix="patches-"))
    return design_library(d, None), design_patches(d, a.patches, a.seed), Path(partial)


@contextlib.contextmanager
def report_output(out, inputs=None, keep=None):
    """Context manager yielding ``(folder or None, scratch folder)``.  ``out``: the report folder (``-o``),
    opened with :func:`metadesign.outputs.product` (kind ``crosscheck``, ``inputs`` declared, its resume
    folder ``OUT.partial`` checked) before the block runs; the scratch folder is ``OUT.partial``
    (:func:`~metadesign.execution.scratch_path`; the solvers make it, marked, and their steps inside it),
    removed when the block completes, kept when it fails or is interrupted (a rerun resumes it).  ``out``
    None: ``(None, a temporary folder)`` removed afterwards.  ``keep``: a folder of the user's for the solves
    instead (``--partial``), never removed."""
    from metadesign.execution import remove_scratch, scratch_path
    from metadesign.outputs import product, temporary

    if out is None:
        if keep is not None:
            yield None, Path(keep)
            return
        with temporary("crosscheck-") as tmp:
            yield None, tmp
        return
    with product(out, "crosscheck", inputs=inputs, scratch=(scratch_path(out),)) as folder:
        yield folder, Path(keep) if keep is not None else scratch_path(folder)
        remove_scratch(scratch_path(folder))


def write_report(folder, script: str, arguments: dict, report: dict):
    """``folder/crosscheck.json`` written atomically: ``{"script", "arguments", "report"}``; the path, or
    None without a folder (print only)."""
    if folder is None:
        return None
    from metadesign.io import atomic_write_text

    path = Path(folder) / REPORT
    atomic_write_text(path, json.dumps({"script": script, "arguments": arguments, "report": report}, indent=2)
                      + "\n")
    return path


def crosscheck(a, script: str, inputs: dict, compute, show, keep=None) -> int:
    """A cross-check's run: the report folder ``a.output`` opened (:func:`report_output`), ``compute(scratch)``
    -> the report, written (:func:`write_report`), then printed as JSON (``a.json``) or by ``show(report)``.
    A refusal (:class:`~metadesign.validation.ValidationError`): one line on stderr, exit 2."""
    from metadesign.validation import ValidationError

    try:
        with report_output(a.output, inputs, keep) as (folder, scratch):
            rep = compute(scratch)
            write_report(folder, script, vars(a), rep)
    except ValidationError as exc:
        print(f"{script}: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(rep, indent=2))
    else:
        show(rep)
    return 0

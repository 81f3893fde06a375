"""Shared by the benchmarks that run on the paper design folder (not a benchmark itself)."""

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def design_arguments(ap) -> None:
    """The design folder (default: the paper design), the worker count and ``--json``."""
    ap.add_argument("design", nargs="?", default=str(REPO / "layouts" / "paper-5mm"))
    ap.add_argument("-j", "--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true")


def paper_device(design):
    """The design folder's as-fabricated device with torch at one thread, or None after one line on stderr
    when the folder has no design (the README's layout section makes it)."""
    if not (Path(design) / "design.npz").exists():
        print(f"{design}: no design.npz (make it: metadesign design layouts/paper-5mm.toml)", file=sys.stderr)
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
    ap.add_argument("--partial", help="folder of the solves (resumable; default: a temporary one)")


def paper_patches(a):
    """``(library, patches (n, 4, 4, 2), partial folder)`` of the design folder ``a.design`` drawn as `library
    patches` draws them (``a.patches``, ``a.seed``), or None after one line on stderr without a design."""
    import tempfile

    if not (Path(a.design) / "design.npz").exists():
        print(f"{a.design}: no design.npz (make it: metadesign design layouts/paper-5mm.toml)", file=sys.stderr)
        return None
    from metadesign.design.store import design_library, load_design
    from metadesign.studies.supercells import design_patches

    d = load_design(a.design)
    partial = Path(a.partial) if a.partial else Path(tempfile.mkdtemp(prefix="patches-"))
    return design_library(d, None), design_patches(d, a.patches, a.seed), partial

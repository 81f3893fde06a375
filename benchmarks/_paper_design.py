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

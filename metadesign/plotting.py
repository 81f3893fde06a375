"""Shared plotting edge: headless matplotlib and atomic figure saving."""

from __future__ import annotations

from pathlib import Path

from .io import atomic_path

#: the PNG text chunk that marks a figure as metadesign's (metadesign.outputs recognises it)
PNG_KEY = "metadesign"

__all__ = ["pyplot", "save_figure"]


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, out: str | Path, dpi: int = 120) -> Path:
    out = Path(out)
    plt = pyplot()
    with atomic_path(out) as tmp:
        # metadata without the creation date: same inputs, same bytes
        fig.savefig(tmp, dpi=dpi, format=out.suffix.lstrip(".") or "png",
                    metadata={"Software": None, PNG_KEY: "figure"} if out.suffix == ".png" else None)
    plt.close(fig)
    return out

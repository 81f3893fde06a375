"""The error statistics the supercell studies share: per polarisation, per row source, as a histogram."""

from __future__ import annotations


import numpy as np

from .supercell_table import SOURCES


def _stats(e: np.ndarray) -> dict:
    """Mean, median, 90th percentile and max per polarisation of errors (n, 2)."""
    return {"mean": e.mean(0).tolist(), "median": np.median(e, 0).tolist(), "p90": np.percentile(e, 90, 0).tolist(),
            "max": e.max(0).tolist()}


def _by_source(source: np.ndarray, e: np.ndarray, e_lpa: np.ndarray) -> dict:
    """The held-out errors of a model and of the LPA per row source (:data:`SOURCES`)."""
    out = {}
    for s, name in enumerate(SOURCES):
        sel = source == s
        if sel.any():
            out[name] = {"n": int(sel.sum()), "model": _stats(e[sel]), "lpa": _stats(e_lpa[sel])}
    return out


def _error_histogram(ax, e: np.ndarray, e_lpa: np.ndarray, name: str, top: float) -> None:
    """The held-out error distributions of a model and of the LPA on one axis (bins up to ``top``)."""
    bins = np.linspace(0, top, 40)
    ax.hist(e_lpa, bins, alpha=0.6, color="C3", label=f"LPA (mean {e_lpa.mean():.3f})")
    ax.hist(e, bins, alpha=0.6, color="C0", label=f"{name} (mean {e.mean():.3f})")
    ax.set(xlabel="|t - t_RCWA| / rms|t_i| (both polarisations)", ylabel="held-out supercells x pol",
           title="held-out error")
    ax.legend(fontsize=8)

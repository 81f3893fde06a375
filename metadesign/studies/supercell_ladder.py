"""The convergence ladder of a supercell table's labels: held-out rows re-solved at rising truncation."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..execution import SERIAL, Execution
from ..library.coupling import lpa_t, relative_error
from ..library.store import interpolate_t
from ..library.supercells import (
    SupercellTable,
    matched_unit_harmonics,
    solve_table,
)
from .supercell_errors import _stats

__all__ = ["convergence_ladder"]


def convergence_ladder(table: SupercellTable, lib, rows: np.ndarray, harmonics, partial: Path,
                       run: Execution = SERIAL) -> dict:
    """Rows ``rows`` of ``table`` re-solved at each requested truncation of ``harmonics`` (ascending), each
    with its unit cells at the matched truncation; per level the label in the library's frame (LPA + the
    coupling measured there, :meth:`SupercellTable.labels`), and between consecutive levels its change in
    units of the pillars' rms ``|t|`` (the convergence of a label: the goal is <= 0.01), beside the change of
    the raw supercell ``t``.  Chunks under ``partial/level-<nG>`` (resumable)."""
    rows = np.asarray(rows)
    w = table.widths[rows]
    tu = interpolate_t(lib, w[..., 0], w[..., 1])[0]
    lpa = lpa_t(tu)
    levels = []
    for h in sorted(int(v) for v in harmonics):
        ns, nu = matched_unit_harmonics(h, lib.stack)
        t0 = time.perf_counter()
        t, nG, _, t_unit = solve_table(w, lib.stack, ns, Path(partial) / f"level-{ns - 1}", workers=run.workers,
                                       scheduler=run.scheduler, chunk_size=1, unit_harmonics=nu, progress=run.progress,
                                       log=run.log)
        levels.append({"n_harmonics": nG, "unit_n_harmonics": nu - 1, "t": t, "t_unit": t_unit,
                       "label": lpa + t - t_unit.mean((1, 2)), "seconds": time.perf_counter() - t0})
        run.log(f"  nG {nG}: {len(rows)} supercells in {levels[-1]['seconds']:.0f} s")
    steps = []
    for a, b in zip(levels[:-1], levels[1:]):
        d_label = relative_error(b["label"], a["label"], tu)
        d_raw = relative_error(b["t"], a["t"], tu)
        steps.append({"from": a["n_harmonics"], "to": b["n_harmonics"], "label_change": _stats(d_label),
                      "raw_t_change": _stats(d_raw), "label_change_max_both": float(d_label.max()),
                      "label_change_mean_both": float(d_label.mean()),
                      "label_change_per_row": d_label.max(1).tolist()})
    at_table = None
    nG_table = table.meta.get("n_harmonics")
    top = levels[-1]
    ref_labels = table.rows(rows).labels(lpa)
    at_table = {"n_harmonics": nG_table, "vs_top_level": _stats(relative_error(ref_labels, top["label"], tu))}
    return {"rows": rows.tolist(), "levels": [{k: v for k, v in lv.items() if k not in ("t", "t_unit", "label")}
                                              for lv in levels],
            "steps": steps, "table_labels": at_table,
            "_labels": np.stack([lv["label"] for lv in levels])}

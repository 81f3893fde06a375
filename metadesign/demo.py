"""``metadesign demo``: the embedded demo through every stage built so far."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .io import atomic_write_text
from .paths import default_library_path

__all__ = ["run_demo"]


def _stage_library(out: Path, log) -> dict:
    from .library.plot import plot_library
    from .library.rcwa import SolverSettings, Stack, solve_cell
    from .library.store import load_library

    lib = load_library(default_library_path())
    s = lib.summary()
    fig = plot_library(lib, out / "library-fig-s1.png")
    # spot-check the committed table with fresh RCWA solves
    st = lib.meta["stack"]
    stack = Stack(st["wavelength_m"], st["period_m"], st["height_m"], st["n_pillar"], st["n_substrate"],
                  st["n_superstrate"])
    settings = SolverSettings(lib.meta["solver"]["n_harmonics_requested"])
    idx = [(40, 20), (8, 72), (60, 60)]
    err = max(float(np.abs(solve_cell(lib.wx[i], lib.wy[j], stack, settings).jones - lib.jones[i, j]).max())
              for i, j in idx)
    log(f"library: {s['grid']['n_wx']} x {s['grid']['n_wy']} cells, {100 * s['fraction_above_threshold']:.1f} % "
        f"with T0 >= 70 %, re-solve error {err:.1e}")
    return {"summary": s, "respot_check_max_abs_error": err, "figures": [str(fig)]}


def run_demo(out: Path, log: Callable[[str], None] = print) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result: dict = {"output": str(out), "stages": {}}
    result["stages"]["library"] = _stage_library(out, log)
    result["seconds"] = time.perf_counter() - t0
    lib = result["stages"]["library"]["summary"]
    lines = [
        f"metadesign demo -> {out}/",
        f"  stage 1 library   {lib['grid']['n_wx']}x{lib['grid']['n_wy']} cells, nG {lib['solver']['n_harmonics']}, "
        f"convergence {lib['convergence']['max_phase_change_rad']:.4f} rad, "
        f"{100 * lib['fraction_above_threshold']:.1f} % cells T0 >= 70 %, "
        f"RCWA re-check {result['stages']['library']['respot_check_max_abs_error']:.1e}",
        f"  figures           " + ", ".join(Path(f).name for st in result["stages"].values() for f in st["figures"]),
        f"  time              {result['seconds']:.1f} s",
    ]
    result["text"] = "\n".join(lines)
    atomic_write_text(out / "summary.json", json.dumps({k: v for k, v in result.items() if k != "text"},
                                                      indent=2, sort_keys=True, default=float))
    return result

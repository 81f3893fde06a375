"""The ``library lpa-check`` command: the local-periodic approximation's error on a design."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..cliutil import emit, integer, limit_arg, log_to, num, out_dir, progress_bar, workers_arg
from ..design.store import design_file
from ..outputs import product, zarr_input

__all__ = ["register"]


def _cmd_lpa(a: argparse.Namespace) -> int:
    import numpy as np

    from ..execution import Execution
    from .lpa import LpaSettings, downstream_of, lpa_study

    src = Path(a.design)
    out = out_dir(a.output or (src.parent if src.is_file() else src) / "lpa-check")
    downstream = downstream_of(a.dataset, a.model, a.samples, a.noise, a.seed)
    run = Execution(workers=a.workers, log=log_to(a.json),
                    progress=None if a.json else progress_bar("supercells", unit="cell"))
    inputs = {"design": design_file(src), "--dataset": zarr_input(a.dataset) if a.dataset else None,
              "--model": a.model}
    with product(out, "lpa-check", inputs):
        rep = lpa_study(src, out, LpaSettings(a.supercells, a.harmonics, a.seed, a.check), downstream, run)
    L, Ll = rep["lpa"], rep["lpa_library"]
    lines = [f"LPA error on {rep['supercells']} supercells (RCWA nG {rep['n_harmonics_supercell']}, unit cells nG "
             f"{rep['n_harmonics_unit']}; 1.5x harmonics change <= "
             + ("/".join(f"{v:.1e}" for v in rep["convergence_rel_change_max"]) if rep["convergence_rel_change_max"]
                else "-") + f") -> {out}",
             "                       x-pol        y-pol",
             f"  |eps| mean          {L['rel_magnitude_mean'][0]:.4f}       {L['rel_magnitude_mean'][1]:.4f}",
             f"  |eps| median / p90  {L['rel_magnitude_median'][0]:.3f}/{L['rel_magnitude_p90'][0]:.3f}  "
             f"{L['rel_magnitude_median'][1]:.3f}/{L['rel_magnitude_p90'][1]:.3f}",
             f"  phase RMS [rad]     {L['phase_rms_rad'][0]:.4f}       {L['phase_rms_rad'][1]:.4f}",
             f"  |dt| / rms|t_i|     {L['abs_error_over_unit_rms_mean'][0]:.4f}       "
             f"{L['abs_error_over_unit_rms_mean'][1]:.4f}",
             f"  |1+eps| mean        {L['amplitude_ratio_mean'][0]:.4f}       {L['amplitude_ratio_mean'][1]:.4f}",
             f"  vs library |eps|    {Ll['rel_magnitude_mean'][0]:.4f}       {Ll['rel_magnitude_mean'][1]:.4f}",
             "  corr(|eps|, width contrast) "
             + " / ".join("-" if v is None else f"{v:+.2f}" for v in rep["corr_error_vs_width_contrast"])]
    d = rep.get("downstream")
    if d:
        lines.append(f"  NPiB ({d['samples']} test samples, {d['noise_percent']:g} % noise): nominal "
                     f"{d['nominal']['npib_unet']:.4f}, independent {d['independent']['npib_unet']:.4f}, correlated "
                     f"{d['correlated']['npib_unet']:.4f} (none {d['npib_none']:.3f}, conjugate "
                     f"{d['npib_phase_conjugate']:.3f})")
        for k in ("focusing_efficiency", "strehl", "crosstalk"):
            v = [np.mean([c[k] for c in d[m]["channels"]]) for m in ("nominal", "independent", "correlated")]
            lines.append(f"  mean {k:<20} {v[0]:.4f} -> {v[1]:.4f} (independent), {v[2]:.4f} (correlated)")
    emit(rep, a.json, "\n".join(lines))
    return 0


def _add_lpa_check(sub) -> None:
    lp = sub.add_parser(
        "lpa-check", help="measure the local-periodic approximation's error with supercell RCWA",
        description="Solve random 2 x 2 supercells of a design with RCWA (four different pillars, both "
        "polarisations) and compare their 0th-order transmission with the LPA (the mean of the four unit-cell "
        "values); with --dataset and --model, apply the measured error to the device pupil and report the "
        "channel metrics and the model's NPiB.")
    lp.add_argument("design", help="layout (.oas/.gds) or design folder")
    lp.add_argument("--supercells", type=integer(1, 100000), default=32, help="supercells to solve (default 32)")
    lp.add_argument("--harmonics", type=integer(50, 5000), default=800,
                    help="supercell harmonics requested (default 800: the library's resolution at period 2p)")
    lp.add_argument("--check", type=integer(0, 100), default=2,
                    help="supercells re-solved at 1.5x the harmonics (convergence; default 2)")
    lp.add_argument("--seed", type=integer(0, 2**63 - 1), default=0)
    lp.add_argument("--dataset", help="dataset whose device pupil and test samples serve the downstream study")
    lp.add_argument("--model", help="U-Net weights for the downstream NPiB")
    limit_arg(lp, "at most this many test samples downstream (64)", type=integer(1, 100000), default=64)
    lp.add_argument("--noise-percent", "--noise", dest="noise", type=num(0, 100, unit="%"), default=5.0,
                    help="sensor noise downstream, %% of peak (5)")
    lp.add_argument("-o", "--output", help="output folder (default: lpa-check/ beside the design)")
    workers_arg(lp)
    lp.add_argument("--json", action="store_true", help="print the report as JSON")
    lp.set_defaults(func=_cmd_lpa)


def register(sub, groups: dict) -> None:
    """Add ``lpa-check`` to the ``library`` group."""
    _add_lpa_check(groups["library"])

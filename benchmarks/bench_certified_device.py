"""A whole device under the certified (PEDS) model (#34), sampled: the coupled device's pupil (every
supercell, pair tables), the certified correction on N sampled supercells (the PEDS solves on the local
pool), the spot metrics with their jackknife errors; against the projection of running the PEDS model on
every supercell of the device, measured per supercell in the same run.

    python benchmarks/bench_certified_device.py [layouts/paper-5mm] [--supercells 4000] [--ring N] [-j 2] [--json]

``--ring N``: the neighbour ring too (overlapping windows: the certified model on the three 2 x 2 windows
straddling each of the first N sampled supercells), timed apart, with its effect on the matched sample.

The design folder is the paper design (`metadesign design layouts/paper-5mm.toml`, as the README's
layout section makes it)."""

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _paper_design import design_arguments, paper_device  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    design_arguments(ap)
    ap.add_argument("--supercells", type=int, default=4000)
    ap.add_argument("--replicates", type=int, default=8)
    ap.add_argument("--ring", type=int, default=0, help="neighbour-ring supercells (0: none)")
    a = ap.parse_args(argv)
    fab = paper_device(a.design)
    if fab is None:
        return 2
    from metadesign.sensing.model import load_sensing_recipe
    from metadesign.execution import Execution
    from metadesign.studies.coupling_check import CertifiedSettings, SampledDevice, certified_case

    sr = load_sensing_recipe(REPO / "sensing" / "paper.toml")
    fab = fab.with_coupling("supercell")
    t0 = time.perf_counter()
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid)
    t_pupil = time.perf_counter() - t0
    partial = Path(tempfile.mkdtemp(prefix="bench-certified-"))
    try:
        t0 = time.perf_counter()
        case = certified_case(SampledDevice(fab, cp, sr.sensor, sr.pupil_grid), CertifiedSettings(
            a.supercells, a.replicates, ring_supercells=a.ring), partial, run=Execution(workers=a.workers))
        t_case = time.perf_counter() - t0
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    n, N = case["sampling"]["supercells"], case["sampling"]["eligible_supercells"]
    ring = case["with_ring"]["ring"] if "with_ring" in case else None
    t_ring = ring["seconds"] if ring else 0.0
    per = (case["seconds_solves"] - t_ring) * a.workers / n  # core-seconds per certified supercell, this run
    full_h = N * per / 3600
    eff, se = case["mean"]["spot_efficiency"], case["stderr"]["spot_efficiency"]
    rep = {"supercells_sampled": n, "device_supercells": N, "workers": a.workers,
           "coupled_pupil_seconds": t_pupil, "certified_case_seconds": t_case,
           "certified_core_seconds_per_supercell": per, "every_supercell_core_hours": full_h,
           "every_supercell_hours_on_these_workers": full_h / a.workers,
           "speedup_vs_every_supercell": full_h * 3600 / a.workers / t_case,
           "spot_efficiency": eff, "spot_efficiency_stderr": se, "stderr": case["stderr"], "mean": case["mean"],
           "ring": None if not ring else {"supercells": ring["supercells"], "windows": ring["windows"],
                                          "seconds": t_ring, "core_seconds_per_window":
                                          t_ring * a.workers / max(1, ring["windows"]),
                                          "effect": ring["effect"]}}
    if a.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f"coupled device pupil (all {N:,} supercells, pair tables): {t_pupil:.1f} s")
    print(f"certified case, {n} sampled supercells on {a.workers} workers: {t_case:.0f} s "
          f"({t_case / 60:.1f} min; goal <= 10 min)")
    print(f"  certified model: {per:.3f} core-s per supercell -> every supercell: {full_h:.0f} core-hours "
          f"({full_h / a.workers:.0f} h on {a.workers} workers), {rep['speedup_vs_every_supercell']:.0f}x the "
          "sampled case")
    if ring:
        e = ring["effect"]
        print(f"  neighbour ring (overlapping windows): {ring['windows']} windows of {ring['supercells']} supercells "
              f"in {t_ring:.0f} s ({rep['ring']['core_seconds_per_window']:.2f} core-s per window); its effect: "
              f"spot efficiency {e['spot_efficiency']['mean']:+.5f} +- {e['spot_efficiency']['stderr']:.5f}, "
              f"Strehl {e['spot_strehl']['mean']:+.4f} +- {e['spot_strehl']['stderr']:.4f}")
    print(f"  spot efficiency {eff:.5f} +- {se:.5f} ({100 * se / eff:.2f} %), Strehl "
          f"{case['mean']['spot_strehl']:.4f} +- {case['stderr']['spot_strehl']:.4f}, stray "
          f"{case['mean']['stray']:.4f} +- {case['stderr']['stray']:.4f}, |focal shift| "
          f"{1e3 * case['mean']['focal_shift_mm']:.1f} +- {1e3 * case['stderr']['focal_shift_mm']:.1f} um")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

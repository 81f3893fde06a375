"""A whole device under the certified (PEDS) model (#34), sampled: the coupled device's pupil (every
supercell, pair tables), the certified correction on N sampled supercells (the PEDS solves on the local
pool), the spot metrics with their jackknife errors; against the projection of running the PEDS model on
every supercell of the device, measured per supercell in the same run.

    python benchmarks/bench_certified_device.py [layouts/paper-5mm] [--supercells 4000] [--ring N] [-j 2] [--json]

``--ring N``: the neighbour ring too (the ring model in library/, on the first N sampled supercells: each
one's 4 x 4 patch solved at the ring model's levels), timed apart.

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
    from metadesign.studies.coupling_check import certified_case

    sr = load_sensing_recipe(REPO / "sensing" / "paper.toml")
    fab = fab.with_coupling("supercell")
    t0 = time.perf_counter()
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid)
    t_pupil = time.perf_counter() - t0
    partial = Path(tempfile.mkdtemp(prefix="bench-certified-"))
    try:
        t0 = time.perf_counter()
        case = certified_case(fab, cp, sr.sensor, sr.pupil_grid, a.supercells, a.replicates, partial,
                              workers=a.workers, ring=True if a.ring else None, ring_supercells=a.ring or None)
        t_case = time.perf_counter() - t0
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    n, N = case["sampling"]["supercells"], case["sampling"]["eligible_supercells"]
    ring = case["ring"]
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
           "ring": None if not ring else {"supercells": ring["supercells"], "patches": ring["patches"],
                                          "seconds": t_ring, "core_seconds_per_patch":
                                          t_ring * a.workers / max(1, ring["patches"])}}
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
        print(f"  neighbour ring: {ring['patches']} patches of {ring['supercells']} supercells in {t_ring:.0f} s "
              f"({rep['ring']['core_seconds_per_patch']:.2f} core-s per patch)")
    print(f"  spot efficiency {eff:.5f} +- {se:.5f} ({100 * se / eff:.2f} %), Strehl "
          f"{case['mean']['spot_strehl']:.4f} +- {case['stderr']['spot_strehl']:.4f}, stray "
          f"{case['mean']['stray']:.4f} +- {case['stderr']['stray']:.4f}, |focal shift| "
          f"{1e3 * case['mean']['focal_shift_mm']:.1f} +- {1e3 * case['stderr']['focal_shift_mm']:.1f} um")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

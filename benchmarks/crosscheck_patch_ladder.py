"""The convergence of the neighbour-ring labels (#34): the first P patches of the patch study (the same
draw: `library patches --seed`) solved at a ladder of truncations, each with its four supercells and
sixteen unit cells matched, and per step the change of the ring term (patch minus the mean of its four
supercells, the label the ring model is calibrated on), of the patch's own t and of the supercells' mean,
in units of the pillars' rms |t| (the label's convergence: the goal is <= 0.01).

    python benchmarks/crosscheck_patch_ladder.py [layouts/paper-5mm] [--patches 2] [--harmonics 1300 1800]
        [--partial DIR] [-o FOLDER] [-j 2] [--json]

``-o FOLDER``: the report also written to FOLDER/crosscheck.json (the solves in FOLDER.partial: a rerun after
a kill reuses them).  ``--partial``: keep the solves there instead (resumable; a patch study's OUT.partial
folder reuses its level).  Memory: about 3.5 GB per worker at 1300 harmonics, 7 GB at 1800."""

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _paper_design import (  # noqa: E402
    crosscheck, design_arguments, has_design, output_arguments, paper_patches, patch_arguments)


def ladder(a, scratch) -> dict:
    """The report: the patches solved at each truncation of ``a.harmonics`` (solves under ``scratch``) and
    the change of the ring term, the patch's t and the supercells' mean per step."""
    import numpy as np

    from metadesign.execution import Execution
    from metadesign.studies.supercells import solve_patches

    lib, ws, partial = paper_patches(a, scratch)
    levels = []
    for h in sorted(a.harmonics):
        t0 = time.perf_counter()
        done, ns, nu = solve_patches(ws, lib.stack, h, partial, run=Execution(workers=a.workers))
        tp = np.array([r["t_patch"] for r in done])
        two = np.array([r["t_super"] for r in done]).mean(1)
        tu = np.array([r["t_unit"] for r in done])
        levels.append({"n_harmonics": int(done[0]["n_harmonics"][0]), "supercell": ns - 1, "unit": nu - 1,
                       "seconds": time.perf_counter() - t0, "t_patch": tp, "two": two,
                       "rms": np.sqrt((np.abs(tu) ** 2).mean((1, 2)))})
    steps = []
    for lo, hi in zip(levels[:-1], levels[1:]):
        rms = hi["rms"]
        ring = np.abs((hi["t_patch"] - hi["two"]) - (lo["t_patch"] - lo["two"])) / rms
        steps.append({"from": lo["n_harmonics"], "to": hi["n_harmonics"],
                      "ring_change_mean": float(ring.mean()), "ring_change_max": float(ring.max()),
                      "patch_t_change_mean": float((np.abs(hi["t_patch"] - lo["t_patch"]) / rms).mean()),
                      "supercells_t_change_mean": float((np.abs(hi["two"] - lo["two"]) / rms).mean()),
                      "ring_size_mean": float((np.abs(hi["t_patch"] - hi["two"]) / rms).mean())})
    return {"patches": a.patches, "seed": a.seed, "workers": a.workers,
            "levels": [{k: v for k, v in lv.items() if k in ("n_harmonics", "supercell", "unit", "seconds")}
                       for lv in levels], "steps": steps}


def show(a, rep) -> None:
    for lv in rep["levels"]:
        print(f"patch nG {lv['n_harmonics']} (supercells {lv['supercell']}, unit cells {lv['unit']}): "
              f"{a.patches} patches in {lv['seconds']:.0f} s on {a.workers} workers")
    for st in rep["steps"]:
        print(f"nG {st['from']} -> {st['to']}: ring term moves {st['ring_change_mean']:.4f} mean, "
              f"{st['ring_change_max']:.4f} max of rms|t_i| (its size {st['ring_size_mean']:.4f}); the patch's t "
              f"{st['patch_t_change_mean']:.4f}, the supercells' mean {st['supercells_t_change_mean']:.4f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    design_arguments(ap)
    patch_arguments(ap, 2)
    output_arguments(ap)
    ap.add_argument("--harmonics", type=int, nargs="+", default=[1300, 1800])
    a = ap.parse_args(argv)
    if not has_design(a.design):
        return 2
    return crosscheck(a, Path(__file__).name, {"design": a.design, "solves": a.partial},
                      lambda scratch: ladder(a, scratch), lambda rep: show(a, rep), keep=a.partial)


if __name__ == "__main__":
    raise SystemExit(main())

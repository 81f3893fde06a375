"""The certified surrogate with its neighbour ring, against the best truth a patch has (#34): each 4 x 4
patch of the patch study (the same draw) as its four supercells solved at convergence (nG 797, the
label table's truncation, the library's own) plus the ring term of the patch solve (nG 1289, its
supercells matched).  Models: the PEDS surrogate on overlapping windows (the mean over the patch's
sixteen 2 x 2 windows: what `coupling-check --ring` does; no fitted parameter beyond PEDS's own); the PEDS
surrogate on the four supercells plus the ring low fidelity (patch solves at --ring-levels, its
coefficients fitted with that patch left out); PEDS alone (no ring); the LPA.  In units of the sixteen
pillars' rms |t|, per polarisation.

    python benchmarks/crosscheck_ring_certified.py [layouts/paper-5mm] [--patches 32] [--harmonics 1300]
        [--ring-levels 45 97] [--partial DIR] [-o FOLDER] [-j 2] [--json]

``-o FOLDER``: the report also written to FOLDER/crosscheck.json (the solves in FOLDER.partial: a rerun after
a kill reuses them).  ``--partial``: the patch study's solves (OUT.partial of `library patches`, kept) are
reused from there; the converged supercells are added to it (resumable)."""

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


def _stats(e):
    import numpy as np

    return {"mean": e.mean(0).tolist(), "p90": np.percentile(e, 90, axis=0).tolist(), "max": e.max(0).tolist(),
            "mean_both": float(e.mean()), "p90_both": float(np.percentile(e, 90))}


def ring_report(a, scratch) -> dict:
    """The report: the patches' truth (four converged supercells + the ring term) against each model (solves
    under ``scratch``)."""
    import numpy as np

    from metadesign.execution import Execution
    from metadesign.library.coupling import lpa_t
    from metadesign.library.peds import certified_t, fit_peds, patch_windows, ring_couplings
    from metadesign.library.store import interpolate_t
    from metadesign.library.supercells import solve_table
    from metadesign.studies.supercells import solve_patches

    lib, ws, partial = paper_patches(a, scratch)
    st = lib.stack
    t0 = time.perf_counter()
    done, _, _ = solve_patches(ws, st, a.harmonics, partial, run=Execution(workers=a.workers))
    tp = np.array([r["t_patch"] for r in done])
    ring_hi = tp - np.array([r["t_super"] for r in done]).mean(1)  # (n, 2)
    c = ring_couplings(ws, st, a.ring_levels, partial, workers=a.workers)
    n = len(ws)
    held = np.zeros_like(ring_hi)
    for i in range(n):
        keep = np.arange(n) != i
        held[i] = np.tensordot(fit_peds(c[:, keep], ring_hi[keep]), c[:, i], axes=1)
    quads = np.array([w[2 * i:2 * i + 2, 2 * j:2 * j + 2] for w in ws for i in range(2) for j in range(2)])
    t_conv, nG_conv, _, _ = solve_table(quads, st, a.converged, partial / f"converged-{a.converged}",
                                        workers=a.workers, chunk_size=4)
    win = patch_windows(ws)  # (n, 16, 2, 2, 2); the supercells (quads, in order) at 0, 2, 8, 10
    t_win = certified_t(lib, win.reshape(-1, 2, 2, 2), partial / "peds-windows", workers=a.workers).reshape(n, 16, 2)
    t_peds = t_win[:, [0, 2, 8, 10]].reshape(-1, 2)
    tu = interpolate_t(lib, quads[..., 0], quads[..., 1])[0]  # (4n, 2, 2, 2)
    rms = np.sqrt((np.abs(tu.reshape(n, 16, 2)) ** 2).mean(1))  # the sixteen pillars' (n, 2)
    truth = t_conv.reshape(n, 4, 2).mean(1) + ring_hi
    peds = t_peds.reshape(n, 4, 2).mean(1)
    lpa = lpa_t(tu).reshape(n, 4, 2).mean(1)
    return {"patches": n, "seed": a.seed, "ring_levels": a.ring_levels, "converged_nG": int(nG_conv),
            "seconds": time.perf_counter() - t0, "workers": a.workers,
            "peds_windows": _stats(np.abs(t_win.mean(1) - truth) / rms),
            "peds_plus_ring": _stats(np.abs(peds + held - truth) / rms),
            "peds_alone": _stats(np.abs(peds - truth) / rms),
            "lpa": _stats(np.abs(lpa - truth) / rms),
            "ring_term_alone_residual": _stats(np.abs(held - ring_hi) / rms),
            "per_supercell_peds_vs_converged": _stats(np.abs(t_peds - t_conv) /
                                                      np.sqrt((np.abs(tu) ** 2).mean((1, 2))))}


def show(a, rep) -> None:
    n, nG_conv = rep["patches"], rep["converged_nG"]
    print(f"{n} patches of {a.design} (seed {a.seed}); truth: four supercells at nG {nG_conv} + the patch's ring term; "
          f"{rep['seconds']:.0f} s on {a.workers} workers")
    print("  of rms|t_i|                mean x / y          p90 x / y")
    for k, name in (("peds_windows", "PEDS, overlapping windows"), ("peds_plus_ring", "PEDS + ring low fidelity"), ("peds_alone", "PEDS alone"), ("lpa", "LPA"),
                    ("ring_term_alone_residual", "ring term residual"),
                    ("per_supercell_peds_vs_converged", "PEDS per supercell")):
        s = rep[k]
        print(f"  {name:<26s} {s['mean'][0]:.4f} / {s['mean'][1]:.4f}     {s['p90'][0]:.4f} / {s['p90'][1]:.4f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    design_arguments(ap)
    patch_arguments(ap, 32)
    output_arguments(ap)
    ap.add_argument("--harmonics", type=int, default=1300, help="the patch study's (requested)")
    ap.add_argument("--ring-levels", type=int, nargs="+", default=[45, 97])
    ap.add_argument("--converged", type=int, default=800, help="the supercells' converged truncation (requested)")
    a = ap.parse_args(argv)
    if not has_design(a.design):
        return 2
    return crosscheck(a, Path(__file__).name, {"design": a.design, "solves": a.partial},
                      lambda scratch: ring_report(a, scratch), lambda rep: show(a, rep), keep=a.partial)


if __name__ == "__main__":
    raise SystemExit(main())

"""Cross-check of the committed unit-cell library against an independent RCWA
(meent, numpy backend, its analytic "vector" rectangle model with Li-type
factorization).  Not run by CI:

    pip install meent && python benchmarks/crosscheck_meent.py [--cells 12] [--fto 9] [--json]

meent uses exp(+i omega t) (so its phases are conjugated here), calls E along
y "TE" (pol=0) and E along x "TM" (pol=1) at phi = 0, and its transmission is
referenced like ours after dividing by the bare (no pillar) stack.  Reported:
per cell, the phase and T0 differences for both polarisations.
"""

import json
import os
import sys
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def meent_cell(wx_um, wy_um, pol, fto, st):
    import meent

    p = st["period_m"] * 1e6
    mee = meent.call_mee(backend=0, pol=pol, n_top=st["n_substrate"], n_bot=st["n_superstrate"], theta=0, phi=0,
                         fto=[fto, fto], period=[p, p], wavelength=st["wavelength_m"] * 1e6,
                         thickness=[st["height_m"] * 1e6], type_complex=np.complex128)
    rect = [["rectangle", p / 2, p / 2, wx_um, wy_um, st["n_pillar"], 0]] if wx_um > 0 else []
    mee.ucell = [[st["n_superstrate"], rect]]
    r = mee.conv_solve().res
    amp = r.T_s if pol == 0 else r.T_p
    return complex(amp[fto, fto]), float(r.de_ti[fto, fto])


def have_meent() -> bool:
    """Whether meent imports (else one line on stderr: these cross-checks are not in CI)."""
    try:
        import meent  # noqa: F401
    except ImportError:
        print("meent is not installed: pip install meent", file=sys.stderr)
        return False
    return True


def main() -> int:
    if not have_meent():
        return 2
    from metadesign.library.store import load_library
    from metadesign.paths import default_library_path

    args = sys.argv[1:]
    n_cells = int(args[args.index("--cells") + 1]) if "--cells" in args else 12
    fto = int(args[args.index("--fto") + 1]) if "--fto" in args else 9
    lib = load_library(default_library_path())
    st = lib.meta["stack"]
    rng = np.random.default_rng(0)
    idx = [(40, 20)] + [tuple(int(v) for v in rng.integers(0, len(lib.wx), 2)) for _ in range(n_cells - 1)]
    bare = {pol: meent_cell(0, 0, pol, fto, st)[0] for pol in (0, 1)}
    rows = []
    for i, j in idx:
        wx, wy = float(lib.wx[i] * 1e6), float(lib.wy[j] * 1e6)  # meent wants Python floats
        row = {"wx_um": round(wx, 4), "wy_um": round(wy, 4)}
        for pol, name, k in ((1, "x", 0), (0, "y", 1)):  # meent TM = E along x, TE = E along y
            amp, T0 = meent_cell(wx, wy, pol, fto, st)
            phase = -np.angle(amp / bare[pol])  # exp(+i omega t) -> ours
            ours = np.angle(lib.jones[i, j, k, k])
            row[f"dphase_{name}_rad"] = float(np.angle(np.exp(1j * (ours - phase))))
            row[f"dT0_{name}"] = float(lib.T0[i, j, k] - T0)
        rows.append(row)
    res = {"fto": fto, "harmonics": (2 * fto + 1) ** 2, "cells": rows,
           "max_abs_dphase_rad": max(max(abs(r["dphase_x_rad"]), abs(r["dphase_y_rad"])) for r in rows),
           "max_abs_dT0": max(max(abs(r["dT0_x"]), abs(r["dT0_y"])) for r in rows)}
    if "--json" in args:
        print(json.dumps(res, indent=2))
    else:
        print(f"meent ({res['harmonics']} harmonics) vs committed library, {len(rows)} cells:")
        for r in rows:
            print(f"  wx {r['wx_um']:.3f} wy {r['wy_um']:.3f} um: dphase x {r['dphase_x_rad']:+.4f} y "
                  f"{r['dphase_y_rad']:+.4f} rad, dT0 x {r['dT0_x']:+.4f} y {r['dT0_y']:+.4f}")
        print(f"max |dphase| {res['max_abs_dphase_rad']:.4f} rad, max |dT0| {res['max_abs_dT0']:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

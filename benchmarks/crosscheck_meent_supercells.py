"""Issue #34: the supercell label solver against a second RCWA formulation.  meent (numpy backend, its
analytic vector model of rectangles, Li-type factorisation, square truncation) solves the same 2 x 2
supercells of the committed label table (`library/paper-supercells.npz`: the project's staircase Li rule,
circular truncation, symmetry sectors) at increasing truncation; reported per supercell and polarisation:
the complex 0th-order ``t`` of each against the table's label, as ``|t_meent - t_table| / rms|t|`` (the
coupling model's error measure), and meent's own change between its last two truncations.  Not run by CI:

    pip install meent && python benchmarks/crosscheck_meent_supercells.py [--rows 4 9 14] [--fto 9 12 15] [--json]

Conventions as `crosscheck_meent.py`: meent's ``exp(+i omega t)`` is conjugated, its TE (pol 0) is E along
y and TM (pol 1) E along x, and its amplitudes are divided by its bare stack's (no pillar) and multiplied
by ours (``2 n_sub / (n_sub + n_sup)``, real), which cancels the two codes' reference planes.  The pillars
sit at ``((c + 1/2) p, (r + 1/2) p)`` in meent's cell ``[0, 2p)^2``: the project's cell shifted by half a
pitch, which leaves the 0th order unchanged."""

import json
import os
import sys
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def meent_supercell(widths_um, pol: int, fto: int, st: dict) -> complex:
    """meent's 0th-order transmitted amplitude of the 2 x 2 supercell ``widths_um[r][c] = (wx, wy)`` (um;
    None: the bare stack)."""
    import meent

    p = st["period_m"] * 1e6
    mee = meent.call_mee(backend=0, pol=pol, n_top=st["n_substrate"], n_bot=st["n_superstrate"], theta=0, phi=0,
                         fto=[fto, fto], period=[2 * p, 2 * p], wavelength=st["wavelength_m"] * 1e6,
                         thickness=[st["height_m"] * 1e6], type_complex=np.complex128)
    rects = [] if widths_um is None else [
        ["rectangle", (c + 0.5) * p, (r + 0.5) * p, float(widths_um[r][c][0]), float(widths_um[r][c][1]),
         st["n_pillar"], 0] for r in range(2) for c in range(2)]
    mee.ucell = [[st["n_superstrate"], rects]]
    res = mee.conv_solve().res
    amp = res.T_s if pol == 0 else res.T_p
    return complex(amp[fto, fto])


def main() -> int:
    from crosscheck_meent import have_meent

    if not have_meent():
        return 2
    from metadesign.io import read_npz

    args = sys.argv[1:]

    def ints(flag, default):
        if flag not in args:
            return default
        i = args.index(flag) + 1
        out = []
        while i < len(args) and not args[i].startswith("--"):
            out.append(int(args[i]))
            i += 1
        return out

    rows = ints("--rows", [4, 9, 14, 19, 24, 29])
    ftos = ints("--fto", [9, 12, 15])
    table = read_npz(REPO / "library" / "paper-supercells.npz")
    meta = json.loads(str(table["meta"]))
    st = meta["stack"] if "stack" in meta else meta["library"]["stack"]
    n_sub, n_sup = st["n_substrate"], st["n_superstrate"]
    ours_bare = 2 * n_sub / (n_sub + n_sup)
    t_tab, widths = table["t"], table["widths_m"]
    bare = {(pol, f): meent_supercell(None, pol, f, st) for pol in (0, 1) for f in ftos}
    out = []
    for i in rows:
        w_um = widths[i] * 1e6
        rec = {"row": int(i), "widths_um": np.round(w_um, 4).tolist(), "t_table": {}, "t_meent": {}, "seconds": {}}
        for name, k, pol in (("x", 0, 1), ("y", 1, 0)):  # meent TM (pol 1) = E along x
            ts = []
            for f in ftos:
                t0 = time.perf_counter()
                amp = meent_supercell(w_um, pol, f, st)
                rec["seconds"][f"{name}_{f}"] = round(time.perf_counter() - t0, 1)
                ts.append(np.conj(amp / bare[(pol, f)]) * ours_bare)
            rec["t_meent"][name] = [[float(t.real), float(t.imag)] for t in ts]
            rec["t_table"][name] = [float(t_tab[i, k].real), float(t_tab[i, k].imag)]
        out.append(rec)
        print(f"row {i}: " + ", ".join(
            f"{nm} |dt| {abs(complex(*rec['t_meent'][nm][-1]) - complex(*rec['t_table'][nm])):.4f}"
            for nm in ("x", "y")), file=sys.stderr, flush=True)
    rms = float(np.sqrt(np.mean(np.abs(t_tab[rows]) ** 2)))  # the table's rms |t| over these rows and pols

    def err(r, nm, level):
        return abs(complex(*r["t_meent"][nm][level]) - complex(*r["t_table"][nm])) / rms

    summary = {
        "fto": ftos, "harmonics": [(2 * f + 1) ** 2 for f in ftos], "table_n_harmonics": meta.get("n_harmonics"),
        "rows": out, "rms_abs_t": rms,
        "vs_table_mean": [float(np.mean([err(r, nm, j) for r in out for nm in "xy"])) for j in range(len(ftos))],
        "vs_table_max": [float(np.max([err(r, nm, j) for r in out for nm in "xy"])) for j in range(len(ftos))],
        "meent_last_step_mean": float(np.mean([abs(complex(*r["t_meent"][nm][-1]) - complex(*r["t_meent"][nm][-2]))
                                               / rms for r in out for nm in "xy"])) if len(ftos) > 1 else None,
    }
    if "--json" in args:
        print(json.dumps(summary, indent=1))
    else:
        print(f"meent vs the label table (nG {summary['table_n_harmonics']}) on {len(rows)} supercells, |dt| / rms|t|:")
        for f, h, m, x in zip(ftos, summary["harmonics"], summary["vs_table_mean"], summary["vs_table_max"]):
            print(f"  meent fto {f} ({h} harmonics): mean {m:.4f}, max {x:.4f}")
        if summary["meent_last_step_mean"] is not None:
            print(f"  meent's own last truncation step: mean {summary['meent_last_step_mean']:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The supercell coupling (#25): RCWA supercells per second per core (the table's cost), the coupling
model's evaluation per million supercells (network path, as for jittered widths, and pair-table path, as
for a design's atoms), the compensating discretizer per million supercells, and the projections for the
paper device (12.75 M supercells) and for a table of N solves on one machine and on a 64-worker cluster.

    python benchmarks/bench_coupling.py [--model library/paper-coupling.safetensors] [--solves 2] [--json]

Without a committed model an untrained one of the default architecture is timed (the cost does not depend
on the weights)."""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

PAPER_SUPERCELLS = 3571 * 3571


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=str(REPO / "library" / "paper-coupling.safetensors"))
    ap.add_argument("--solves", type=int, default=2, help="RCWA supercells timed (5 s each)")
    ap.add_argument("--n", type=int, default=200_000, help="supercells for the model and discretizer timings")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from metadesign.design.compensate import _descend, atom_neighbours
    from metadesign.design.store import load_design
    from metadesign.library import (
        CouplingConfig,
        build_coupling,
        coupling_t,
        is_coupling,
        load_coupling,
        pair_tables,
        tuple_t,
    )
    from metadesign.library.rcwa import Stack
    from metadesign.library.store import interpolate_t, load_library
    from metadesign.library.supercell import solve_supercell
    from metadesign.library.supercells import matched_unit_harmonics

    lib = load_library(REPO / "library" / "paper.npz")
    if is_coupling(a.model):
        model, _ = load_coupling(a.model, lib)
        which = Path(a.model).name
    else:
        model, which = build_coupling(CouplingConfig(interaction="pair"), lib).eval(), "untrained"
    rng = np.random.default_rng(0)
    rep = {"model": which, "config": vars(model.cfg) if hasattr(model.cfg, "__dict__") else str(model.cfg)}

    # RCWA: one core
    st = lib.meta["stack"]
    stack = Stack(st["wavelength_m"], st["period_m"], st["height_m"], st["n_pillar"], st["n_substrate"],
                  st["n_superstrate"])
    ns, _ = matched_unit_harmonics(800, stack)
    ts = []
    for _ in range(a.solves):
        w = rng.uniform(0.15e-6, 0.45e-6, size=(2, 2, 2))
        t = time.perf_counter()
        solve_supercell(w, stack, ns)
        ts.append(time.perf_counter() - t)
    s_solve = float(np.median(ts))
    rep["rcwa_seconds_per_supercell_core"] = s_solve
    rep["rcwa_supercells_per_second_core"] = 1 / s_solve
    for n in (1000, 2000, 10000):
        rep[f"table_{n}_hours_one_2core_machine"] = n * s_solve / 2 / 3600
        rep[f"table_{n}_minutes_64_workers"] = n * s_solve / 64 / 60

    # the model: network path
    n = a.n
    w = rng.uniform(0.12e-6, 0.48e-6, size=(n, 2, 2, 2))
    tu, _, _ = interpolate_t(lib, w[..., 0], w[..., 1])
    t = time.perf_counter()
    coupling_t(model, w, tu)
    s_net = time.perf_counter() - t
    rep["network_seconds_per_million"] = s_net / n * 1e6
    rep["network_paper_device_seconds"] = s_net / n * PAPER_SUPERCELLS
    # pair-table path over the paper design's atoms
    d = load_design(REPO / "layouts" / "paper-5mm") if (REPO / "layouts" / "paper-5mm" / "design.npz").exists() \
        else None
    if d is None:
        import tempfile

        from metadesign.design.recipe import load_design_recipe
        from metadesign.design.store import run_design

        with tempfile.TemporaryDirectory() as tmp:
            d, _ = run_design(load_design_recipe(REPO / "layouts" / "demo.toml"), Path(tmp) / "d")
    aw = np.stack([d.atoms.wx, d.atoms.wy], 1)
    ta = d.atoms.t.astype(np.complex64)
    if model.cfg.interaction == "pair":
        t = time.perf_counter()
        tab = pair_tables(model, aw, ta)
        rep["pair_tables_seconds"] = time.perf_counter() - t
        a4 = rng.integers(0, len(aw), size=(n, 2, 2))
        t = time.perf_counter()
        tuple_t(tab, ta, a4)
        s_tab = time.perf_counter() - t
        rep["table_seconds_per_million"] = s_tab / n * 1e6
        rep["table_vs_network_speedup"] = s_net / s_tab
        S = (np.exp(1j * rng.uniform(-np.pi, np.pi, size=(n, 2))) * 0.6).astype(np.complex64)
        nbr = atom_neighbours(d.atoms.phase, 9)
        t = time.perf_counter()
        _descend(a4.copy(), S, tab, ta, nbr, 2)
        s_comp = time.perf_counter() - t
        rep["compensation_seconds_per_million"] = s_comp / n * 1e6
        rep["compensation_paper_device_seconds"] = s_comp / n * PAPER_SUPERCELLS
    if a.json:
        print(json.dumps(rep, indent=1))
    else:
        print(f"coupling benchmark ({which}, one thread)")
        print(f"  RCWA supercell (nG 797, two sectors):  {s_solve:.2f} s  ({1 / s_solve:.3f} supercells/s/core)")
        for k in (1000, 2000, 10000):
            print(f"    a {k}-row table: {rep[f'table_{k}_hours_one_2core_machine']:.1f} h on one 2-core machine, "
                  f"{rep[f'table_{k}_minutes_64_workers']:.1f} min on 64 workers")
        print(f"  model, network path:   {rep['network_seconds_per_million']:.1f} s per million supercells "
              f"(paper device {rep['network_paper_device_seconds']:.0f} s)")
        if "table_seconds_per_million" in rep:
            print(f"  model, pair tables:    {rep['table_seconds_per_million']:.2f} s per million "
                  f"({rep['table_vs_network_speedup']:.0f}x the network; tables {rep['pair_tables_seconds']:.1f} s)")
            print(f"  compensation (9 neighbours, 2 sweeps): {rep['compensation_seconds_per_million']:.1f} s per "
                  f"million (paper device {rep['compensation_paper_device_seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

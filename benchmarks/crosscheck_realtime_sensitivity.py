"""Issue #50: how strongly does the real-time network answer each mode around a closed loop's residual?  The
network's optical gain per mode (a pyramid sensor's term): each unit-rms Zernike of its basis (Noll 2 on)
pushed by +/- ``--push`` rad on a field, rendered through a loop recipe's device (noise-free, normalised as
the loop does), and the change of the network's coefficient of that mode over the change applied (1: reads
it exactly; 0: does not see it).  Fields: the flat wavefront, and closed-loop residuals of
``sensing/dataset-loop`` (validation beacons seen through a converged mirror).  A mode read at sensitivity
``s`` with a small bias ``b`` settles at ``g b / (1 - leak + g s)`` in an integrator (``tests/
test_ao_kernels.py``): what a leak of 0.99 lets pile up in the modes the network barely sees.  ~1 min for
20 modes on 12 residuals:

    python benchmarks/crosscheck_realtime_sensitivity.py [--recipe sensing/loop-demo-w48.toml]
        [--dataset sensing/dataset-loop] [--residuals 12] [--modes 20] [--push 0.2] [--json]
"""

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--recipe", default=str(REPO / "sensing" / "loop-demo-w48.toml"))
    p.add_argument("--dataset", default=str(REPO / "sensing" / "dataset-loop"))
    p.add_argument("--residuals", type=int, default=12)
    p.add_argument("--modes", type=int, default=20)
    p.add_argument("--push", type=float, default=0.2)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    if not 1 <= a.residuals <= 1000 or not 1 <= a.modes <= 1000 or not (np.isfinite(a.push) and 0 < a.push <= 2):
        p.error("expected --residuals 1-1000, --modes 1-1000, 0 < --push <= 2 rad")
    if not Path(a.dataset, "zarr.json").is_file():
        print(f"crosscheck_realtime_sensitivity: {a.dataset}: no dataset (build it: metadesign dataset build "
              "sensing/dataset-loop.toml)", file=sys.stderr)
        return 2
    import torch
    import zarr

    from metadesign.reconstruction.dataset import normalise_psf
    from metadesign.reconstruction.refine import load_network
    from metadesign.studies.loop_recipe import load_loop_recipe
    from metadesign.studies.loop_study import build_loop

    torch.set_num_threads(1)
    rec = load_loop_recipe(a.recipe)
    if rec.realtime is None:
        p.error(f"--recipe: {a.recipe} names no [device] realtime network")
    with tempfile.TemporaryDirectory() as d:
        _, device, _ = build_loop(rec, Path(d), lambda s: None)
    net, _ = load_network(rec.realtime)
    A = net.config.aperture_size
    basis = net.basis.numpy().reshape(-1, A, A).astype(np.float64)
    K = min(a.modes, len(basis))
    mask = net.mask.numpy() > 0
    g = zarr.open_group(a.dataset, mode="r")
    split, gain = np.asarray(g["split"][:]), np.asarray(g["loop_gain"][:])
    idx = np.nonzero((split == 1) & (gain > 0))[0][:a.residuals]
    fields = {"flat": [np.where(mask, 1.0, 0.0)], "residuals": list(np.asarray(g["received"].oindex[idx]))}

    def render(u):
        psf, _ = normalise_psf(device.render(device.pupil_field(np.asarray(u, np.complex64))).psfs)
        return psf

    out = {}
    for name, us in fields.items():
        s = np.empty((len(us), K))
        for i, u in enumerate(us):
            x = np.stack([render(u * np.exp(sg * 1j * a.push * basis[j])) for j in range(K) for sg in (1, -1)])
            with torch.no_grad():
                c = net.commands(torch.from_numpy(x.astype(np.float32))).numpy().astype(np.float64).reshape(K, 2, -1)
            s[i] = [(c[j, 0, j] - c[j, 1, j]) / (2 * a.push) for j in range(K)]
        out[name] = {"mean": s.mean(axis=0).tolist(), "min": s.min(axis=0).tolist(), "max": s.max(axis=0).tolist(),
                     "fields": len(us)}
    rep = {"recipe": a.recipe, "network": str(rec.realtime), "push_rad": a.push,
           "noll": list(range(2, K + 2)), "sensitivity": out}
    if a.json:
        print(json.dumps(rep, indent=1))
        return 0
    print(f"{Path(str(rec.realtime)).name} on {Path(a.recipe).name}'s device: d(coefficient) / d(applied), "
          f"+/-{a.push:g} rad pushes")
    print("  Noll        " + " ".join(f"{n:5d}" for n in rep["noll"]))
    for name, v in out.items():
        print(f"  {name:<11} " + " ".join(f"{x:5.2f}" for x in v["mean"]) + f"   ({v['fields']} fields, mean)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Issue #50: how well does the real-time network read tip and tilt?  In the headline loop
(``sensing/loop-demo-w48.toml``) its loop holds more tip/tilt power below 50 Hz than the open loop does; a
closed loop's residual in a mode is, below its bandwidth, the sensor's error in that mode.  This measures that
error on the network's own validation beacons (open loop), against a reference that needs no phase
unwrapping: the received field's mean phase gradient over the aperture, ``mean(angle(u[i+1] conj u[i]))``
(wrap-free as long as neighbouring samples differ by < pi), which for a unit-rms Noll 2 / 3 Zernike
(``2 rho cos / sin``) on a disc of radius ``R`` samples is ``2 a / R`` per sample.  Printed per mode: the
reference's rms, the network's, the regression slope, the correlation and the rms of the network's error
about the reference (rad rms of the mode; its square is the residual variance a loop keeps in that mode
below its bandwidth).  Needs the network's dataset built (``metadesign dataset build
sensing/dataset-realtime.toml``; ~1 min for the 768 validation beacons' reads):

    python benchmarks/crosscheck_realtime_tilt.py [--model sensing/models/realtime-w48.safetensors]
        [--dataset sensing/dataset-realtime] [--limit 768] [--linear sensing/loop-demo-w48.toml] [--json]

``--linear LOOP_RECIPE``: also the push-pull linear reconstructor of Noll 2, 3 on that loop's device (what
the loop's ``realtime_tt`` method reads tip and tilt with; its device designed in a temporary folder, ~1 min).
"""

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

#: rad: the beacons whose tilt is as small as a closed loop's residual
SMALL_RAD = 0.5


def gradient_tilts(u: np.ndarray, mask: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The unit-rms Noll 2 (x) and 3 (y) coefficients of the phase of fields ``u`` (B, A, A) from their mean
    wrap-free phase differences over the pairs of samples inside ``mask``."""
    gx = np.angle(u[:, :, 1:] * np.conj(u[:, :, :-1]))
    gy = np.angle(u[:, 1:, :] * np.conj(u[:, :-1, :]))
    mx, my = mask[:, 1:] & mask[:, :-1], mask[1:, :] & mask[:-1, :]
    return gx[:, mx].mean(axis=1) * radius / 2, gy[:, my].mean(axis=1) * radius / 2


def _linear_tilts(recipe: str, x: np.ndarray) -> np.ndarray:
    """The loop's push-pull tip/tilt reconstructor (its ``realtime_tt``) on the recipe's device: (B, 2)."""
    import tempfile

    from metadesign.studies.loop_recipe import load_loop_recipe
    from metadesign.studies.loop_study import build_loop, linear_estimator

    rec = load_loop_recipe(recipe)
    with tempfile.TemporaryDirectory() as d:
        _, device, _ = build_loop(rec, Path(d), lambda s: None)
        lin = linear_estimator(rec, device, modes=2).reconstructor
    return np.asarray(lin.estimate(x), np.float64)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default=str(REPO / "sensing" / "models" / "realtime-w48.safetensors"))
    p.add_argument("--dataset", default=str(REPO / "sensing" / "dataset-realtime"))
    p.add_argument("--limit", type=int, default=768, help="validation beacons read (default 768: all of them)")
    p.add_argument("--linear", metavar="LOOP_RECIPE", help="also the push-pull tip/tilt reconstructor of this "
                   "loop recipe's device")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    if a.limit < 2:
        p.error(f"--limit: expected at least 2 beacons, got {a.limit}")
    if not Path(a.dataset, "zarr.json").is_file():
        print(f"crosscheck_realtime_tilt: {a.dataset}: no dataset (build it: metadesign dataset build "
              "sensing/dataset-realtime.toml)", file=sys.stderr)
        return 2
    import torch
    import zarr

    from metadesign.reconstruction.refine import load_network

    torch.set_num_threads(1)
    net, _ = load_network(a.model)
    g = zarr.open_group(a.dataset, mode="r")
    idx = np.nonzero(np.asarray(g["split"][:]) == 1)[0][:a.limit]  # the validation split
    x = np.asarray(g["psf"].oindex[idx], np.float32)  # stored as the network reads it (channels sum to 8)
    u = np.asarray(g["received"].oindex[idx])
    with torch.no_grad():
        c = np.concatenate([net.commands(torch.from_numpy(x[i:i + 64])).numpy() for i in range(0, len(x), 64)])
    mask = net.mask.numpy() > 0
    radius = (net.config.aperture_size - 1) / 2.0  # the basis' disc: diameter aperture_size - 1 samples
    readers = {"network": c[:, :2]}
    if a.linear:
        readers["linear"] = _linear_tilts(a.linear, x)
    rows = []
    for (reader, cs), j in ((r, j) for r in readers.items() for j in range(2)):
        name, ref = ("Noll 2 (tip, x)", "Noll 3 (tilt, y)")[j], gradient_tilts(u, mask, radius)[j]
        est = cs[:, j].astype(np.float64)
        small = np.abs(ref) < SMALL_RAD
        slope = float(np.dot(ref, est) / np.dot(ref, ref))
        rows.append({"reader": reader, "mode": name, "reference_rms_rad": float(ref.std()),
                     "estimate_rms_rad": float(est.std()),
                     "slope": slope, "correlation": float(np.corrcoef(ref, est)[0, 1]),
                     "error_rms_rad": float(np.sqrt(np.mean((est - ref) ** 2))),
                     # a closed loop's residual tilts are small: the error where the reference is
                     "small": SMALL_RAD, "small_beacons": int(np.sum(np.abs(ref) < SMALL_RAD)),
                     "small_error_rms_rad": float(np.sqrt(np.mean((est - ref)[small] ** 2))) if small.any() else None,
                     "small_slope": float(np.dot(ref[small], est[small]) / np.dot(ref[small], ref[small]))
                     if small.any() else None})
    rep = {"model": a.model, "dataset": a.dataset, "beacons": int(len(idx)), "modes": rows}
    if a.json:
        print(json.dumps(rep, indent=1))
        return 0
    print(f"{Path(a.model).name} on {len(idx)} validation beacons of {Path(a.dataset).name} "
          "(reference: the field's mean phase gradient)")
    for r in rows:
        print(f"  {r['reader']:<8} {r['mode']:<17} reference {r['reference_rms_rad']:.3f} rad rms, "
              f"estimate {r['estimate_rms_rad']:.3f}, "
              f"slope {r['slope']:.3f}, correlation {r['correlation']:.3f}, error {r['error_rms_rad']:.3f} rad rms "
              f"({r['error_rms_rad'] ** 2:.3f} rad^2)")
        if r["small_error_rms_rad"] is not None:
            print(f"  {'':<8} {'':<17} where |reference| < {SMALL_RAD:g} rad ({r['small_beacons']} beacons): error "
                  f"{r['small_error_rms_rad']:.3f} rad rms, slope {r['small_slope']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

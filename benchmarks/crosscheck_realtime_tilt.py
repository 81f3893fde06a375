"""Issue #50: which tip and tilt does the real-time loop need, and who reads it?  A closed loop's residual in
a mode is, below its bandwidth, its sensor's error in that mode; this measures that error for tip and tilt
on a dataset's validation beacons (with ``sensing/dataset-loop``: closed-loop residuals and open beacons,
apart) against three references computed from the received field:

* ``overlap``: the tilt that maximises the corrected field's overlap with the received one,
  ``|sum u exp(-i (a Z2 + b Z3))|^2`` (a brute-force search, 0.04 rad steps over +/-5 rad): the position of
  the far field's peak, what the power in the bucket rewards;
* ``gradient``: the mean phase gradient over the aperture, ``mean(angle(u[i+1] conj u[i]))``;
* ``centroid``: the intensity-weighted mean phase gradient (the far field's centroid).

For a unit-rms Noll 2 / 3 Zernike (``2 rho cos / sin``) on a disc of radius ``R`` samples the gradients
are ``2 a / R`` per sample.  Under scintillation the three differ by 0.3-0.5 rad rms; a loop should track
the first.  Readers: the network (``--model``), and with ``--linear LOOP_RECIPE`` / ``--peak LOOP_RECIPE``
the push-pull linear reconstructor of Noll 2, 3 (the loop's ``realtime_tt``) and the in-focus channel's
peak (:mod:`metadesign.reconstruction.peak_tilt`, the loop's ``realtime_peak``) on that recipe's device
(designed in a temporary folder, ~1 min).  Each reads the PSFs with ``--noise-percent`` % of each
channel's peak of Gaussian noise (default 5: the loop's; 0: noise-free), renormalised as the loop does.
Printed per reader, subset and reference: the error per mode (rad rms; its square is the variance a loop
keeps below its bandwidth) and the overlap kept (the mean of overlap(reading) / overlap(best)).  Needs the
dataset built (``metadesign dataset build sensing/dataset-loop.toml``):

    python benchmarks/crosscheck_realtime_tilt.py [--model sensing/models/realtime-w48.safetensors]
        [--dataset sensing/dataset-realtime] [--limit 768] [--linear sensing/loop-demo-w48.toml]
        [--peak sensing/loop-demo-w48.toml] [--noise-percent 5] [--json]
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

#: rad: the overlap search's half range and step
SEARCH_RAD, SEARCH_STEP = 5.0, 0.04


def gradient_tilts(u: np.ndarray, mask: np.ndarray, radius: float, weighted: bool = False) -> np.ndarray:
    """The unit-rms Noll 2 (x) and 3 (y) coefficients ``(B, 2)`` of the phase of fields ``u`` (B, A, A) from
    their mean wrap-free phase differences over the pairs of samples inside ``mask`` (``weighted``: each
    pair weighted by its ``|u[i+1] u[i]|``, the far field's centroid)."""
    out = []
    for d, m in ((u[:, :, 1:] * np.conj(u[:, :, :-1]), mask[:, 1:] & mask[:, :-1]),
                 (u[:, 1:, :] * np.conj(u[:, :-1, :]), mask[1:, :] & mask[:-1, :])):
        w = np.abs(d[:, m]) if weighted else np.ones(d[:, m].shape)
        out.append((np.angle(d[:, m]) * w).sum(axis=1) / w.sum(axis=1) * radius / 2)
    return np.stack(out, axis=1)


def overlap(u: np.ndarray, mask: np.ndarray, radius: float, t: np.ndarray) -> np.ndarray:
    """``|sum_mask u exp(-i (t_x Z2 + t_y Z3))|^2`` for fields ``u`` (B, A, A) and tilts ``t`` (B, 2)."""
    c = (np.arange(u.shape[-1]) - (u.shape[-1] - 1) / 2) / radius
    ph = 2 * (t[:, 0, None, None] * c[None, None, :] + t[:, 1, None, None] * c[None, :, None])
    return np.abs(np.sum(np.where(mask, u, 0) * np.exp(-1j * ph), axis=(1, 2))) ** 2


def overlap_tilts(u: np.ndarray, mask: np.ndarray, radius: float) -> np.ndarray:
    """The tilts ``(B, 2)`` that maximise :func:`overlap` on a grid (separable: one matrix product a field)."""
    c = (np.arange(u.shape[-1]) - (u.shape[-1] - 1) / 2) / radius
    grid = np.arange(-SEARCH_RAD, SEARCH_RAD + SEARCH_STEP / 2, SEARCH_STEP)
    E = np.exp(-1j * 2 * np.outer(c, grid))  # (x, a)
    out = np.empty((len(u), 2))
    for k, f in enumerate(np.where(mask, u, 0)):
        o = np.abs(E.T @ f @ E) ** 2  # (b: y, a: x)
        i, j = np.unravel_index(np.argmax(o), o.shape)
        out[k] = grid[j], grid[i]
    return out


def _device(recipe: str):
    import tempfile

    from metadesign.studies.loop_recipe import load_loop_recipe
    from metadesign.studies.loop_study import build_loop

    rec = load_loop_recipe(recipe)
    with tempfile.TemporaryDirectory() as d:
        _, device, _ = build_loop(rec, Path(d), lambda s: None)
    return rec, device


def _noisy(x: np.ndarray, percent: float, seed: int = 0) -> np.ndarray:
    """The loop's detector on each channel (``percent`` % of its peak, Gaussian), renormalised (channels sum
    to 8)."""
    if not percent:
        return x
    from metadesign.sensing.detector import Detector

    y = Detector.gaussian(percent, seed).read(x, np.random.default_rng(seed))
    return (y * (8.0 / y.sum(axis=(1, 2, 3), keepdims=True))).astype(np.float32)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default=str(REPO / "sensing" / "models" / "realtime-w48.safetensors"))
    p.add_argument("--dataset", default=str(REPO / "sensing" / "dataset-realtime"))
    p.add_argument("--limit", type=int, default=768, help="validation beacons read (default 768)")
    p.add_argument("--linear", metavar="LOOP_RECIPE", help="also the push-pull tip/tilt reconstructor of this "
                   "loop recipe's device")
    p.add_argument("--peak", metavar="LOOP_RECIPE", help="also the in-focus channel's peak on this loop recipe's "
                   "device")
    p.add_argument("--noise-percent", type=float, default=5.0, help="Gaussian noise, %% of each channel's peak "
                   "(default 5: the loop's)")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    if a.limit < 2:
        p.error(f"--limit: expected at least 2 beacons, got {a.limit}")
    if not (0 <= a.noise_percent <= 100):
        p.error(f"--noise-percent: expected 0-100, got {a.noise_percent}")
    if not Path(a.dataset, "zarr.json").is_file():
        print(f"crosscheck_realtime_tilt: {a.dataset}: no dataset (build it: metadesign dataset build "
              "sensing/dataset-realtime.toml)", file=sys.stderr)
        return 2
    import torch
    import zarr

    from metadesign.optics.dm import ModalDM
    from metadesign.reconstruction.peak_tilt import PeakTipTilt
    from metadesign.reconstruction.refine import load_network
    from metadesign.studies.loop_study import linear_estimator

    torch.set_num_threads(1)
    net, _ = load_network(a.model)
    g = zarr.open_group(a.dataset, mode="r")
    idx = np.nonzero(np.asarray(g["split"][:]) == 1)[0][:a.limit]  # the validation split
    x = _noisy(np.asarray(g["psf"].oindex[idx], np.float32), a.noise_percent)
    u = np.asarray(g["received"].oindex[idx])
    closed = np.asarray(g["loop_gain"].oindex[idx]) > 0 if "loop_gain" in g else np.zeros(len(idx), bool)
    with torch.no_grad():
        c = np.concatenate([net.commands(torch.from_numpy(x[i:i + 64])).numpy() for i in range(0, len(x), 64)])
    mask = net.mask.numpy() > 0
    radius = (net.config.aperture_size - 1) / 2.0  # the basis' disc: diameter aperture_size - 1 samples
    readers = {"network": c[:, :2].astype(np.float64)}
    if a.linear:
        rec, device = _device(a.linear)
        readers["linear"] = np.asarray(linear_estimator(rec, device, modes=2).reconstructor.estimate(x), np.float64)
    if a.peak:
        rec, device = _device(a.peak)
        pt = PeakTipTilt.build(device, ModalDM.for_crop(device.crop, n_modes=2).influence)
        readers["peak"] = pt.estimate(x)
    refs = {"overlap": overlap_tilts(u, mask, radius), "gradient": gradient_tilts(u, mask, radius),
            "centroid": gradient_tilts(u, mask, radius, weighted=True)}
    best = overlap(u, mask, radius, refs["overlap"])
    subsets = {"closed-loop residuals": closed, "open loop": ~closed} if closed.any() else {"open loop": ~closed}
    rows = []
    for reader, est in {**readers, **{f"({r})": t for r, t in refs.items() if r != "overlap"}}.items():
        kept = overlap(u, mask, radius, est) / best
        for sub, sel in subsets.items():
            if not sel.any():
                continue
            row = {"reader": reader, "subset": sub, "beacons": int(sel.sum()),
                   "overlap_kept": float(kept[sel].mean()), "errors_rad": {}}
            for ref, t in refs.items():
                e = est[sel] - t[sel]
                row["errors_rad"][ref] = {"tip": float(np.sqrt(np.mean(e[:, 0] ** 2))),
                                          "tilt": float(np.sqrt(np.mean(e[:, 1] ** 2))),
                                          "slope": float(np.sum(t[sel] * est[sel]) / np.sum(t[sel] ** 2))}
            rows.append(row)
    spread = {sub: {f"{r1}-{r2}": float(np.sqrt(np.mean((refs[r1][sel] - refs[r2][sel]) ** 2)))
                    for r1, r2 in (("overlap", "gradient"), ("overlap", "centroid"), ("gradient", "centroid"))}
              for sub, sel in subsets.items()}
    rep = {"model": a.model, "dataset": a.dataset, "beacons": int(len(idx)), "noise_percent": a.noise_percent,
           "rows": rows, "reference_spread_rad": spread}
    if a.json:
        print(json.dumps(rep, indent=1))
        return 0
    print(f"{Path(a.model).name} on {len(idx)} validation beacons of {Path(a.dataset).name}, "
          f"{a.noise_percent:g} % noise; errors rad rms (tip, tilt) against each reference")
    for sub, d in spread.items():
        print(f"  {sub}: the references differ by " + ", ".join(f"{k} {v:.2f}" for k, v in d.items()) + " rad rms")
    for r in rows:
        errs = "  ".join(f"{ref} {v['tip']:.3f}/{v['tilt']:.3f} (slope {v['slope']:.2f})"
                         for ref, v in r["errors_rad"].items())
        print(f"  {r['reader']:<10} {r['subset']:<21} ({r['beacons']:>3}): overlap kept {r['overlap_kept']:.3f}; {errs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

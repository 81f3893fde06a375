"""A frame that cannot be plugged in wrong (#52): the flat-frame orientation check measured.

Flat-wavefront frames of the paper device (the demo models' dataset recipe, ``demo-unet-robust``) and of the
co-designed one (``codesign-demo-unet``: the paper device with its learned diversity), each device exactly as
its exported contract describes it (:func:`metadesign.reconstruction.contract_device.contract_device`), read
by the detector at 0, 5 and 10 % Gaussian noise (of each frame's peak; a few draws each), then turned as a
lab might deliver them: flipped up-down, mirrored left-right, rotated by 180 degrees, transposed (a camera
on its side), the polarisation frames swapped (alone and with each flip), offset by 2, 4 and 8 px, scaled
by 0.95 and 1.05 (the relay's magnification).  Each goes through
:func:`metadesign.sensing.orientation.diagnose` against the contract's signature:

* a misoriented frame must be refused with its orientation named (undeclared) and accepted once that
  orientation is declared (corrected);
* an offset or scaled frame must be accepted with its shift (px) and scale measured (then corrected by
  moving the quadrant windows: the input tensor's error against the nominal one with and without that);
* a correct frame must never be refused.

    python benchmarks/bench_orientation.py [--seeds 3] [--json] [-o sensing/orientation-check.json]
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "examples"))

import numpy as np

DEVICES = {"paper": "demo-unet-robust", "co-designed": "codesign-demo-unet"}
TURNS = ("flip-ud", "flip-lr", "rot180", "transpose", "swap-pol", "swap-pol+flip-ud", "swap-pol+flip-lr",
         "swap-pol+rot180")
OFFSETS = ((2, -1), (4, -2), (8, -4))
SCALES = (0.95, 1.05)


def shifted(frames: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """Frames moved by whole pixels (dx columns, dy rows), zeros let in."""
    out = np.zeros_like(frames)
    H, W = frames.shape[-2:]
    out[:, max(dy, 0):H + min(dy, 0), max(dx, 0):W + min(dx, 0)] = \
        frames[:, max(-dy, 0):H + min(-dy, 0), max(-dx, 0):W + min(-dx, 0)]
    return out


def scaled(frames: np.ndarray, s: float) -> np.ndarray:
    """Frames magnified by ``s`` about their centre (bilinear; power per pixel / s^2: the light is conserved)."""
    from scipy.ndimage import affine_transform

    H, W = frames.shape[-2:]
    c = np.array([(H - 1) / 2, (W - 1) / 2])
    return np.stack([affine_transform(f, np.eye(2) / s, offset=c - c / s, order=1) / s**2 for f in frames])


def tensor_error(frames, camera, nominal, shift=(0.0, 0.0), scale=1.0) -> float:
    """Relative rms error of the stand-alone example's input tensor against the nominal frames'."""
    from deploy_onnx import input_tensor

    x = input_tensor(list(frames), camera, None, "identity", shift, scale)
    return float(np.sqrt(((x - nominal) ** 2).sum() / (nominal**2).sum()))


def run(seeds: int, log=print) -> dict:
    from metadesign.reconstruction.contract_device import contract_device
    from metadesign.reconstruction.export import camera_contract
    from metadesign.sensing.detector import NoiseSpec, add_noise
    from metadesign.sensing.device import Device
    from metadesign.sensing.orientation import diagnose, orient_frames

    rows, devices = [], {}
    for name, model in DEVICES.items():
        path = REPO / "sensing" / "models" / f"{model}.safetensors"
        card = json.loads(path.with_name(path.name + ".json").read_text())
        t0 = time.perf_counter()
        cd = contract_device(path, card, log=log)
        cam = camera_contract(cd)
        rec = cam["calibration_signature"]
        flat = Device(cd.device.pupil, cd.device.sensor).frames().astype(np.float64)
        devices[name] = {"model": model, "design": cd.identity["design"], "symmetric": rec["symmetric"],
                         "signature": rec["channels"], "seconds": round(time.perf_counter() - t0, 1)}
        from deploy_onnx import input_tensor

        nominal = input_tensor(list(flat), cam)
        for noise in (0.0, 5.0, 10.0):
            for seed in range(seeds if noise else 1):
                def read(f, seed=seed, noise=noise):
                    return add_noise(f, NoiseSpec(gaussian_sigma=noise / 100, seed=seed)) if noise else f

                def add(case, kind, v, name=name, noise=noise, seed=seed, **extra):
                    rows.append({"device": name, "noise_percent": noise, "seed": seed, "case": case, "kind": kind,
                                 "best": v.best, "chi2": v.chi2, "runner_up": v.runner_up,
                                 "runner_up_chi2": v.runner_up_chi2, "refused": v.problem() is not None,
                                 "problem": v.problem(), "shift_px": list(v.shift_px), "scale": v.scale, **extra})

                add("correct", "correct", diagnose(read(flat), rec))
                for turn in TURNS:
                    g = read(orient_frames(flat, turn))
                    v = diagnose(g, rec)
                    add(turn, "misoriented", v, named=v.best == turn)
                    d = diagnose(g, rec, declared=turn)
                    add(turn + " (declared)", "declared", d)
                for dx, dy in OFFSETS:
                    g = shifted(flat, dx, dy)
                    v = diagnose(read(g), rec)
                    extra = {"true_shift_px": [dx, dy], "shift_error_px": float(np.hypot(v.shift_px[0] - dx,
                                                                                         v.shift_px[1] - dy))}
                    if not noise:
                        extra |= {"tensor_error_uncorrected": tensor_error(g, cam, nominal),
                                  "tensor_error_corrected": tensor_error(g, cam, nominal, v.shift_px, v.scale)}
                    add(f"offset {dx:+d},{dy:+d} px", "offset", v, **extra)
                for s in SCALES:
                    g = scaled(flat, s)
                    v = diagnose(read(g), rec)
                    extra = {"true_scale": s, "scale_error": abs(v.scale - s)}
                    if not noise:
                        extra |= {"tensor_error_uncorrected": tensor_error(g, cam, nominal),
                                  "tensor_error_corrected": tensor_error(g, cam, nominal, v.shift_px, v.scale)}
                    add(f"scale {s:g}", "scale", v, **extra)
        log(f"{name}: {sum(r['device'] == name for r in rows)} frames checked")
    return {"devices": devices, "rows": rows, "summary": summarise(rows)}


def summarise(rows: list) -> dict:
    """Per (device, noise, case): frames, refused, named, chi2 max / runner-up min, worst alignment errors; and
    the verdicts: misoriented frames all refused and named, declared ones all accepted, offset and scaled
    ones all accepted and measured, correct frames never refused."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["device"], r["noise_percent"], r["case"]), []).append(r)
    table = []
    for (dev, noise, case), rs in groups.items():
        t = {"device": dev, "noise_percent": noise, "case": case, "kind": rs[0]["kind"], "frames": len(rs),
             "refused": sum(r["refused"] for r in rs), "chi2_max": max(r["chi2"] for r in rs),
             "runner_up_chi2_min": min(r["runner_up_chi2"] for r in rs)}
        if rs[0]["kind"] == "misoriented":
            t["named"] = sum(r["named"] for r in rs)
        for k in ("shift_error_px", "scale_error", "tensor_error_uncorrected", "tensor_error_corrected"):
            if k in rs[0]:
                t[k + "_max"] = max(r[k] for r in rs)
        table.append(t)

    def count(kind, ok):
        sel = [r for r in rows if r["kind"] == kind]
        return {"frames": len(sel), "ok": sum(ok(r) for r in sel)}

    verdict = {
        "misoriented_refused_and_named": count("misoriented", lambda r: r["refused"] and r["named"]),
        "declared_corrected": count("declared", lambda r: not r["refused"]),
        "offset_accepted_and_measured": count("offset", lambda r: not r["refused"] and r["shift_error_px"] < 0.5),
        "scaled_accepted_and_measured": count("scale", lambda r: not r["refused"] and r["scale_error"] < 0.005),
        "correct_accepted": count("correct", lambda r: not r["refused"]),
    }
    return {"table": table, "verdict": verdict, "all_pass": all(v["ok"] == v["frames"] for v in verdict.values())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3, help="noise draws per noisy case (default 3)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("-o", "--output", help="write the results as JSON (e.g. sensing/orientation-check.json)")
    a = ap.parse_args()
    t0 = time.perf_counter()
    res = run(a.seeds, log=(lambda s: print(s, file=sys.stderr)) if a.json else print)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    res["made_with"] = {"command": "python benchmarks/bench_orientation.py " + " ".join(sys.argv[1:]),
                        "noise": "metadesign.sensing.detector: Gaussian, sigma = noise % of each frame's peak"}
    if a.output:
        from metadesign.io import atomic_write_text

        kept = {k: v for k, v in res.items() if k != "rows"}  # the summary: each frame's row stays out
        atomic_write_text(Path(a.output), json.dumps(kept, indent=1, default=float) + "\n")
    if a.json:
        print(json.dumps(res["summary"], indent=1))
        return
    print(f"{'device':12s} {'noise':>5s} {'case':28s} {'frames':>6s} {'refused':>7s} {'named':>5s} {'chi2 max':>9s} "
          f"{'next min':>9s}  alignment")
    for t in res["summary"]["table"]:
        al = ""
        if "shift_error_px_max" in t:
            al = f"shift error <= {t['shift_error_px_max']:.2f} px"
        if "scale_error_max" in t:
            al = f"scale error <= {t['scale_error_max']:.4f}"
        if "tensor_error_corrected_max" in t:
            al += (f"; tensor error {t['tensor_error_uncorrected_max']:.3f} -> "
                   f"{t['tensor_error_corrected_max']:.3f} corrected")
        print(f"{t['device']:12s} {t['noise_percent']:5.0f} {t['case']:28s} {t['frames']:6d} {t['refused']:7d} "
              f"{t.get('named', ''):>5} {t['chi2_max']:9.3g} {t['runner_up_chi2_min']:9.3g}  {al}")
    for k, v in res["summary"]["verdict"].items():
        print(f"{k}: {v['ok']}/{v['frames']}")
    print(f"all pass: {res['summary']['all_pass']}; {res['seconds']:.0f} s")


if __name__ == "__main__":
    main()

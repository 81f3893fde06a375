"""The loop in time (issue #50): the cost of one second of link time of the demo loop
(``sensing/loop-demo.toml``'s device: the paper's 5 mm design, its sensor, the 256^2 13-screen turbulence at
Rytov 0.5, wind 2.7 m/s; 2,000 steps at 2 kHz with 4 exposure sub-steps) on one core, for the ideal phase
sensor and the metasurface U-Net (its latency declared 0 so that the loop corrects), measured on a shorter
run and scaled, split by part of the step: the frozen-flow screens (and the long screens' draw for the whole
second), the propagation (split step + collimation), the sensor's exposure (the device's PSFs integrated over
the sub-steps, read by its detector), the reconstruction, the mirror (fit, controller, surface) and the
power in the bucket (the back-propagated corrected beam); "other" is the rest of the step (residual rms,
branch points, modal coefficients).  Goal: <= 10 min of wall time per second of link time on 2 cores.

    python benchmarks/bench_loop.py [--steps 40] [--json]
"""

import argparse
import copy
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np

LINK_STEPS = 2000  # one second at 2 kHz
GOAL_S = 600.0  # 10 min of wall time per second of link time ...
GOAL_CORES = 2  # ... on 2 cores
PARTS = ("screens", "propagation", "exposure", "reconstruction", "mirror", "pib")


def _timed(fn, part, acc):
    def wrapper(*a, **k):
        t = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            acc[part] += time.perf_counter() - t

    return wrapper


def _recipe(folder: Path) -> Path:
    """loop-demo.toml with absolute paths, the two closed loops, the U-Net's latency declared 0."""
    s = REPO / "sensing"
    p = folder / "loop-bench.toml"
    p.write_text(f'[device]\ndesign = "{REPO / "layouts" / "paper-5mm.toml"}"\nsensor = "{s / "paper.toml"}"\n'
                 f'turbulence = "{s / "turbulence.toml"}"\nmodel = "{s / "models" / "demo-refine.safetensors"}"\n'
                 '[loop]\nrate_hz = 2000.0\nsteps = 2000\nsubsteps = 4\nrytov = 0.5\ngain = 0.4\nleak = 0.99\n'
                 'noise_percent = 5.0\nmethods = ["unet", "ideal"]\nlatency_ms = {unet = 0}\nseed = 0\n'
                 '[dm]\nactuators = 12\ncoupling = 0.15\nregularisation = 1e-3\n[wind]\nspeed_m_s = 2.7\n')
    return p


def _run(ctx, m: str, steps: int) -> dict:
    """``steps`` frames of method ``m`` with every part of the step timed (a copy of the world, sensor and
    mirror whose methods are wrapped; the engine itself untouched)."""
    from metadesign.optics.control import Controller
    from metadesign.studies.loop import run_loop

    acc = dict.fromkeys(PARTS, 0.0)
    world = copy.copy(ctx.world(0))
    world.screens_at = _timed(world.screens_at, "screens", acc)
    world.received = _timed(world.received, "propagation", acc)
    world.npib = _timed(world.npib, "pib", acc)
    sensor = copy.copy(ctx.sensor(m, 0))
    sensor.expose = _timed(sensor.expose, "exposure", acc)
    sensor.reconstruct = _timed(sensor.reconstruct, "reconstruction", acc)
    dm = copy.copy(ctx.dm)
    for name in ("fit", "surface", "clip"):
        setattr(dm, name, _timed(getattr(dm, name), "mirror", acc))
    timing = ctx.timing(m)
    lp = ctx.rec.loop
    ctl = Controller(lp.gain, timing.delay_frames, lp.leak)
    ctl.step = _timed(ctl.step, "mirror", acc)
    run_loop(world, timing, 2, m, copy.copy(sensor), copy.copy(dm), Controller(lp.gain, timing.delay_frames, lp.leak),
             ctx.modes)  # warm-up (the mirror's reconstructor, torch's first calls)
    acc.update(dict.fromkeys(PARTS, 0.0))
    t0 = time.perf_counter()
    s = run_loop(world, timing, steps, m, sensor, dm, ctl, ctx.modes, pseudo_open_loop=lp.pseudo_open_loop)
    total = time.perf_counter() - t0
    acc["other"] = total - sum(acc[p] for p in PARTS)
    return {"seconds": total, "parts": acc, "npib_mean": float(np.mean(s["npib"]))}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=40, help="frames measured per method (scaled to 2,000)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from metadesign.studies.loop_recipe import load_loop_recipe
    from metadesign.studies.loop_study import build_loop
    from metadesign.turbulence.frozen import FrozenFlow

    with tempfile.TemporaryDirectory() as tmp:
        rec = load_loop_recipe(_recipe(Path(tmp)))
        t = time.perf_counter()
        ctx, _, temporal = build_loop(rec, Path(tmp) / "out", lambda *_: None)
        build = time.perf_counter() - t
        lp = rec.loop
        t = time.perf_counter()
        FrozenFlow(ctx.tb.grid, ctx.tb.path.r0_screens, ctx.wind, 1.0 / (lp.rate_hz * lp.substeps),
                   LINK_STEPS * lp.substeps, 0)
        draw = time.perf_counter() - t  # the long screens of one second of link time, once per realisation
        ctx.world(0)  # the measured run's own (shorter) draw, not timed
        res = {"device": "sensing/loop-demo.toml (paper-5mm)", "grid": ctx.tb.sc.n_grid,
               "screens": ctx.tb.sc.n_screens, "rate_hz": lp.rate_hz, "substeps": lp.substeps,
               "greenwood_hz": temporal["greenwood_hz"], "steps_measured": a.steps, "link_steps": LINK_STEPS,
               "build_s": build, "flow_draw_per_link_s": draw, "threads": 1, "methods": {}}
        for m in ("ideal", "unet"):
            r = _run(ctx, m, a.steps)
            scale = LINK_STEPS / a.steps
            per_link = r["seconds"] * scale + draw
            parts = {p: v * scale for p, v in r["parts"].items()}
            parts["screens"] += draw
            res["methods"][m] = {"ms_per_step": r["seconds"] / a.steps * 1e3, "s_per_link_s_per_core": per_link,
                                 "parts_s_per_link_s": parts,
                                 "parts_fraction": {p: v / per_link for p, v in parts.items()},
                                 "wall_on_goal_cores_s": per_link / GOAL_CORES,
                                 "ratio_to_goal": per_link / GOAL_CORES / GOAL_S, "npib_mean": r["npib_mean"]}
    if a.json:
        print(json.dumps(res, indent=1))
        return 0
    print(f"{res['device']}: {res['grid']}^2, {res['screens']} screens, {lp.rate_hz:g} Hz x {lp.substeps} sub-steps, "
          f"f_G {res['greenwood_hz']:.0f} Hz; one core; {a.steps} steps measured, scaled to {LINK_STEPS} (1 s of link)")
    print(f"  build (design, system, sensors) {build:.1f} s, once; long screens for 1 s of link {draw:.2f} s")
    for m, r in res["methods"].items():
        split = ", ".join(f"{p} {r['parts_fraction'][p] * 100:.0f} %" for p in PARTS + ("other",))
        print(f"  {m:<6} {r['ms_per_step']:.0f} ms/step -> {r['s_per_link_s_per_core']:.0f} s per second of link per core; "
              f"on {GOAL_CORES} cores {r['wall_on_goal_cores_s'] / 60:.1f} min = {r['ratio_to_goal']:.2f}x the goal "
              f"(<= 10 min)")
        print(f"         {split}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

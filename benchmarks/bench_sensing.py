"""As-fabricated forward model benchmark (paper design).

Prints: the per-sample PSF time of the fast path (8 quadrant MFTs from the
coarse pupil, default 256^2 grid) on one core, the ratio to a full
angular-spectrum propagation of the same pupil (sampled finely enough for the
f/10 lens, padded to hold the sensor); the one-off coarse-pupil build; and the
full-resolution 5 mm verification (51 M pillars, chunked, complex64) time and
peak RSS with its agreement with the fast path.

    python benchmarks/bench_sensing.py [--json]
"""

import json
import os
import resource
import sys
import time
from pathlib import Path

os.environ.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def main() -> int:
    import subprocess

    from metadesign.optics.propagation import angular_spectrum, cexp
    from metadesign.sensing.forward import full_resolution_frames, sensor_frames
    from metadesign.sensing.model import AsFabricated, load_sensing_recipe
    from metadesign.sensing.sensor import quadrant_slices
    from metadesign.sensing.transmission import pillar_transmission

    lay = REPO / "layouts" / "paper-5mm" / "layout.oas"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    if not lay.exists():
        for args in (["design", REPO / "layouts" / "paper-5mm.toml"], ["layout", REPO / "layouts" / "paper-5mm"]):
            subprocess.run([sys.executable, "-m", "metadesign", *map(str, args)], env=env, check=True,
                           capture_output=True)
    res = {}
    t0 = time.perf_counter()
    fab = AsFabricated.from_files(lay)
    res["read_layout_s"] = time.perf_counter() - t0
    sr = load_sensing_recipe(REPO / "sensing" / "paper.toml")
    t0 = time.perf_counter()
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid)
    res["coarse_pupil_build_s"] = time.perf_counter() - t0
    res["pupil_grid"] = int(cp.G.shape[-1])
    rng = np.random.default_rng(0)
    e_in = cexp(rng.normal(0, 0.3, cp.G.shape[-2:]))
    sensor_frames(cp, sr.sensor, e_in)
    t0 = time.perf_counter()
    reps = 5
    for _ in range(reps):
        sensor_frames(cp, sr.sensor, e_in)
    res["fast_per_sample_s"] = (time.perf_counter() - t0) / reps
    # angular spectrum of the same pupil: 2x finer than the coarse grid (the lens needs dx <= 15.5 um),
    # padded 2x, both polarisations, one FFT pair each
    n = 2 * cp.G.shape[-1]
    u = np.zeros((2 * n, 2 * n), np.complex64)
    t0 = time.perf_counter()
    for p in range(2):
        u[: n, : n] = np.repeat(np.repeat(cp.G[p].sum(0), 2, 0), 2, 1)
        angular_spectrum(u, cp.pitch / 2, fab.wavelength, sr.sensor.distance)
    res["asm_per_sample_s"] = time.perf_counter() - t0
    res["ratio_asm_over_fast"] = res["asm_per_sample_s"] / res["fast_per_sample_s"]
    # ... but that grid (9.8 um) cannot resolve a 19 um Airy radius: sampling the focal plane at the
    # sensor's pixel pitch (1.5 um) needs the pupil at that pitch: N = 4096 (5 mm / 1.5 um, padded)
    n_fine = 1 << int(np.ceil(np.log2(fab.n_cells * fab.period / sr.sensor.focal_pitch)))
    big = np.zeros((n_fine, n_fine), np.complex64)
    big[: n, : n] = 1
    t0 = time.perf_counter()
    for p in range(2):
        angular_spectrum(big, sr.sensor.focal_pitch, fab.wavelength, sr.sensor.distance)
    res["asm_sensor_sampled_per_sample_s"] = time.perf_counter() - t0
    res["asm_sensor_grid"] = n_fine
    res["ratio_asm_sensor_sampled_over_fast"] = res["asm_sensor_sampled_per_sample_s"] / res["fast_per_sample_s"]

    def rows(r0, r1):
        return pillar_transmission(fab.layout.index_map, fab.layout.atom_widths_nm, fab.lib, rows=slice(r0, r1))

    t0 = time.perf_counter()
    full, _ = full_resolution_frames(rows, fab.n_cells, fab.period, fab.wavelength, sr.sensor, fab.tn_scale,
                                     window=64)
    res["full_resolution_s"] = time.perf_counter() - t0
    res["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    flat = sensor_frames(cp, sr.sensor)
    errs = []
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sr.sensor, k)
            a, b = full[p][r, c], flat[p][r, c]
            m = a > 0
            errs.append(float(np.linalg.norm(a[m] - b[m]) / np.linalg.norm(a[m])))
    res["fast_vs_full_rel_l2_max"] = max(errs)
    if "--json" in sys.argv:
        print(json.dumps(res, indent=2))
    else:
        print(f"paper layout read back in {res['read_layout_s']:.1f} s; coarse pupil {res['pupil_grid']}^2 built in "
              f"{res['coarse_pupil_build_s']:.1f} s (once per design and distance)")
        print(f"fast path per sample (8 PSFs, 1 core)   {res['fast_per_sample_s'] * 1e3:.1f} ms")
        print(f"angular spectrum, same pupil            {res['asm_per_sample_s'] * 1e3:.1f} ms  "
              f"(ratio {res['ratio_asm_over_fast']:.1f}x; output on a 9.8 um grid, too coarse for the PSFs)")
        print(f"angular spectrum at sensor sampling     {res['asm_sensor_sampled_per_sample_s'] * 1e3:.0f} ms  "
              f"(ratio {res['ratio_asm_sensor_sampled_over_fast']:.0f}x; {res['asm_sensor_grid']}^2 grid of 1.5 um)")
        print(f"full-resolution 5 mm verification       {res['full_resolution_s']:.1f} s, peak RSS "
              f"{res['peak_rss_gb']:.2f} GB (64x64 px per quadrant, 51 M pillars, chunked complex64)")
        print(f"fast vs full resolution                 max rel. L2 {res['fast_vs_full_rel_l2_max']:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

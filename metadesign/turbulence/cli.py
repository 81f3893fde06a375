"""``metadesign turbulence show|validate`` (stage 5 CLI)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from ..cliutil import SEED, emit, integer, num, out_dir, progress_bar
from ..validation import ValidationError

__all__ = ["register"]

RYTOV = num(0, 5, open_lo=True)


def _scenario(a):
    from ..paths import repo_root
    from .scenario import load_scenario

    return load_scenario(a.recipe or repo_root() / "sensing" / "turbulence.toml")


def _cmd_show(a: argparse.Namespace) -> int:
    from .path import check_sampling, solve_path

    sc = _scenario(a)
    if a.rytov is not None:
        sc = replace(sc, rytov=a.rytov)
    pm = solve_path(sc)
    rep = check_sampling(sc, pm)
    info = {"rytov": sc.rytov, "cn2": pm.cn2, "r0_m": pm.r0, "D_over_r0": sc.receiver_aperture / pm.r0,
            "r0_screens_m": [float(x) for x in pm.r0_screens], "rytov_screens": pm.rytov_screens.tolist(),
            "rytov_achieved": pm.rytov_achieved, "sampling_ok": rep.ok, "constraints": rep.constraints,
            "failures": list(rep.failures), "magnification": sc.magnification,
            "memory_per_sample_bytes": sc.sample_bytes}
    lines = [f"Rytov {sc.rytov:g}: Cn^2 {pm.cn2:.3g} m^-2/3, r0 {pm.r0 * 100:.2f} cm, D/r0 "
             f"{info['D_over_r0']:.2f}, screens' Rytov " + " ".join(f"{v:.3f}" for v in pm.rytov_screens),
             f"sampling: {'OK' if rep.ok else 'INFEASIBLE'}"]
    lines += [f"  {k}: {v[0]:.4g} vs {v[1]:.4g}" for k, v in rep.constraints.items()]
    lines += [f"  ! {f}" for f in rep.failures]
    lines += _wind_lines(a, sc, info)
    emit(info, a.json, "\n".join(lines))
    return 0 if rep.ok else 2


def _wind_lines(a, sc, info: dict) -> list[str]:
    """f_G and tau0 when the recipe has [wind] (added to ``info``); nothing otherwise."""
    from ..paths import repo_root
    from .scenario import load_wind
    from .temporal import temporal_summary

    wind = load_wind(a.recipe or repo_root() / "sensing" / "turbulence.toml", sc)
    if wind is None:
        return []
    t = temporal_summary(sc, wind)
    info.update(t)
    return [f"wind: Greenwood frequency {t['greenwood_hz']:.1f} Hz, tau0 {t['tau0_s'] * 1e3:.3g} ms, v_5/3 "
            f"{t['v53_m_s']:.3g} m/s (plane-wave path weighting; spherical-wave f_G "
            f"{t['greenwood_spherical_hz']:.1f} Hz)"]


def _cmd_validate(a: argparse.Namespace) -> int:
    from ..io import atomic_write_text
    from ..outputs import product
    from .path import check_sampling, solve_path
    from .validate import plot_validation, validate

    sc = _scenario(a)
    rytovs = a.rytov or [0.1, 0.3, 0.5, 0.7]
    for r in rytovs:  # refuse infeasible sampling before any work
        rep = check_sampling(replace(sc, rytov=r), solve_path(replace(sc, rytov=r)))
        if not rep.ok:
            raise ValidationError(f"Rytov {r:g}: infeasible sampling: " + "; ".join(rep.failures))
    out = out_dir(a.output)
    with product(out, "turbulence-validation", {"recipe": a.recipe}):
        res = validate(sc, rytovs, a.samples, a.seed, progress=progress_bar("turbulence", unit="sample"))
        figs = plot_validation(res, out)
        atomic_write_text(out / "turbulence-validation.json", json.dumps(res, default=float))
    sf = res["structure_function"]
    lines = [f"wrote {', '.join(f.name for f in figs)} and turbulence-validation.json to {out}",
             "structure function / theory: " + " ".join(f"{x:.3f}" for x in sf["ratio"])
             + f" (separations {sf['r_m'][0] * 1e3:g}..{sf['r_m'][-1] * 1e3:g} mm)",
             "Rytov nominal -> measured (weak theory with inner scale), D/r0, NPiB complex / phase / none:"]
    for lv in res["levels"]:
        nb = {k: float(np.mean(v)) for k, v in lv["npib"].items()}
        lines.append(f"  {lv['rytov_nominal']:.2f} -> {lv['rytov_measured']:.3f} ({lv['rytov_weak_theory_inner_scale']:.3f}),"
                     f" D/r0 {lv['D_over_r0']:.2f}, NPiB {nb['complex']:.3f} / {nb['phase']:.3f} / {nb['none']:.3f}")
    summary = {"structure_function": sf, "levels": [{k: v for k, v in lv.items() if k in (
        "rytov_nominal", "rytov_measured", "rytov_weak_theory_inner_scale", "r0_m", "D_over_r0")}
        | {"npib_mean": {k: float(np.mean(v)) for k, v in lv["npib"].items()}} for lv in res["levels"]],
        "figures": [str(f) for f in figs]}
    emit(summary, a.json, "\n".join(lines))
    return 0


def register(sub) -> None:
    tu = sub.add_parser(
        "turbulence", help="stage 5: turbulence show (path, r0, sampling) | turbulence validate (Figs. S5, S6)",
        description="Stage 5. `turbulence show` solves the path (Rytov -> Cn^2 -> r0 -> per-screen r0) and checks "
        "the split-step sampling constraints (exit 2 when infeasible). `turbulence validate` compares screens and "
        "received fields with theory: structure function, log-amplitude variance vs nominal Rytov, coherence "
        "factor, long-exposure MTF, and power in bucket after phase-only / complex-field / no correction.")
    tsub = tu.add_subparsers(dest="turbulence_command", metavar="ACTION")
    tsub.required = True
    s = tsub.add_parser("show", help="path model, r0, per-screen r0, sampling constraints, memory")
    s.add_argument("recipe", nargs="?", help="scenario recipe (default: sensing/turbulence.toml)")
    s.add_argument("--rytov", type=RYTOV, help="Rytov number in (0, 5] (default: the recipe's)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.set_defaults(func=_cmd_show)
    v = tsub.add_parser("validate", help="screens and received fields against theory (Figs. S5, S6)")
    v.add_argument("recipe", nargs="?", help="scenario recipe (default: sensing/turbulence.toml)")
    v.add_argument("--rytov", type=RYTOV, nargs="+", help="Rytov numbers in (0, 5] (default: 0.1 0.3 0.5 0.7)")
    v.add_argument("--samples", type=integer(2, 100000), default=40, help="samples per Rytov number (default 40)")
    v.add_argument("--seed", type=SEED, default=0, help="master seed")
    v.add_argument("-o", "--output", default="turbulence-out", help="output folder (default: ./turbulence-out)")
    v.add_argument("--json", action="store_true", help="print the summary as JSON")
    v.set_defaults(func=_cmd_validate)

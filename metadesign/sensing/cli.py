"""``metadesign psf`` and ``metadesign fab-study`` (stage 4 CLI)."""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np

from ..cliutil import SEED, emit, integer, num, out_dir, progress_bar, workers_arg
from ..config import InputError
from ..outputs import product


__all__ = ["register"]

BIAS = num(-200, 200, unit="nm")
JITTER = num(0, 100, unit="nm")
CORNER = num(0, 500, unit="nm")


def _inputs(a: argparse.Namespace, *names: str) -> dict:
    """The declared inputs of a command: the named options' paths (those given)."""
    if Path(a.layout).is_dir():
        raise InputError(f"{a.layout}: is a folder, expected a layout file (.oas or .gds)")
    return {("" if n == "layout" else "--") + n.replace("_", "-"): getattr(a, n, None) for n in names}


def _sensing_recipe(a):
    from ..paths import repo_root
    from .model import load_sensing_recipe

    return load_sensing_recipe(a.sensor or repo_root() / "sensing" / "paper.toml")


def _read_wavefront(path: str):
    from ..io import read_npz

    z = read_npz(path, "wavefront file")
    if "field" not in z:
        raise InputError(f"{path}: expected a complex array 'field' on the coarse pupil grid")
    from ..validation import check_finite_array

    return check_finite_array(f"{path}: field", z["field"])


def _cmd_psf(a: argparse.Namespace) -> int:
    from .plot import plot_frames
    from .render import check_field, full_resolution_check, render_psf, save_psf
    from .transmission import Perturbation

    sr = _sensing_recipe(a)
    if len(a.bias_nm) > 2:
        raise InputError(f"--bias-nm: one value (both axes) or two (x y), got {len(a.bias_nm)}")
    pert = Perturbation.from_nm(a.bias_nm[0], a.bias_nm[-1], a.jitter_nm, a.corner_nm, a.seed)
    if a.full_resolution is not None:
        qmax = min(sr.sensor.width_px, sr.sensor.height_px) // 2
        if not 1 <= a.full_resolution <= qmax:
            raise InputError(f"--full-resolution: expected an integer in [1, {qmax}] (pixels of a quadrant), "
                             f"got {a.full_resolution}")
        if a.wavefront:
            raise InputError("--full-resolution checks the flat-wavefront PSFs; omit --wavefront")
    beside = _beside(a.beside, sr) if a.beside else None
    out = out_dir(a.output if a.output else Path(a.layout).with_name("psf"))
    with product(out, "psf", _inputs(a, "layout", "sensor", "library", "coupling_model", "wavefront", "beside")):
        field = _read_wavefront(a.wavefront) if a.wavefront else None
        fab = _device(a, sr)
        pupil = fab.pupil(sr.sensor.distance, sr.pupil_grid, pert, progress_bar("pupil", unit="block-row"),
                          workers=a.workers)
        if field is not None:
            field = check_field(field, pupil, f"{a.wavefront}: field")
        res = render_psf(fab, sr, field, pert, pupil=pupil, noise=sr.noise if sr.noise.active else None)
        full_check = None
        if a.full_resolution:
            clean = res.frames if not sr.noise.active else render_psf(fab, sr, None, pert, pupil=pupil).frames
            full_check = full_resolution_check(fab, sr, clean, a.full_resolution, pert,
                                               progress_bar("full resolution", unit="row"))
        save_psf(out / "psf.npz", res, fab, sr, {"wavefront": str(a.wavefront) if a.wavefront else None})
        name = f"{fab.layout.provenance.get('design') or Path(a.layout).name} ({fab.n_cells * fab.period * 1e3:.3g} mm)"
        fig = plot_frames(res.frames, sr.sensor, out / "psf-fig-2c.png", fab.channels,
                          f"{name}: sensor frames (bias {a.bias_nm} nm, jitter {a.jitter_nm} nm)", beside, name)
    cp = res.pupil
    summary = {"output": str(out), "frames_shape": list(res.frames.shape), "tensor_shape": list(res.tensor.shape),
               "pupil_grid": list(cp.G.shape[-2:]), "block_cells": cp.block, "clamped_pillars": cp.n_clamped,
               "power_per_frame": [float(f.sum()) for f in res.frames], "figure": str(fig),
               "aperture_m2": (fab.n_cells * fab.period) ** 2, "full_resolution_check": full_check}
    text = (f"wrote {out}/psf.npz (frames 2x{sr.sensor.height_px}x{sr.sensor.width_px}, tensor "
            f"{tuple(res.tensor.shape)}) and {Path(fig).name}; coarse pupil {cp.G.shape[-1]}^2 ({cp.block}x{cp.block} "
            f"cells per sample); power on sensor x {summary['power_per_frame'][0] / summary['aperture_m2']:.3f} "
            f"y {summary['power_per_frame'][1] / summary['aperture_m2']:.3f} of incident; "
            f"{cp.n_clamped} pillars outside the library range (clamped)")
    if full_check:
        text += (f"\nfull-resolution check ({a.full_resolution}x{a.full_resolution} px per quadrant, every pillar): "
                 f"fast path within {max(full_check['rel_l2_per_channel']):.2e} relative L2")
    emit(summary, a.json, text)
    return 0


def _cmd_fab_study(a: argparse.Namespace) -> int:
    from .render import FabCases, fab_study, write_fab_study

    sr = _sensing_recipe(a)
    if a.seed + a.seeds - 1 > 2**63 - 1:
        raise InputError("--seed: the last jitter seed (--seed + --seeds - 1) exceeds 2^63 - 1")
    out = out_dir(a.output if a.output else Path(a.layout).with_name("fab-study"))
    with product(out, "fab-study", _inputs(a, "layout", "sensor", "library", "coupling_model", "fab_library")):
        fab = _device(a, sr)
        needs_axes = any(h for h in a.height_nm) or any(x != 90 for x in a.sidewall_deg) or a.height_gradient_nm \
            or a.sidewall_gradient_deg
        if a.fab_library:
            from ..library.store import load_library

            fab.fab_lib = load_library(a.fab_library)
        if needs_axes and fab.fab_lib is None and fab.lib.fab is None:
            raise InputError("--height-nm / --sidewall-deg need a library with height and sidewall axes: build one "
                             "with a [fab_axes] recipe section and pass it as --fab-library")
        cases = FabCases(tuple(a.bias_nm), tuple(a.jitter_nm), tuple(a.corner_nm), tuple(a.height_nm),
                         tuple(a.sidewall_deg), a.seeds, a.seed, a.height_gradient_nm, a.sidewall_gradient_deg)
        rows = fab_study(fab, sr, cases, progress_bar("fab-study", unit="case"))
        files = write_fab_study(rows, out)
    n_cases = len(a.bias_nm) * len(a.jitter_nm) * len(a.corner_nm) * len(a.height_nm) * len(a.sidewall_deg) * a.seeds
    lines = [f"wrote {out}/fab-study.csv, fab-study.png ({n_cases} cases x 8 channels)",
             "  bias  jitter corner height wall | mean eff  mean Strehl  mean |focal shift| mm  mean crosstalk  clamped"]
    for b, j, c, h, w in itertools.product(a.bias_nm, a.jitter_nm, a.corner_nm, a.height_nm, a.sidewall_deg):
        rr = [r for r in rows if (r["bias_nm"], r["jitter_nm"], r["corner_nm"], r["height_nm"], r["sidewall_deg"])
              == (b, j, c, h, w)]
        lines.append(f"  {b:+5g} {j:6g} {c:6g} {h:+6g} {w:4g} | {np.mean([r['focusing_efficiency'] for r in rr]):.4f}    "
                     f"{np.mean([r['strehl'] for r in rr]):.4f}       "
                     f"{np.mean([abs(r['focal_shift_mm']) for r in rr]):.4f}                "
                     f"{np.mean([r['crosstalk'] for r in rr]):.4f}         {max(r['clamped_pillars'] for r in rr)}")
    emit({"rows": rows, "files": [str(f) for f in files]}, a.json, "\n".join(lines))
    return 0


def _cmd_phasemap(a: argparse.Namespace) -> int:
    from .phasemap import phase_maps, plot_phase_maps, save_phase_maps
    from .transmission import Perturbation

    if len(a.bias_nm) > 2:
        raise InputError(f"--bias-nm: one value (both axes) or two (x y), got {len(a.bias_nm)}")
    pert = Perturbation.from_nm(a.bias_nm[0], a.bias_nm[-1], a.jitter_nm, a.corner_nm, a.seed)
    out = out_dir(a.output if a.output else Path(a.layout).with_name("phasemap"))
    with product(out, "phasemap", _inputs(a, "layout", "library", "coupling_model")):
        fab = _device(a)
        maps = phase_maps(fab, pert, tuple(a.window) if a.window else None, a.bin,
                          progress=progress_bar("phasemap", unit="row"))
        f = save_phase_maps(out / "phasemap.npz", maps, {"layout": str(a.layout), "perturbation": pert.to_dict()})
        fig = plot_phase_maps(maps, out / "phasemap.png", f"{Path(a.layout).name}: as-fabricated phase "
                              f"(bias {a.bias_nm} nm, jitter {a.jitter_nm} nm, corner {a.corner_nm} nm)")
    st = maps["stats"]
    w = maps["window"]
    lines = [f"wrote {f} and {fig.name}: window ({w['ix0']}, {w['iy0']}) {w['cells']}^2 pillars at full resolution, "
             f"whole aperture in {maps['binned']['supercells_per_bin']}^2-supercell bins "
             f"({maps['binned']['residual'].shape[-1]}^2 per channel)",
             f"  residual vs design (per-polarisation offset {maps['offset_rad'][0]:+.3f} / {maps['offset_rad'][1]:+.3f}"
             f" rad removed): window RMS x {st['window_residual_rms_rad'][0]:.3f}, y {st['window_residual_rms_rad'][1]:.3f} rad"]
    for p in range(2):
        lines.append(f"  {'xy'[p]}-pol binned residual RMS per channel: "
                     + ", ".join("-" if v is None else f"{v:.3f}" for v in st["binned_residual_rms_rad"][p]) + " rad")
    emit({"output": str(out), "files": [str(f), str(fig)], "offset_rad": maps["offset_rad"], "stats": st,
          "window": {k: w[k] for k in ("ix0", "iy0", "cells")},
          "supercells_per_bin": maps["binned"]["supercells_per_bin"]}, a.json, "\n".join(lines))
    return 0


def _beside(path: str, sr) -> tuple:
    """(frames, channels, label) of another device's PSF product on the same camera (``--beside``)."""
    from .model import channels_from_provenance
    from .render import load_psf

    z, meta = load_psf(path)
    mine, theirs = sr.sensor.to_dict(), meta.get("sensor") or {}
    keys = ("width_px", "height_px", "pixel_um", "magnification")
    if any(theirs.get(k) != mine.get(k) for k in keys):
        raise InputError(f"--beside {path}: its camera ({', '.join(f'{k} {theirs.get(k)}' for k in keys)}) is not "
                         "this sensor's; frames side by side need the same pixels")
    chans, _ = channels_from_provenance({"channels": meta.get("channels") or []})
    ap = meta.get("aperture_m")
    design = (meta.get("layout") or {}).get("design") or Path(path).parent.name
    return z["frames"], chans, f"{design}" + (f" ({ap * 1e3:.3g} mm)" if ap else "")


def _forward_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("layout", help="layout file (.oas/.gds) written by `metadesign layout`")
    p.add_argument("--sensor", help="sensing recipe (default: sensing/paper.toml)")
    p.add_argument("--library", help="unit-cell library (default: the one recorded in the layout, found by sha256)")
    p.add_argument("--coupling", choices=("lpa", "supercell", "coupling", "peds"), help="the supercell model "
                   "(metadesign.library.surrogates): lpa: every pillar as in an infinite array of itself; coupling "
                   "(or supercell): plus its neighbours' coupling from the coupling network; peds: the certified "
                   "surrogate, sampled by `library coupling-check --certified` (default: the sensing recipe's "
                   "pupil.coupling, else lpa)")
    p.add_argument("--coupling-model", help="the supercell coupling model (default: the one fitted against the "
                   "layout's library, found in library/)")


def _device(a, sr=None):
    """The as-fabricated device of ``a.layout`` with the coupling the options (else the recipe) choose."""
    from .model import AsFabricated

    fab = AsFabricated.from_files(a.layout, a.library)
    kind = a.coupling or (sr.coupling if sr is not None else "lpa")
    model = a.coupling_model or (sr.coupling_model if sr is not None else None)
    if a.coupling_model and kind not in ("supercell", "coupling"):
        raise InputError("--coupling-model needs --coupling coupling (or supercell)")
    return fab if kind == "lpa" else fab.with_coupling(kind, model)


def register(sub) -> None:
    psf = sub.add_parser(
        "psf", help="stage 4: as-fabricated 8 PSFs of a layout on the sensor (Fig. 2c)",
        description="Stage 4. Rebuild the complex transmission from the layout file itself (pillars read back, "
        "optional fab perturbations, complex-t interpolation in the full RCWA library), propagate to the sensor "
        "with the fast coarse-pupil Fresnel path, and write OUT/psf.npz (frames 2 x H x W, tensor 8 x S x S in "
        "the order x-pol QI..QIV, y-pol QI..QIV, and provenance) and OUT/psf-fig-2c.png.")
    _forward_args(psf)
    psf.add_argument("--wavefront", help=".npz with a complex 'field' on the pupil grid (default: flat)")
    psf.add_argument("--beside", metavar="PSF_NPZ", help="another device's psf.npz on the same camera (e.g. the "
                     "5 mm paper device's): its frames drawn under these in psf-fig-2c.png")
    psf.add_argument("--bias-nm", type=BIAS, nargs="+", default=[0.0], help="width bias in [-200, 200] nm: one "
                     "value or x y")
    psf.add_argument("--jitter-nm", type=JITTER, default=0.0, help="random width jitter sigma in [0, 100] nm")
    psf.add_argument("--corner-nm", type=CORNER, default=0.0, help="corner rounding radius in [0, 500] nm")
    psf.add_argument("--seed", type=SEED, default=0, help="jitter seed")
    psf.add_argument("--full-resolution", type=integer(1, 4096), metavar="PX",
                     help="also evaluate every pillar without block averaging on the central PX x PX pixels of "
                     "each quadrant (chunked, bounded memory) and report the fast path's error")
    psf.add_argument("-o", "--output", help="output folder (default: psf/ beside the layout)")
    workers_arg(psf, default=1, what="worker processes for the pupil (block-row shares; large apertures: -j 2)")
    psf.add_argument("--json", action="store_true", help="print the summary as JSON")
    psf.set_defaults(func=_cmd_psf)

    fs = sub.add_parser(
        "fab-study", help="stage 4: sweep fab perturbations: efficiency, Strehl, focal/centroid shift, crosstalk",
        description="For every combination of --bias-nm, --jitter-nm, --corner-nm (and --seeds jitter draws), "
        "rebuild the as-fabricated pupil and report per channel: focusing efficiency (power in the designed "
        "quadrant / incident), Strehl ratio at best focus, focal shift, centroid shift, crosstalk into the other "
        "quadrants. Writes OUT/fab-study.csv, .json and .png.")
    _forward_args(fs)
    fs.add_argument("--bias-nm", type=BIAS, nargs="+", default=[-10.0, 0.0, 10.0], help="width biases (nm)")
    fs.add_argument("--jitter-nm", type=JITTER, nargs="+", default=[0.0], help="jitter sigmas (nm)")
    fs.add_argument("--corner-nm", type=CORNER, nargs="+", default=[0.0], help="corner radii (nm)")
    fs.add_argument("--height-nm", type=num(-500, 500), nargs="+", default=[0.0],
                    help="etch depth errors (pillar height - nominal, nm); needs --fab-library")
    fs.add_argument("--sidewall-deg", type=num(60, 90), nargs="+", default=[90.0],
                    help="sidewall angles (deg, 90 = vertical); needs --fab-library")
    fs.add_argument("--height-gradient-nm", type=num(-500, 500), default=0.0,
                    help="extra etch depth error at the aperture's +x edge (opposite at -x), nm")
    fs.add_argument("--sidewall-gradient-deg", type=num(-30, 30), default=0.0,
                    help="extra sidewall angle at the aperture's +x edge (opposite at -x)")
    fs.add_argument("--fab-library", help="library with height / sidewall axes ([fab_axes]); its difference from "
                    "its nominal slice corrects the layout's library")
    fs.add_argument("--seeds", type=integer(1, 1000), default=1, help="jitter draws per case")
    fs.add_argument("--seed", type=SEED, default=0, help="first jitter seed")
    fs.add_argument("-o", "--output", help="output folder (default: fab-study/ beside the layout)")
    fs.add_argument("--json", action="store_true", help="print the rows as JSON")
    fs.set_defaults(func=_cmd_fab_study)

    pm = sub.add_parser(
        "phasemap", help="stage 4: as-fabricated phase and amplitude maps of a layout, and their residual vs design",
        description="Per polarisation: the as-fabricated phase and amplitude of every pillar in a window (full "
        "resolution), the wrapped design phase and the residual; over the whole aperture, per channel, the "
        "residual phase and amplitude averaged over bins of supercells. Writes OUT/phasemap.npz (np.load with "
        "allow_pickle=False) and OUT/phasemap.png.")
    _forward_args(pm)
    pm.add_argument("--window", type=integer(0, 10**7), nargs=3, metavar=("IX0", "IY0", "CELLS"),
                    help="full-resolution window: first column, first row, size in pillars (default: central 64)")
    pm.add_argument("--bin", type=integer(1, 10**6), help="supercells per bin of the whole-aperture maps "
                    "(default: at most 512 bins across)")
    pm.add_argument("--bias-nm", type=BIAS, nargs="+", default=[0.0], help="width bias in [-200, 200] nm: one "
                    "value or x y")
    pm.add_argument("--jitter-nm", type=JITTER, default=0.0, help="random width jitter sigma in [0, 100] nm")
    pm.add_argument("--corner-nm", type=CORNER, default=0.0, help="corner rounding radius in [0, 500] nm")
    pm.add_argument("--seed", type=SEED, default=0, help="jitter seed")
    pm.add_argument("-o", "--output", help="output folder (default: phasemap/ beside the layout)")
    pm.add_argument("--json", action="store_true", help="print the summary as JSON")
    pm.set_defaults(func=_cmd_phasemap)

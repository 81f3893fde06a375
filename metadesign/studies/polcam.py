"""Which polarisation camera to buy (issue #52): the captured fraction of the U-Net and its refinement when the two
frames come from one division-of-focal-plane camera (:mod:`metadesign.sensing.mosaic`) instead of two ideal frames,
against the micro-polarisers' extinction ratio and the mosaic's resolution, without retraining.

For every sample of a dataset split the study regenerates the beacon exactly as the dataset build drew it (its
screens from its seed, the split step, the field on the metasurface), renders it through each camera of the recipe
(a grid of extinction ratios x mosaic pitches, plus named variants: unmixed, diagonal pixels, crosstalk), normalises
the PSF tensor as the datasets do and draws the evaluation's sensor noise on it (``noise_percent`` of each channel's
peak, the seed of every evaluation, :data:`~metadesign.reconstruction.metrics.EVAL_NOISE_SEED`: the same draws for
every camera, so the comparisons are paired), and scores the model's corrections by the power in the bucket through
the sample's own screens.  The ideal camera's tensors are the dataset's own (today's frames): its row is what
``metadesign evaluate`` reports.  A refiner is scored at its U-Net's estimate (``unet``) and after its steps
(``refine``); its twin keeps rendering an ideal camera's frames.

The recipe (``metadesign polcam RECIPE``; paths relative to it):

.. code-block:: toml

    [study]
    dataset = "dataset-demo"
    model = "models/demo-refine.safetensors"   # a refiner (its U-Net too), or a U-Net
    split = "test"
    limit = 160
    noise_percent = 5.0
    extinction_ratios = [0.0, 300.0, 100.0, 30.0]   # 0: ideal polarisers
    pixel_pitch_um = [7.5, 15.0]     # the mosaic's pitch on the camera (the sensor's 15 um: frames 2x coarser)
    tolerance = 0.02                 # captured fraction allowed below the ideal camera's

    [camera]                         # every camera's other settings (the sensing recipe's [camera] keys)
    crosstalk_percent = 0.0

    [[variant]]                      # further cameras: [camera] with these keys changed
    label = "ER 30, unmixed"
    extinction_ratio = 30.0
    pixel_pitch_um = 7.5
    unmix = true

Retraining on the camera's frames is not part of the study (it needs a dataset rendered through the camera: the
``[camera]`` section of the dataset's sensing recipe, ``dataset build``, ``train --init``); the report says so and
gives the commands."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..cliutil import json_safe
from ..config import Param, Section, load_toml, parse
from ..io import atomic_write_text
from ..plotting import pyplot, save_figure
from ..reconstruction.data import PSFDataset, apply_noise
from ..reconstruction.dataset_build import normalise_psf
from ..reconstruction.losses import PiB
from ..reconstruction.metrics import EVAL_NOISE_SEED, captured_fraction, npib_rows
from ..reconstruction.model import check_fits
from ..reconstruction.refine import load_network
from ..sensing.model import CAMERA_SECTION, camera_from_values
from ..sensing.mosaic import MosaicCamera, fields_key, raw_of_sites, site_fields
from ..sensing.sensor import psf_tensor
from ..turbulence.propagate import Turbulence
from ..validation import ConfigError, ValidationError
from .madewith import made_with

__all__ = [
    "POLCAM_FORMAT",
    "RETRAIN_COMMANDS",
    "SECTIONS",
    "PolcamRecipe",
    "load_polcam_recipe",
    "polcam_from_dict",
    "run_polcam",
    "write_polcam",
]

POLCAM_FORMAT = "metadesign.polcam/1"

SECTIONS = (
    Section("study", (
        Param("dataset", str), Param("model", str),
        Param("split", str, "test", choices=("train", "val", "test")),
        Param("limit", int, 160, lo=1, hi=1_000_000),
        Param("noise_percent", float, 5.0, lo=0, hi=100),
        Param("extinction_ratios", list, [0.0, 300.0, 100.0, 30.0], lo=0, hi=1e9),
        Param("pixel_pitch_um", list, [7.5, 15.0], lo=0, open_lo=True, hi=1000),
        Param("tolerance", float, 0.02, lo=0, open_lo=True, hi=1),
        Param("batch", int, 16, lo=1, hi=4096),
        Param("seed", int, 0, lo=0, hi=2**63 - 1, help="the bootstrap's"),
    )),
    replace(CAMERA_SECTION, optional=True),
)

#: how a user would retrain on a camera's frames (not run by the study: see the module's docstring)
RETRAIN_COMMANDS = (
    "metadesign dataset build sensing/dataset-polcam.toml",
    "metadesign dataset operators sensing/dataset-polcam --split train val",
    ("torchrun --nproc_per_node 2 -m metadesign train sensing/train-polcam.toml --init "
     "sensing/models/demo-unet-robust.safetensors -o sensing/train-polcam-run"),
    ("metadesign polcam sensing/polcam-demo.toml --model sensing/train-polcam-run/model.safetensors "
     "-o sensing/polcam-retrained"),
)


@dataclass(frozen=True)
class PolcamRecipe:
    dataset: Path
    model: Path
    split: str = "test"
    limit: int = 160
    noise_percent: float = 5.0
    cameras: tuple = ()  # ((label, MosaicCamera, grid point (er, pitch) or None), ...)
    tolerance: float = 0.02
    batch: int = 16
    seed: int = 0
    name: str = "polcam"
    raw: dict = field(default_factory=dict)
    source: Path | None = None  # the recipe file


def _er(v: float, where: str) -> float:
    if 0 < v <= 1:
        raise ConfigError(where, f"expected a number > 1, or 0 for ideal polarisers, got {v!r}")
    return math.inf if v == 0 else float(v)


def _camera(raw: dict, where: str) -> MosaicCamera:
    vals = parse({"camera": {**raw, "kind": "mosaic"}}, (CAMERA_SECTION,), where)["camera"]
    return camera_from_values(vals)


def label_of(cam: MosaicCamera) -> str:
    er = "inf" if math.isinf(cam.extinction_ratio) else f"{cam.extinction_ratio:g}"
    return f"ER {er}, {cam.pixel_pitch * 1e6:g} um"


def polcam_from_dict(data: dict, base: Path | None = None, source: str = "recipe") -> PolcamRecipe:
    """A study recipe from its parsed TOML (``base``: the folder its paths are relative to)."""
    data = dict(data)
    variants = data.pop("variant", [])
    if not isinstance(variants, list) or not all(isinstance(v, dict) for v in variants):
        raise ConfigError("variant", "expected [[variant]] tables")
    v = parse(data, SECTIONS, source)
    st, cam_raw = v["study"], dict(data.get("camera") or {})
    cam_raw.pop("kind", None)
    ers = [_er(x, f"study.extinction_ratios[{i}]") for i, x in enumerate(st["extinction_ratios"])]
    pitches = list((data.get("study") or {}).get("pixel_pitch_um", [7.5, 15.0]))  # um, as written (checked above)
    if not ers or not pitches:
        raise ConfigError("study.extinction_ratios", "expected at least one extinction ratio and one pixel pitch")
    cams = []
    for pitch in pitches:
        for er in ers:
            c = _camera({**cam_raw, "extinction_ratio": 0.0 if math.isinf(er) else er, "pixel_pitch_um": pitch},
                        source)
            cams.append((label_of(c), c, (er, c.pixel_pitch)))
    for i, var in enumerate(variants):
        var = dict(var)
        label = var.pop("label", None)
        if not isinstance(label, str) or not label.strip():
            raise ConfigError(f"variant[{i}].label", "expected a name for the camera")
        var.pop("kind", None)
        c = _camera({**cam_raw, **var}, f"{source} variant[{i}]")
        cams.append((label.strip(), c, None))
    labels = [c[0] for c in cams]
    dup = next((x for x in labels if labels.count(x) > 1), None)
    if dup is not None:
        raise ConfigError("variant", f"two cameras are labelled {dup!r}")
    base = Path(base) if base is not None else Path.cwd()
    return PolcamRecipe(base / st["dataset"], base / st["model"], st["split"], st["limit"], st["noise_percent"],
                        tuple(cams), st["tolerance"], st["batch"], st["seed"], raw=data | {"variant": variants})


def load_polcam_recipe(path: str | Path) -> PolcamRecipe:
    path = Path(path)
    return replace(polcam_from_dict(load_toml(path), path.parent, str(path)), name=path.stem, source=path)


def _beacon(tb0: Turbulence, ds: PSFDataset, i: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``i``'s screens and incident field on the ``n x n`` pupil grid, as the dataset build drew them
    (:meth:`metadesign.turbulence.chain.BeaconChain.sample`)."""
    tb = tb0.at_rytov(ds.exact_rytov(i), check=False)
    ph = tb.screens(int(ds.info.seed[i]))
    return ph, tb.to_metasurface(tb.element.forward(tb.source, ph), n)


def _tensor(frames: np.ndarray, sensor, noise_percent: float, i: int) -> np.ndarray:
    """The network's input of ``frames``: the PSF tensor, normalised as the datasets do, with the evaluation's
    noise draw of sample ``i`` (:class:`~metadesign.reconstruction.data.PSFDataset`'s, epoch 0)."""
    psf, _ = normalise_psf(psf_tensor(frames, sensor))
    return _noisy(psf, noise_percent, i)


def _noisy(psf: np.ndarray, noise_percent: float, i: int) -> np.ndarray:
    if not noise_percent:
        return psf
    rng = np.random.default_rng(np.random.SeedSequence(EVAL_NOISE_SEED, spawn_key=(0, i)))
    return apply_noise(psf, rng, noise_percent)


def run_polcam(rec: PolcamRecipe, progress=None, log=print) -> dict:
    """Per-sample NPiB of the model (its U-Net and, for a refiner, its refinement) for the ideal camera and every
    camera of the recipe; see the module docstring."""
    import torch

    t0 = time.perf_counter()
    model, card = load_network(rec.model)
    refines = "refine" in card
    base = PSFDataset(rec.dataset, rec.split, limit=rec.limit)
    if len(base) == 0:
        raise ValidationError(f"{rec.dataset}: the {rec.split} split is empty")
    check_fits(model, base.info, str(rec.model))
    dev = base.device()
    if base.info.attrs.get("provenance", {}).get("camera"):
        raise ValidationError(f"{rec.dataset}: a dataset rendered through a camera already; the study needs the "
                              "ideal camera's dataset")
    for _, cam, _ in rec.cameras:  # every camera's grid, before any work
        cam.frame_sensor(dev.sensor)
    c0, a = base.crop()
    pib = PiB(base.scenario(), c0, a, "cpu")
    tb0 = Turbulence(base.scenario(), check=False)
    labels = ["ideal"] + [c[0] for c in rec.cameras]
    rows = {k: [] for k in ("index", "none", "phase_conjugate")}
    est = {lab: {"unet": [], **({"refine": []} if refines else {})} for lab in labels}
    check = None
    n = len(base)
    for b0 in range(0, n, rec.batch):
        js = range(b0, min(n, b0 + rec.batch))
        idx = [int(base.idx[j]) for j in js]
        inputs = {lab: [] for lab in labels}
        screens, received = [], []
        for j, i in zip(js, idx):
            s = base.get(j)
            ph, e_in = _beacon(tb0, base, i, dev.pupil_n)
            screens.append(ph)
            received.append(s["received"])
            inputs["ideal"].append(_noisy(s["psf"], rec.noise_percent, i))  # today's frames: the dataset's tensor
            if check is None:  # the beacon is the dataset's: its ideal render is the stored tensor
                check = float(np.abs(normalise_psf(dev.psfs(e_in))[0] - s["psf"]).max() / s["psf"].max())
            fields: dict = {}
            for lab, cam, _ in rec.cameras:
                key = fields_key(cam, dev.sensor)
                if key not in fields:  # cameras that differ only in their polarisers share the fields
                    fields[key] = site_fields(dev.pupil, dev.sensor, cam, e_in)
                frames = cam.demosaic(raw_of_sites(fields[key], dev.sensor, cam), dev.sensor)
                inputs[lab].append(_tensor(frames, cam.frame_sensor(dev.sensor), rec.noise_percent, i))
        scr = torch.from_numpy(np.stack(screens))
        rec_t = torch.from_numpy(np.stack(received))
        with torch.no_grad():
            for lab in labels:
                x = torch.from_numpy(np.stack(inputs[lab]))
                if refines:
                    traj = model.trajectory(x)
                    phis = {"unet": traj[0] * model.mask, "refine": traj[-1] * model.mask}
                else:
                    phis = {"unet": model(x)}
                if lab == "ideal":
                    ref = npib_rows(pib, phis["unet"], scr, rec_t)
                    rows["none"].append(ref["none"].numpy())
                    rows["phase_conjugate"].append(ref["phase_conjugate"].numpy())
                    est[lab]["unet"].append(ref["estimate"].numpy())
                    if refines:
                        est[lab]["refine"].append(pib.npib_phase(phis["refine"], scr).numpy())
                else:
                    for k, phi in phis.items():
                        est[lab][k].append(pib.npib_phase(phi, scr).numpy())
        rows["index"].append(np.array(idx))
        if progress:
            progress(js[-1] + 1, n)
    out = {k: np.concatenate(v) for k, v in rows.items()}
    per = {lab: {k: np.concatenate(v) for k, v in d.items()} for lab, d in est.items()}
    return {"rows": out, "estimates": per, "card": card, "refines": refines, "n": n, "recipe": rec,
            "sensor": dev.sensor, "ideal_render_check": check, "seconds": time.perf_counter() - t0}


def _um(x: float) -> float:
    """Metres -> micrometres, rounded to the picometre (no 14.999999999999998 in the report)."""
    return round(x * 1e6, 6)


def _ci(none, est, ref, pc, n_boot: int, seed: int) -> list[float]:
    """95 % paired bootstrap interval of ``cf(est) - cf(ref)`` (the same resampled samples for both)."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(none), size=(n_boot, len(none)))
    mn, mp = none[idx].mean(1), pc[idx].mean(1)
    d = (est[idx].mean(1) - ref[idx].mean(1)) / np.maximum(mp - mn, 1e-12)
    return [float(np.quantile(d, 0.025)), float(np.quantile(d, 0.975))]


def summarise(res: dict, n_boot: int = 2000) -> dict:
    """Per camera and network: mean NPiB, captured fraction, its difference from the ideal camera's (with a paired
    bootstrap interval); the verdict (:func:`verdict`)."""
    rec: PolcamRecipe = res["recipe"]
    none, pc = res["rows"]["none"], res["rows"]["phase_conjugate"]
    ideal = res["estimates"]["ideal"]
    nets = list(ideal)
    sensor = res["sensor"]
    cams = {"ideal": {"label": "ideal camera (two ideal frames, today)", "camera": None,
                      "frame_pitch_um": _um(sensor.pixel_pitch), "grid": None}}
    for lab, cam, grid in rec.cameras:
        fs = cam.frame_sensor(sensor)
        cams[lab] = {"label": lab, "camera": cam.to_dict(), "frame_pitch_um": _um(fs.pixel_pitch),
                     "frame_px": [fs.width_px, fs.height_px],
                     "grid": None if grid is None else {"extinction_ratio": None if math.isinf(grid[0]) else grid[0],
                                                         "pixel_pitch_um": _um(grid[1])}}
    for lab, d in res["estimates"].items():
        for k in nets:
            e = d[k]
            cf = captured_fraction(none, e, pc)
            cams[lab][k] = {"npib": float(np.mean(e)), "captured_fraction": cf,
                            "delta_vs_ideal": cf - captured_fraction(none, ideal[k], pc),
                            "delta_ci95": _ci(none, e, ideal[k], pc, n_boot, rec.seed) if lab != "ideal" else [0.0, 0.0]}
    return {"format": POLCAM_FORMAT, "name": rec.name, "split": rec.split, "n": res["n"],
            "noise_percent": rec.noise_percent, "tolerance": rec.tolerance, "networks": nets,
            "npib": {"none": float(np.mean(none)), "phase_conjugate": float(np.mean(pc))},
            "cameras": cams, "ideal_render_check": res["ideal_render_check"],
            "verdict": verdict(cams, nets, rec.tolerance), "seconds": res["seconds"],
            "made_with": made_with(rec.model, rec.dataset, recipe=rec.source),
            "retraining": _retraining(res["card"], rec)}


def _retraining(card: dict, rec) -> dict:
    """Whether the model was trained on another dataset's frames than the study's (a camera's: retrained)."""
    trained = ((card.get("unet") or {}).get("dataset") if "refine" in card else None) or card.get("dataset") or {}
    on = trained.get("path")
    if on and Path(on).name != Path(rec.dataset).name:
        return {"run": True, "trained_on": on, "model": str(rec.model),
                "why": f"the model was trained on {Path(on).name}'s frames, not on the study's dataset's"}
    return {"run": False, "why": "this model was trained on the study's dataset's ideal frames; the retrained "
            "model's rows: sensing/polcam-retrained (the commands)", "commands": list(RETRAIN_COMMANDS)}


def verdict(cams: dict, nets: list, tol: float) -> dict:
    """Which camera to buy: the coarsest mosaic pitch whose ideal polarisers keep every network's captured fraction
    within ``tol`` of the ideal camera's, and the lowest extinction ratio at that pitch that does (every higher
    ratio of the grid doing so too)."""
    def ok(c):
        return all(c[k]["delta_vs_ideal"] >= -tol for k in nets)

    grid = {}
    for c in cams.values():
        if c.get("grid"):
            er = c["grid"]["extinction_ratio"]
            grid.setdefault(c["grid"]["pixel_pitch_um"], []).append((math.inf if er is None else er, c))
    out = {"tolerance": tol, "by_pitch": {}}
    best = None
    for pitch in sorted(grid, reverse=True):  # the coarsest first
        col = sorted(grid[pitch], key=lambda t: -t[0])  # the highest extinction ratio first
        need = None
        for er, c in col:
            if not ok(c):
                break
            need = er
        frame = col[0][1]["frame_pitch_um"]
        out["by_pitch"][f"{pitch:g}"] = {"frame_pitch_um": frame,
                                         "extinction_ratio_needed": None if need is None else
                                         ("inf" if math.isinf(need) else need),
                                         "within_tolerance": [lab["label"] for _, lab in col if ok(lab)]}
        if need is not None and best is None:
            best = (pitch, need, frame)
    if best is None:
        out["buy"] = None
        out["text"] = (f"no mosaic camera of the grid keeps the captured fraction within {tol:g} of the ideal camera; "
                       "a finer mosaic, or retraining on the camera's frames, is needed")
    else:
        pitch, need, frame = best
        out["buy"] = {"pixel_pitch_um": pitch, "frame_pitch_um": frame,
                      "extinction_ratio": "inf" if math.isinf(need) else need}
        er = "ideal polarisers (the grid's highest ratio)" if math.isinf(need) else f"an extinction ratio of {need:g}:1 or better"
        out["text"] = (f"a mosaic of {pitch:g} um pixels behind the sensor's relay (x and y frames at {frame:g} um) with "
                       f"{er} keeps the captured fraction within {tol:g} of the ideal camera")
    return out


def plot_polcam(summ: dict, path: Path) -> Path:
    """Captured fraction vs extinction ratio, one line per mosaic pitch, one panel per network, the ideal camera's
    band and the variants."""
    plt = pyplot()
    nets = summ["networks"]
    names = {"unet": "U-Net (robust)", "refine": "U-Net + refinement"}
    fig, axs = plt.subplots(1, len(nets), figsize=(5.6 * len(nets), 4.2), constrained_layout=True, squeeze=False)
    cams = summ["cameras"]
    grid = {}
    for c in cams.values():
        if c.get("grid"):
            er = c["grid"]["extinction_ratio"]
            grid.setdefault(c["grid"]["pixel_pitch_um"], []).append((er, c))
    finite = [er for col in grid.values() for er, _ in col if er is not None]
    x_inf = 10 ** (np.log10(max(finite or [100])) + 0.6)
    for ax, k in zip(axs[0], nets):
        ideal = cams["ideal"][k]["captured_fraction"]
        ax.axhspan(ideal - summ["tolerance"], ideal, color="0.85", label=f"ideal camera - {summ['tolerance']:g}")
        ax.axhline(ideal, color="k", lw=1, label=f"ideal camera ({ideal:.3f})")
        for pitch, col in sorted(grid.items()):
            col = sorted(col, key=lambda t: math.inf if t[0] is None else t[0])
            xs = [x_inf if er is None else er for er, _ in col]
            ax.plot(xs, [c[k]["captured_fraction"] for _, c in col], "o-",
                    label=f"mosaic {pitch:g} um (frames {col[0][1]['frame_pitch_um']:g} um)")
        for c in cams.values():
            if c.get("camera") and not c.get("grid"):
                er = c["camera"]["extinction_ratio"]
                ax.plot(x_inf if er is None else er, c[k]["captured_fraction"], "D", ms=6, label=c["label"])
        ticks = sorted(set(finite))
        ax.set_xscale("log")
        ax.set_xticks(ticks + [x_inf], [f"{t:g}" for t in ticks] + ["inf"])
        ax.minorticks_off()
        ax.set(xlabel="extinction ratio of the micro-polarisers", ylabel="captured fraction",
               title=f"{names.get(k, k)}: {summ['n']} {summ['split']} samples, {summ['noise_percent']:g} % noise")
        ax.legend(fontsize=7, loc="lower right")
    rt = summ.get("retraining") or {}
    fig.suptitle("Polarisation camera (2 x 2 micro-polariser mosaic) instead of two ideal frames, " +
                 (f"the model retrained on {Path(rt['trained_on']).name}" if rt.get("run") else "no retraining"),
                 fontsize=10)
    return save_figure(fig, path)


def write_polcam(summ: dict, out: Path) -> list[Path]:
    """``OUT/polcam.json`` and ``OUT/polcam.png``."""
    out = Path(out)
    j = out / "polcam.json"
    atomic_write_text(j, json.dumps(json_safe(summ), indent=1, allow_nan=False) + "\n")
    return [j, plot_polcam(summ, out / "polcam.png")]

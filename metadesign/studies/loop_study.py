"""The loop study (``metadesign loop RECIPE``): every method of a loop recipe on the same moving turbulence,
their power-in-bucket time series, fades and spectra, against the references, into one report.

The device as made (the recipe's design, its sensor, the turbulence scenario at the loop's Rytov number) is
built once; the frozen-flow screens are drawn once from the recipe's seed and shared by every method (same
seed, same turbulence).  A method's delay is the loop's (:class:`~metadesign.studies.loop.LoopTiming`) with
its reconstruction's latency: declared in the recipe (``latency_ms``), else measured on this machine (the
median of single-frame estimates, batch 1)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..design.recipe import load_design_recipe
from ..design.store import run_design
from ..io import atomic_write_text
from ..optics.control import Controller, rejection_tf
from ..optics.dm import DeformableMirror, ModalDM
from ..plotting import pyplot, save_figure
from ..reconstruction.dataset import received_crop
from ..reconstruction.estimators import make_estimator
from ..reconstruction.losses import PiB
from ..reconstruction.refine import load_network
from ..reconstruction.shack_hartmann import SHConfig
from ..sensing.detector import Detector
from ..sensing.device import Device, ReceiverCrop
from ..sensing.model import AsFabricated
from ..turbulence.frozen import FrozenFlow
from ..turbulence.system import build_system
from ..turbulence.scenario import wind_from_dict
from ..turbulence.temporal import temporal_summary
from .loop import ORACLES, IdealPhaseSensor, LoopTiming, LoopWorld, MetasurfaceSensor, run_loop
from .loop_recipe import LoopRecipe
from .loop_stats import cdf_points, fade_statistics, rejection_measured, welch_psd

__all__ = ["run_loop_study", "LABELS", "ShackHartmannLoopSensor"]

LABELS = {"unet": "metasurface + U-Net", "refine": "metasurface + learned refinement",
          "shack_hartmann": "Shack-Hartmann", "ideal": "ideal phase sensor", "fitted": "DM-fitted oracle (no delay)",
          "conjugate": "phase conjugate", "open": "open loop"}
#: Zernike modes of the modal spectra (Noll 2..)
MODES = 10


class ShackHartmannLoopSensor:
    """A Shack-Hartmann in the received plane in the loop: its spots integrated over the exposure, read by its
    detector (Gaussian noise of the frame's peak, drawn from ``seed`` and the frame), reconstructed by its
    estimator."""

    def __init__(self, estimator, noise_percent: float, seed: int):
        self.est, self.noise, self.seed = estimator, float(noise_percent), int(seed)

    def expose(self, crops: list, k: int) -> dict:
        sh = self.est.sh
        spots = np.mean([sh.frames(np.asarray(c)[None]) for c in crops], axis=0)
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(12, int(k))))
        return {"sh_spots": sh.add_noise(spots, self.noise, rng), "index": np.array([k])}

    def reconstruct(self, frame: dict) -> np.ndarray:
        return np.asarray(self.est.estimate(frame), np.float64)[0]

    def measure(self, crops: list, k: int) -> np.ndarray:
        return self.reconstruct(self.expose(crops, k))


def _system(rec: LoopRecipe, work: Path, tensor_size: int | None):
    d, _ = run_design(load_design_recipe(rec.design), work / "design")
    system = build_system(AsFabricated.from_design(d), rec.sensor, rec.turbulence, tensor_size=tensor_size)
    return system.chain()


def _latency(sensor, world: LoopWorld, repeats: int = 15) -> float:
    """Median seconds of one frame's reconstruction on this machine (batch 1, from the recorded frame to the
    phase estimate: the exposure is the camera's, not the reconstruction's)."""
    frame = sensor.expose([world.received(world.screens_at(0))], 0)
    sensor.reconstruct(frame)  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sensor.reconstruct(frame)
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def _sensors(rec: LoopRecipe, device: Device, world: LoopWorld) -> dict:
    """Each closed-loop method's sensor (its reconstruction included) and its latency (s)."""
    lp = rec.loop
    net = unet = refiner = None
    if rec.model is not None:
        net, _ = load_network(rec.model)
        refiner = net if hasattr(net, "trajectory") else None
        unet = refiner.unet if refiner is not None else net
    det = Detector.gaussian(lp.noise_percent, lp.seed) if lp.noise_percent else None
    out = {}
    for m in lp.methods:
        if m in ORACLES:
            continue
        if m == "ideal":
            s = IdealPhaseSensor()
        elif m == "shack_hartmann":
            est = make_estimator("shack_hartmann", device)
            est = type(est)(device, SHConfig(lenslets=est.config.lenslets, threshold=0.3,
                                             noise_percent=lp.noise_percent))
            s = ShackHartmannLoopSensor(est, lp.noise_percent, lp.seed)
        elif m == "refine" and refiner is None:
            raise ValueError("loop.methods: refine needs a refiner as the model")
        else:
            est = make_estimator(m, device, model=unet, refiner=refiner)
            s = MetasurfaceSensor(device, est, det, lp.seed)
        lat = lp.latency_ms.get(m) if m in lp.latency_ms else (0.0 if m == "ideal" else _latency(s, world))
        out[m] = (s, float(lat))
    return out


def _plot(rep: dict, series: dict, out: Path) -> list[Path]:
    plt = pyplot()
    lp = rep["loop"]
    fig, axs = plt.subplots(1, 3, figsize=(16, 4.2), constrained_layout=True)
    t = np.arange(lp["steps"]) / lp["rate_hz"] * 1e3
    for m, s in series.items():
        axs[0].plot(t, s["npib"], lw=0.8, label=LABELS[m])
        v, p = cdf_points(s["npib"])
        axs[1].semilogy(v, p, lw=1, label=LABELS[m])
    axs[0].set(xlabel="time (ms)", ylabel="NPiB", title=f"{lp['rate_hz']:g} Hz loop, f_G {rep['turbulence']['greenwood_hz']:.0f} Hz")
    axs[1].set(xlabel="NPiB", ylabel="P(NPiB <= x)", title="CDF of the power in the bucket")
    for m, r in rep["methods"].items():
        if "rejection" in r:
            f, db = np.array(r["rejection"]["f_hz"]), np.array(r["rejection"]["measured_db"])
            line, = axs[2].semilogx(f[1:], db[1:], lw=1, label=f"{LABELS[m]} (measured)")
            axs[2].semilogx(f[1:], np.array(r["rejection"]["theory_db"])[1:], "--", lw=0.8, color=line.get_color())
    axs[2].set(xlabel="f (Hz)", ylabel="|RTF|^2 (dB)", title="rejection: measured (solid), theory (dashed)")
    for a in axs:
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    return [save_figure(fig, out / "loop.png")]


def _method_report(m: str, s: dict, lat: float, timing: LoopTiming, rec: LoopRecipe, open_modal) -> dict:
    lp = rec.loop
    r = {"label": LABELS[m], "latency_ms": lat * 1e3, "delay_frames": timing.delay_frames if m not in ORACLES else 0.0,
         "npib_mean": float(np.mean(s["npib"])), "npib_p01": float(np.percentile(s["npib"], 1)),
         "residual_rms_rad": float(np.mean(s["residual_rms"])),
         "branch_points_mean": float(np.mean(s["branch_points"])),
         "fades": fade_statistics(s["npib"], timing.dt, lp.threshold_db)}
    if m not in ORACLES and open_modal is not None and len(s["npib"]) >= 64:
        f, rtf = rejection_measured(s["modal"], open_modal, lp.rate_hz, segment=min(256, len(s["npib"]) // 2))
        theory = np.abs(rejection_tf(f, lp.rate_hz, lp.gain, timing.delay_frames, lp.leak)) ** 2
        r["rejection"] = {"f_hz": f.tolist(), "measured_db": (10 * np.log10(np.maximum(rtf, 1e-30))).tolist(),
                          "theory_db": (10 * np.log10(np.maximum(theory, 1e-30))).tolist()}
    if len(s["npib"]) >= 64:
        f, P = welch_psd(s["modal"], lp.rate_hz, segment=min(256, len(s["npib"]) // 2))
        r["modal_psd"] = {"f_hz": f.tolist(), "noll": list(range(2, 2 + P.shape[1])), "psd_rad2_hz": P.T.tolist()}
    return r


def run_loop_study(rec: LoopRecipe, out: Path, log=print, progress=None) -> dict:
    """Every method of ``rec`` on the same turbulence, into ``out`` (``loop.json``, ``loop.png``, the
    designed device in ``out/design``)."""
    t_start = time.perf_counter()
    lp = rec.loop
    tensor = None
    if rec.model is not None:
        net, _ = load_network(rec.model)
        tensor = (net.unet if hasattr(net, "trajectory") else net).config.input_size
    chain = _system(rec, out, tensor)
    tb = chain.at(lp.rytov)
    sc = tb.sc
    wind = wind_from_dict({"wind": rec.wind}, sc, str(rec.source))
    c0, a = received_crop(sc)
    flow = FrozenFlow(tb.grid, tb.path.r0_screens, wind, 1.0 / (lp.rate_hz * lp.substeps), lp.steps * lp.substeps,
                      lp.seed)
    world = LoopWorld(tb, flow.screens, c0, a, PiB(sc, c0, a))
    device = Device(chain.pupil, chain.sensing.sensor, ReceiverCrop.of_scenario(sc, c0, a))
    temporal = temporal_summary(sc, wind)
    log(f"loop: {rec.name}: Rytov {lp.rytov:g}, f_G {temporal['greenwood_hz']:.0f} Hz, {lp.rate_hz:g} Hz, {lp.steps} steps "
        f"x {lp.substeps} sub-steps; methods {', '.join(lp.methods)}")
    dm = DeformableMirror.for_crop(device.crop, n_act=rec.dm.actuators, coupling=rec.dm.coupling,
                                   regularisation=rec.dm.regularisation)
    sensors = _sensors(rec, device, world)
    modes = np.asarray(ModalDM.for_crop(device.crop, n_modes=MODES).influence, np.float64)  # unit-rms Zernikes
    series, reports = {}, {}
    order = ["open"] + [m for m in lp.methods if m != "open"]
    for m in order:
        if m not in lp.methods and m != "open":
            continue
        sensor, lat = sensors.get(m, (None, 0.0))
        timing = LoopTiming(lp.rate_hz, lp.substeps, lp.readout_frames, lat, lp.dm_frames)
        ctl = Controller(lp.gain, timing.delay_frames, lp.leak) if m not in ORACLES else None
        t0 = time.perf_counter()
        s = run_loop(world, timing, lp.steps, m, sensor, dm, ctl, modes, progress)
        series[m] = s
        reports[m] = _method_report(m, s, lat, timing, rec, series["open"]["modal"] if m != "open" else None)
        reports[m]["seconds"] = time.perf_counter() - t0
        log(f"  {LABELS[m]:<34} NPiB {reports[m]['npib_mean']:.3f}, P(fade {lp.threshold_db:g} dB) "
            f"{reports[m]['fades']['probability']:.3g}, delay {reports[m]['delay_frames']:.2f} frames "
            f"({reports[m]['seconds']:.0f} s)")
    rep = {"format": "metadesign.loop/1", "recipe": str(rec.source), "loop": {**lp.__dict__, "methods": list(lp.methods)},
           "dm": rec.dm.__dict__, "turbulence": {**temporal, "rytov": lp.rytov, "wind": rec.wind},
           "methods": {m: reports[m] for m in lp.methods if m in reports} | ({"open": reports["open"]}),
           "seconds": time.perf_counter() - t_start}
    rep["verdict"] = _verdict(rep)
    rep["figures"] = [str(p) for p in _plot(rep, {m: series[m] for m in rep["methods"]}, out)]
    atomic_write_text(out / "loop.json", json.dumps(rep, indent=1, default=float))
    return rep


def _verdict(rep: dict) -> dict:
    """The headline: the metasurface loops' mean NPiB against the ideal-phase loop's and the Shack-Hartmann
    loop's (the issue's goals: >= 0.8 of the ideal, >= 2x the Shack-Hartmann)."""
    ms = rep["methods"]
    best = max((m for m in ("refine", "unet") if m in ms), key=lambda m: ms[m]["npib_mean"], default=None)
    out = {"best_metasurface": best}
    if best is None:
        return out
    v = ms[best]["npib_mean"]
    if "ideal" in ms:
        out["vs_ideal"] = v / ms["ideal"]["npib_mean"] if ms["ideal"]["npib_mean"] > 0 else None
    if "shack_hartmann" in ms:
        out["vs_shack_hartmann"] = v / ms["shack_hartmann"]["npib_mean"] if ms["shack_hartmann"]["npib_mean"] > 0 else None
    return out

"""The loop study (``metadesign loop RECIPE``): every method of a loop recipe on the same moving turbulence,
their power-in-bucket time series, fades and spectra, against the references, into one report.

The device as made (the recipe's design, its sensor, the turbulence scenario at the loop's Rytov number) is
built once.  The recipe's ``seeds`` turbulence realisations are frozen flows drawn from the recipe's seed
(:func:`~metadesign.studies.loop.flow_seed`: the first is the seed itself, the others SeedSequence spawn keys
of it), and every method runs on each of them (same seed, same turbulence).  Each run (one realisation x one
method) is a task (:meth:`metadesign.execution.Execution.run`): on ``-j`` local processes or a Dask
scheduler, its series kept as ``OUT.partial/NAME.npz`` as it finishes, so a killed study resumes where it
stopped, and the report, computed from the tasks' series in a fixed order, has the same bytes on any
worker count.  The report pools the series over the realisations.

A method's delay is the loop's (:class:`~metadesign.studies.loop.LoopTiming`) with its reconstruction's
latency: declared in the recipe (``latency_ms``), else measured on this machine (the median of single-frame
estimates, batch 1; a warm-started method's warm-started frame), once per study (kept in the resume folder:
a resumed study keeps the delays it began with).  The ``retrieval`` method's iteration count is chosen for
its latency budget just before (:meth:`~metadesign.studies.loop.RetrievalLoopSensor.calibrate`, kept
there too).

``gain = "optimise"``: each closed loop's gain is chosen before the runs by a grid search of the mean NPiB
over ``gain_steps`` frames of the first realisation (:data:`GAIN_GRID`, then :data:`GAIN_REFINE` around the
grid's best: the best of all the trials wins, the lowest gain on a tie), the trials tasks like the runs."""

from __future__ import annotations

import copy
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..design.recipe import load_design_recipe
from ..design.store import run_design
from ..execution import SERIAL, Execution, scratch_path
from ..io import atomic_write_text
from ..optics.control import Controller
from ..optics.dm import DeformableMirror, ModalDM, TipTiltSplit
from ..reconstruction.dataset import received_crop
from ..reconstruction.estimators import ShackHartmannEstimator, make_estimator
from ..reconstruction.linear import LinearEstimator, LinearReconstructor, TipTiltSplitEstimator
from ..reconstruction.peak_tilt import PeakTipTilt
from ..reconstruction.realtime import RealtimeEstimator
from ..reconstruction.losses import PiB
from ..reconstruction.refine import load_network
from ..reconstruction.retrieval import RetrievalConfig
from ..reconstruction.shack_hartmann import SHConfig
from ..sensing.detector import Detector, NoiseSpec
from ..sensing.device import Device, ReceiverCrop
from ..sensing.model import AsFabricated
from ..turbulence.frozen import FrozenFlow
from ..turbulence.path import solve_path
from ..turbulence.system import build_system
from ..turbulence.scenario import wind_from_dict
from ..turbulence.temporal import temporal_summary
from ..tasks import TaskFolder, content_key, file_key
from ..validation import ConfigError
from .loop import (ORACLES, IdealPhaseSensor, LoopTiming, LoopWorld, MetasurfaceSensor, RefineWarmSensor,
                   RetrievalLoopSensor, flow_seed, noise_stream, run_loop)
from .loop_recipe import AUTO, REALTIME, SH_LENSLETS_RANGE, LoopRecipe, load_influence
from .loop_report import LABELS, loop_provenance, loop_report, plot_loop
from .loop_report import pooled_fades as _pooled_fades  # noqa: F401  (the loop map's name for it)

__all__ = ["run_loop_study", "LABELS", "ShackHartmannLoopSensor", "LoopContext", "GAIN_GRID", "GAIN_REFINE",
           "gain_search", "sh_lenslets_for", "SH_MIN_SAMPLES", "loop_detector", "loop_mirror", "calibrate_retrieval",
           "build_loop", "linear_estimator"]

#: Zernike modes of the modal spectra (Noll 2..)
MODES = 10
#: ``gain = "optimise"``: the gains tried first, then the refinement's offsets around the best of them
GAIN_GRID = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
GAIN_REFINE = (-0.075, -0.05, -0.025, 0.025, 0.05, 0.075)


class ShackHartmannLoopSensor:
    """A Shack-Hartmann in the received plane in the loop: its spots integrated over the exposure, read as one
    frame (all the spots) by ``detector`` (a :class:`~metadesign.sensing.detector.Detector`, the metasurface
    sensor's model: its noise in units of the frame's peak; None: noise-free), drawn from ``seed``, the
    ``stream`` and the frame, reconstructed by its estimator."""

    def __init__(self, estimator, detector: Detector | None, seed: int, stream: tuple = ()):
        self.est, self.detector, self.seed = estimator, detector, int(seed)
        self.stream = tuple(stream)

    def expose(self, crops: list, k: int) -> dict:
        sh = self.est.sh
        spots = np.mean([sh.frames(np.asarray(c)[None]) for c in crops], axis=0)  # (1, L, L, K, K)
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(*self.stream, 12, int(k))))
        if self.detector is not None:
            B, L, _, K, _ = spots.shape
            frame = spots.transpose(0, 1, 3, 2, 4).reshape(B, L * K, L * K)  # the detector's frame
            spots = self.detector.read(frame, rng).reshape(B, L, K, L, K).transpose(0, 1, 3, 2, 4)
        return {"sh_spots": spots, "index": np.array([k])}

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
    run = getattr(sensor, "steady_state", sensor.reconstruct)  # a warm-started sensor: a warm-started frame
    run(frame)  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run(frame)
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def loop_detector(rec: LoopRecipe) -> Detector | None:
    """The loop's detector (None: noise-free): ``noise_percent`` % of each frame's peak of additive Gaussian
    noise, and with ``photons_per_frame`` > 0 shot noise with that many photo-electrons at each frame's peak
    plus ``read_noise_e`` electrons rms of read noise (the sensing stage's detector, as the datasets draw it)."""
    lp = rec.loop
    spec = NoiseSpec(gaussian_sigma=lp.noise_percent / 100.0, photons_at_peak=lp.photons_per_frame or None,
                     read_noise_e=lp.read_noise_e if lp.photons_per_frame else 0.0, seed=lp.seed)
    return Detector(spec) if spec.active else None


#: ``sh_lenslets = "auto"``: the fewest received-field samples across one lenslet
SH_MIN_SAMPLES = 4


def sh_lenslets_for(sc, requested="auto") -> dict:
    """The loop's Shack-Hartmann lenslet count on the path ``sc`` (a :class:`~metadesign.turbulence.path.Scenario`
    at the loop's Rytov number) and why: ``requested`` (an int, the recipe's) or ``"auto"``, the fewest lenslets
    whose sub-apertures are no larger than the path's Fried parameter, ``ceil(D / r0)`` (the spherical-wave r0
    of the path at its Rytov number and wavelength, :func:`~metadesign.turbulence.path.solve_path`), clipped
    to [2, floor(D / (SH_MIN_SAMPLES dx))] (see :mod:`metadesign.studies.loop_recipe` for why).
    ``{"lenslets", "rule", "r0_m", "d_over_r0", "max_lenslets", "why"}``."""
    D, dx, r0 = float(sc.receiver_aperture), float(sc.dx), float(solve_path(sc).r0)
    lo, hi = SH_LENSLETS_RANGE
    top = int(max(lo, min(hi, np.floor(D / (SH_MIN_SAMPLES * dx) + 1e-9))))
    if requested == AUTO:
        want = int(np.ceil(D / r0 - 1e-9))
        n = int(min(max(want, lo), top))
        why = (f"ceil(D / r0) = ceil({D / r0:.2f}) = {want} lenslets across (sub-apertures no larger than the "
               f"spherical-wave r0 = {r0 * 100:.2f} cm of the path at Rytov {sc.rytov:g}, "
               f"{sc.wavelength * 1e9:g} nm)" + (f", clipped to [{lo}, {top}] ({SH_MIN_SAMPLES} received-field "
                                                  f"samples of {dx * 1e3:g} mm per lenslet at least)"
                                                  if n != want else ""))
    else:
        n = int(requested)
        why = f"the recipe's sh_lenslets = {n}"
    return {"lenslets": n, "rule": "auto" if requested == AUTO else "recipe", "r0_m": r0,
            "d_over_r0": D / n / r0, "max_lenslets": top, "why": why}


def loop_mirror(rec: LoopRecipe, crop: ReceiverCrop, wavelength: float):
    """The recipe's mirror on the received crop: Gaussian (``actuators``, ``coupling``) or measured
    (``influence``) zonal, or modal (``modes``); its commands clipped at ``+- 4 pi stroke / wavelength`` rad (a
    reflective surface's stroke in phase at the beacon's ``wavelength``); a separate tip/tilt mirror ahead of
    it with ``tip_tilt`` (:class:`~metadesign.optics.dm.TipTiltSplit`)."""
    d = rec.dm
    stroke = np.inf if d.stroke_m is None else 4 * np.pi * d.stroke_m / wavelength
    if rec.influence is not None:
        x, D = np.asarray(crop.coords(), float), float(crop.aperture)
        dm = DeformableMirror.measured(x, D, load_influence(rec.influence, crop.size), stroke=stroke,
                                       regularisation=d.regularisation)
    elif d.kind == "modal":
        dm = ModalDM.for_crop(crop, n_modes=d.modes, stroke=stroke, regularisation=d.regularisation)
    else:
        dm = DeformableMirror.for_crop(crop, n_act=d.actuators, coupling=d.coupling, stroke=stroke,
                                       regularisation=d.regularisation)
    return TipTiltSplit(dm) if d.tip_tilt else dm


def _sensors(rec: LoopRecipe, device: Device, lenslets: int = 8) -> dict:
    """Each closed-loop method's sensor (its reconstruction included; the Shack-Hartmann's ``lenslets``
    across)."""
    lp = rec.loop
    net = unet = refiner = None
    if rec.model is not None:
        net, _ = load_network(rec.model)
        refiner = net if hasattr(net, "trajectory") else None
        unet = refiner.unet if refiner is not None else net
    det = loop_detector(rec)
    out = {}
    for m in lp.methods:
        if m in ORACLES:
            continue
        if m == "ideal":
            s = IdealPhaseSensor()
        elif m == "shack_hartmann":
            # the centroid threshold's background noise: the Gaussian part and the read noise (% of the peak)
            bg = float(np.hypot(lp.noise_percent, 100 * lp.read_noise_e / lp.photons_per_frame)
                       if lp.photons_per_frame else lp.noise_percent)
            est = ShackHartmannEstimator(device, SHConfig(lenslets=lenslets, threshold=0.3, noise_percent=min(bg, 100)))
            s = ShackHartmannLoopSensor(est, det, lp.seed)
        elif m == "linear":
            s = MetasurfaceSensor(device, linear_estimator(rec, device), det, lp.seed)
        elif m in REALTIME:
            rt, _ = load_network(rec.realtime)
            if not hasattr(rt, "commands"):
                raise ConfigError("device.realtime", f"{rec.realtime} is not a modal network (model.kind = \"modal\")")
            est = RealtimeEstimator(rt)
            if m == "realtime_tt":  # its tip and tilt from the push-pull reconstructor of Noll 2, 3
                est = TipTiltSplitEstimator(est, linear_estimator(rec, device, modes=2).reconstructor)
            elif m == "realtime_peak":  # its tip and tilt from the in-focus channel's far-field peak
                est = TipTiltSplitEstimator(est, PeakTipTilt.build(device, ModalDM.for_crop(device.crop,
                                                                                            n_modes=2).influence))
            s = MetasurfaceSensor(device, est, det, lp.seed)
        elif m == "refine" and refiner is None:
            raise ValueError("loop.methods: refine needs a refiner as the model")
        elif m == "refine_warm":
            s = RefineWarmSensor(device, refiner, det, lp.seed)
        elif m == "retrieval":
            cfg = RetrievalConfig(misfit="gaussian", noise_percent=lp.noise_percent, modal_iterations=0,
                                  zonal_iterations=1)
            s = RetrievalLoopSensor(device, cfg, det, lp.seed)  # its iterations: calibrate_retrieval
        else:
            est = make_estimator(m, device, model=unet, refiner=refiner)
            s = MetasurfaceSensor(device, est, det, lp.seed)
        out[m] = s
    return out


def linear_estimator(rec: LoopRecipe, device: Device, modes: int | None = None):
    """The push-pull linear reconstructor (:mod:`metadesign.reconstruction.linear`) of the first ``modes``
    (default ``[dm] modes``) unit-rms Zernikes (Noll 2..) on the crop, PSFs binned 8 x 8 (or the largest
    divisor of the tensor's side below 8), as the loop's estimator."""
    s = device.sensor.tensor_size
    b = max(d for d in range(1, 9) if s % d == 0)
    basis = ModalDM.for_crop(device.crop, n_modes=modes or rec.dm.modes).influence
    return LinearEstimator(LinearReconstructor.build(device, basis, bin=b))


@dataclass
class LoopContext:
    """What every task of a loop study shares, built once and sent to each worker once: the recipe, the
    turbulence at the loop's Rytov number and its wind, the received crop and its bucket, the mirror, the
    modal basis, the closed loops' sensors and each method's latency (s).  :meth:`world` draws a
    realisation's frozen flow (the last one kept in the process: a worker runs a realisation's methods
    without drawing it again)."""

    rec: LoopRecipe
    tb: Any
    wind: Any
    c0: int
    a: int
    pib: Any
    dm: Any
    modes: np.ndarray
    sensors: dict
    latency: dict = field(default_factory=dict)
    sh: dict = field(default_factory=dict)  # the Shack-Hartmann's lenslet count and why (sh_lenslets_for)
    retrieval: dict = field(default_factory=dict)  # the retrieval's budget, costs and iterations (calibrate)
    _cache: dict = field(default_factory=dict, repr=False)

    def __getstate__(self):
        return {**self.__dict__, "_cache": {}}  # the drawn flow stays where it was drawn

    def world(self, r: int) -> LoopWorld:
        """Realisation ``r``'s world (the frozen flow of :func:`~metadesign.studies.loop.flow_seed`)."""
        if r not in self._cache:
            lp = self.rec.loop
            self._cache.clear()
            flow = FrozenFlow(self.tb.grid, self.tb.path.r0_screens, self.wind, 1.0 / (lp.rate_hz * lp.substeps),
                              lp.steps * lp.substeps, flow_seed(lp.seed, r))
            self._cache[r] = LoopWorld(self.tb, flow.screens, self.c0, self.a, self.pib)
        return self._cache[r]

    def timing(self, m: str) -> LoopTiming:
        lp = self.rec.loop
        return LoopTiming(lp.rate_hz, lp.substeps, lp.readout_frames, self.latency.get(m, 0.0), lp.dm_frames)

    def sensor(self, m: str, r: int):
        """Method ``m``'s sensor on realisation ``r`` (its detector noise drawn from that realisation's stream)."""
        s = self.sensors.get(m)
        if s is None or not hasattr(s, "stream"):
            return s
        s = copy.copy(s)
        s.stream = noise_stream(r)
        return s

    def run(self, m: str, r: int, gain: float, steps: int, modal: bool = True) -> dict:
        """``steps`` frames of method ``m`` at ``gain`` on realisation ``r``: its series (arrays) and ``seconds``."""
        lp = self.rec.loop
        timing = self.timing(m)
        ctl = Controller(gain, timing.delay_frames, lp.leak) if m not in ORACLES else None
        t0 = time.perf_counter()
        s = run_loop(self.world(r), timing, steps, m, self.sensor(m, r), self.dm, ctl,
                     self.modes if modal else None, pseudo_open_loop=lp.pseudo_open_loop)
        return {**s, "seconds": np.array(time.perf_counter() - t0)}


def _task(ctx: LoopContext, task: tuple) -> tuple[str, dict]:
    """One task of a loop study: ``(name, method, realisation, gain, steps, modal)`` -> ``(name, series)``."""
    name, m, r, gain, steps, modal = task
    return name, ctx.run(m, r, gain, steps, modal)


def build_loop(rec: LoopRecipe, out: Path, log) -> tuple[LoopContext, Device, dict]:
    """The device as made, the mirror, the sensors: the study's :class:`LoopContext` (latencies not yet
    measured), its device and the turbulence's temporal summary."""
    lp = rec.loop
    sizes = {}
    for key, path in (("device.model", rec.model), ("device.realtime", rec.realtime)):
        if path is not None:
            net, _ = load_network(path)
            sizes[key] = (net.unet if hasattr(net, "trajectory") else net).config.input_size
    if len(set(sizes.values())) > 1:
        raise ConfigError("device.realtime", f"its input ({sizes['device.realtime']}^2) differs from device.model's "
                          f"({sizes['device.model']}^2); the loop renders one tensor size")
    tensor = next(iter(sizes.values()), None)
    chain = _system(rec, out, tensor)
    tb = chain.at(lp.rytov)
    sc = tb.sc
    wind = wind_from_dict({"wind": rec.wind}, sc, str(rec.source))
    c0, a = received_crop(sc)
    device = Device(chain.pupil, chain.sensing.sensor, ReceiverCrop.of_scenario(sc, c0, a))
    temporal = temporal_summary(sc, wind)
    log(f"loop: {rec.name}: Rytov {lp.rytov:g}, f_G {temporal['greenwood_hz']:.0f} Hz, {lp.rate_hz:g} Hz, {lp.steps} steps "
        f"x {lp.substeps} sub-steps x {lp.seeds} seed{'s' if lp.seeds > 1 else ''}; methods {', '.join(lp.methods)}")
    dm = loop_mirror(rec, device.crop, sc.wavelength)
    modes = np.asarray(ModalDM.for_crop(device.crop, n_modes=MODES).influence, np.float64)  # unit-rms Zernikes
    sh = sh_lenslets_for(sc, lp.sh_lenslets) if "shack_hartmann" in lp.methods else {}
    if sh:
        log(f"  Shack-Hartmann: {sh['lenslets']} lenslets across, d/r0 {sh['d_over_r0']:.2f} ({sh['why']})")
    ctx = LoopContext(rec, tb, wind, c0, a, PiB(sc, c0, a), dm, modes,
                      _sensors(rec, device, sh.get("lenslets", 8)), sh=sh)
    return ctx, device, temporal


def _job_key(rec: LoopRecipe) -> str:
    """The content key of a loop study's tasks (what shapes their series; never where the files lie)."""
    files = {k: file_key(p) for k, p in (("design", rec.design), ("sensor", rec.sensor),
                                         ("turbulence", rec.turbulence), ("model", rec.model),
                                         ("realtime", rec.realtime)) if p is not None}
    lp = {**rec.loop.__dict__, "methods": list(rec.loop.methods)}
    return content_key({"format": "metadesign.loop-tasks/1", "loop": lp, "dm": rec.dm.__dict__, "wind": rec.wind,
                        "files": files})


def _measure_latencies(ctx: LoopContext, folder: TaskFolder) -> dict:
    """Each closed loop's latency (s): declared, else measured once (kept in the resume folder)."""
    lp = ctx.rec.loop
    ctx.retrieval = calibrate_retrieval(ctx, folder)

    def measure():
        out = {}
        for m, s in ctx.sensors.items():
            out[m] = (float(lp.latency_ms[m]) if m in lp.latency_ms else 0.0 if m == "ideal" else
                      _latency(s, ctx.world(0)))
        return out

    lat, _ = folder.step("latencies", folder.key, measure)
    return {m: float(v) for m, v in lat.items()}


def calibrate_retrieval(ctx: LoopContext, folder: TaskFolder) -> dict:
    """The ``retrieval`` method's iteration count for ``[loop] retrieval_budget_ms``: its cost measured on this
    machine on the first frame of realisation 0, once per study (kept in the resume folder), and set on its
    sensor (:meth:`~metadesign.studies.loop.RetrievalLoopSensor.calibrate`); ``{}`` without the method."""
    s = ctx.sensors.get("retrieval")
    if s is None:
        return {}
    world = ctx.world(0)

    def measure():
        frame = s.expose([world.received(world.screens_at(0))], 0)
        return s.calibrate(frame, ctx.rec.loop.retrieval_budget_ms * 1e-3)

    cal, _ = folder.step("retrieval-budget", folder.key, measure)
    s.iterations = int(cal["iterations"])
    return cal


def _gain_name(m: str, g: float) -> str:
    return f"gain-{m}-{g:.4f}"


def _search_gains(ctx: LoopContext, folder: TaskFolder, run: Execution) -> dict:
    """``gain = "optimise"``: per closed loop, the mean NPiB of ``gain_steps`` frames of realisation 0 at each
    gain of :data:`GAIN_GRID`, then at :data:`GAIN_REFINE` around the grid's best; ``{method: {"gain": best,
    "gains": [...], "npib_mean": [...]}}`` (the trials in increasing gain)."""
    lp = ctx.rec.loop

    def run_stage(trials: list) -> dict:
        tasks = {_gain_name(m, g): (_gain_name(m, g), m, 0, float(g), lp.gain_steps, False) for m, g in trials}
        res, _ = run.run(_task, tasks, folder, shared=ctx, weight=lambda n: lp.gain_steps, unit="step")
        return {(m, g): float(np.mean(res[name]["npib"])) for name, (_, m, _, g, _, _) in tasks.items()}

    out = gain_search(lp.searched(list(ctx.sensors)), run_stage)
    for m, v in out.items():
        trials = dict(zip(v["gains"], v["npib_mean"]))
        run.log(f"  gain {LABELS[m]:<29} {v['gain']:.3f} (mean NPiB {trials[v['gain']]:.3f} over "
                f"{lp.gain_steps} steps; {len(trials)} trials)")
    return out


def gain_search(keys: list, run_stage: Callable[[list], dict]) -> dict:
    """The two-stage gain search of ``gain = "optimise"`` (the loop study's and the loop map's): for each of
    ``keys`` the gains of :data:`GAIN_GRID`, then :data:`GAIN_REFINE` around the grid's best (rounded to 1e-4,
    kept in (0, 2], those already tried skipped), the best of all winning (the lowest gain on a tie).
    ``run_stage([(key, gain), ...])`` (every key's trials of a stage, in key then gain order) returns
    ``{(key, gain): mean NPiB}``; ``{key: {"gain": best, "gains": [...], "npib_mean": [...]}}`` (the trials in
    increasing gain)."""
    trials: dict = {k: {} for k in keys}
    stages = [lambda k: GAIN_GRID,
              lambda k: [round(_best(trials[k]) + d, 4) for d in GAIN_REFINE if 0 < _best(trials[k]) + d <= 2]]
    for stage in stages:
        todo = [(k, g) for k in keys for g in stage(k) if g not in trials[k]]
        for (k, g), npib in run_stage(todo).items():
            trials[k][g] = npib
    out = {}
    for k in keys:
        gs = sorted(trials[k])
        out[k] = {"gain": _best(trials[k]), "gains": gs, "npib_mean": [trials[k][g] for g in gs]}
    return out


def _best(trials: dict) -> float:
    """The gain of the highest mean NPiB (the lowest such gain on a tie)."""
    return min(trials, key=lambda g: (-trials[g], g))


def run_loop_study(rec: LoopRecipe, out: Path, run: Execution = SERIAL) -> dict:
    """Every method of ``rec`` on each of its turbulence realisations, into ``out`` (``loop.json``,
    ``loop.png``, the designed device in ``out/design``); the tasks resumable in ``OUT.partial`` (removed at
    the end)."""
    t_start = time.perf_counter()
    lp = rec.loop
    ctx, _, temporal = build_loop(rec, out, run.log)
    folder = TaskFolder(scratch_path(out), _job_key(rec), log=run.log, what="loop study")
    ctx.latency = _measure_latencies(ctx, folder)
    if ctx.retrieval:
        run.log(f"  retrieval: {ctx.retrieval['why']} (budget {lp.retrieval_budget_ms:g} ms)")
    ctx._cache.clear()
    search = _search_gains(ctx, folder, run) if lp.optimise_gain else {}
    gains = {m: search[m]["gain"] if m in search else lp.given(m) for m in ctx.sensors}
    order = ["open"] + [m for m in lp.methods if m != "open"]
    names = {(m, r): f"seed{r:05d}-{m}" for m in order for r in range(lp.seeds)}
    tasks = {names[m, r]: (names[m, r], m, r, float(gains.get(m, 0.0)), lp.steps, True)
             for r in range(lp.seeds) for m in order}
    res, _ = run.run(_task, tasks, folder, shared=ctx, weight=lambda n: lp.steps, unit="step")
    runs = {m: [res[names[m, r]] for r in range(lp.seeds)] for m in order}
    measured = [m for m in ctx.sensors if m not in lp.latency_ms and m != "ideal"]
    prov = loop_provenance(rec, out, measured, run.workers,
                           run.scheduler or ("an open Dask client" if run.client is not None else None))
    rep, firsts, pooled = loop_report(rec, runs, {m: ctx.timing(m) for m in order}, ctx.latency, gains, search,
                                      temporal, t_start, GAIN_GRID, GAIN_REFINE, run.log, prov)
    if ctx.sh:
        rep["shack_hartmann"] = ctx.sh  # its lenslet count and why
    if ctx.retrieval:
        rep["retrieval"] = ctx.retrieval  # its budget, its measured costs and the iterations they allow
    rep["figures"] = [str(p) for p in plot_loop(rep, firsts, pooled, out)]
    atomic_write_text(out / "loop.json", json.dumps(rep, indent=1, default=float))
    folder.remove()
    return rep


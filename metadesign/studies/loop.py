"""The loop in time (issue #50): a beacon through moving turbulence, a sensor that integrates each frame over
the turbulence's motion, a reconstruction, a deformable mirror driven by a controller with the loop's real
delay, and the power in the bucket of the corrected outgoing beam at every step.

One step ``k`` of a loop at ``rate_hz`` (frame ``[k, k + 1) / rate_hz``):

1. the turbulence at the exposure's ``substeps`` instants (:class:`LoopWorld`: the frozen-flow screens, the
   beacon's split step, the collimated received crop);
2. the residual the sensor sees, each received crop times ``exp(-i phi_DM)`` (the mirror's phase as it stands
   during the frame), measured by the loop's sensor (:class:`MetasurfaceSensor`: the device's exposure
   integrated over the sub-steps, read once by its detector, an estimator's phase; a Shack-Hartmann in the same
   plane; the ideal-phase sensor), or nothing (open loop);
3. the mirror's fit of that residual estimate, through the controller (a leaky integrator; the total delay in
   frames, real-valued: half the exposure, the readout, the reconstruction's latency, the mirror's response)
   to the commands applied from the next frame on;
4. the normalised power in the bucket of the outgoing beam corrected by the mirror, sent back through the
   turbulence of the frame's first instant, and the residual phase's rms and branch points.

Warm-started reconstructions (:class:`WarmStartSensor`: the retrieval capped by a latency budget,
:class:`RetrievalLoopSensor`, and the learned refinement without its U-Net, :class:`RefineWarmSensor`)
start each frame from the previous frame's estimate moved by the mirror (:class:`WarmStart`), so the
engine hands them the mirror's surface during the frame.

References on the same turbulence: the open loop (no correction), the zero-delay mirror-fitted oracle (the
mirror fitted to the true phase at that instant) and the phase-conjugate oracle (the exact phase).  The
engine takes its mirror and controller as objects with ``fit(phase, mask)`` / ``surface(commands)`` and
``step(error) -> commands`` (:mod:`metadesign.optics.dm`, :mod:`metadesign.optics.control`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from ..optics.control import pseudo_open_loop as _pol
from ..optics.dm import ORACLE_ITERATIONS, fitted_oracle, phase_of  # noqa: F401  (the loop's names, kept here)
from ..optics.propagation import cexp
from ..reconstruction.dataset import normalise_psf
from ..reconstruction.estimators import make_estimator
from ..reconstruction.retrieval import RetrievalConfig, retrieve

__all__ = ["LoopTiming", "LoopWorld", "MetasurfaceSensor", "IdealPhaseSensor", "run_loop", "branch_points",
           "fitted_oracle", "phase_of", "ORACLES", "flow_seed", "noise_stream", "pol_rejection_tf", "WarmStart",
           "WarmStartSensor", "RetrievalLoopSensor", "RefineWarmSensor", "budget_iterations", "MAX_RETRIEVAL_ITERATIONS"]

#: references that need no sensor, mirror or controller
ORACLES = ("open", "fitted", "conjugate")

#: the spawn-key tag of a loop's turbulence realisations after the first (``(REALISATION_TAG, r, ...)``)
REALISATION_TAG = 0x4C4F4F50  # "LOOP"


def flow_seed(seed: int, r: int) -> int | np.random.SeedSequence:
    """The frozen-flow seed of realisation ``r`` of a loop seeded ``seed``: ``seed`` itself for the first
    (realisation 0 is the one-seed loop's turbulence, bit for bit), else the SeedSequence of ``seed`` with the
    spawn key ``(REALISATION_TAG, r, 0)`` (the flow spawns one child per screen below it: no stream is shared
    with another realisation, another screen, or the sensors' noise)."""
    return int(seed) if r == 0 else np.random.SeedSequence(int(seed), spawn_key=(REALISATION_TAG, int(r), 0))


def noise_stream(r: int) -> tuple:
    """The spawn-key prefix of realisation ``r``'s detector noise (a sensor's frame ``k`` draws from
    ``SeedSequence(seed, spawn_key=(*stream, 11 or 12, k))``): empty for the first (the one-seed loop's noise),
    ``(REALISATION_TAG, r, 1)`` after it."""
    return () if r == 0 else (REALISATION_TAG, int(r), 1)


@dataclass(frozen=True)
class LoopTiming:
    """A loop's clock: ``rate_hz`` frames per second, each exposure integrated over ``substeps`` instants; the
    total delay in frames (real-valued, :class:`metadesign.optics.control.Controller`'s) from the frame
    measured to the frame corrected: half the exposure and half the mirror's hold (one frame: a frame
    corrected on the next), the readout, the reconstruction's latency and the mirror's response,
    ``1 + readout_frames + latency_s * rate_hz + dm_frames``."""

    rate_hz: float
    substeps: int = 4
    readout_frames: float = 0.0
    latency_s: float = 0.0
    dm_frames: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError("rate_hz must be > 0")
        if self.substeps < 1:
            raise ValueError("substeps must be >= 1")

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def delay_frames(self) -> float:
        return 1.0 + self.readout_frames + self.latency_s * self.rate_hz + self.dm_frames

    def sub_steps(self, k: int) -> range:
        """The turbulence's steps (of ``dt / substeps``) during frame ``k``'s exposure."""
        return range(k * self.substeps, (k + 1) * self.substeps)


@dataclass
class LoopWorld:
    """The turbulence a loop runs in: ``screens_at(j)`` (the moving screens, (n_screens, n, n) rad at the
    turbulence's step ``j``, ``t = j dt / substeps``: :meth:`metadesign.turbulence.frozen.FrozenFlow.screens`), the path (:class:`~metadesign.turbulence.propagate.Turbulence` at the loop's Rytov number), the
    received crop ``[c0, c0 + a)`` and its bucket (:class:`~metadesign.reconstruction.losses.PiB`)."""

    turbulence: Any
    screens_at: Callable[[int], np.ndarray]
    c0: int
    a: int
    pib: Any
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def mask(self) -> np.ndarray:
        """(a, a) bool: the receiver aperture on the crop."""
        c0, a = self.c0, self.a
        return self.turbulence.aperture[c0:c0 + a, c0:c0 + a]

    def received(self, screens: np.ndarray) -> np.ndarray:
        """The collimated received crop (a, a) complex64 of the beacon through ``screens``."""
        tb, c0, a = self.turbulence, self.c0, self.a
        return tb.collimated(tb.element.forward(tb.source, screens))[c0:c0 + a, c0:c0 + a]

    def npib(self, phi: np.ndarray, screens: np.ndarray) -> float:
        """NPiB of the phase-only correction conjugating ``phi`` (a, a) through ``screens``."""
        import torch

        with torch.no_grad():
            return float(self.pib.npib_phase(torch.from_numpy(np.asarray(phi, np.float32))[None],
                                             torch.from_numpy(np.asarray(screens, np.float32))[None]))


class MetasurfaceSensor:
    """The metasurface wavefront sensor in the loop: each frame the device's exposure of the residual crops
    (:meth:`~metadesign.sensing.device.Device.expose`: integrated over the sub-steps, read once by the
    detector, drawn from ``seed`` and the frame), normalised as the datasets are, and the estimator's phase
    estimate of the residual (rad, on the crop).  ``stream``: the noise's spawn-key prefix
    (:func:`noise_stream`: one per turbulence realisation)."""

    def __init__(self, device, estimator, detector=None, seed: int = 0, stream: tuple = ()):
        self.device, self.estimator, self.detector, self.seed = device, estimator, detector, int(seed)
        self.stream = tuple(stream)

    def expose(self, crops: list, k: int) -> dict:
        """Frame ``k`` as the camera records it: the estimator's input batch (the sensor's side)."""
        fields = [self.device.pupil_field(c) for c in crops]
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(*self.stream, 11, int(k))))
        shot = self.device.expose(fields, self.detector, rng)
        psf, _ = normalise_psf(shot.psfs)
        return {"psf": psf[None], "received": np.asarray(crops[-1])[None], "index": np.array([k])}

    def reconstruct(self, frame: dict) -> np.ndarray:
        """The estimator's phase estimate (rad, on the crop) of one recorded frame: what its latency times."""
        return np.asarray(self.estimator.estimate(frame), np.float64)[0]

    def measure(self, crops: list, k: int) -> np.ndarray:
        return self.reconstruct(self.expose(crops, k))


class IdealPhaseSensor:
    """A perfect phase sensor: the phase of the residual field averaged over the exposure (rad, on the crop;
    wrapped where the field has branch points), with no latency."""

    def expose(self, crops: list, k: int) -> np.ndarray:
        return np.mean(np.asarray(crops), axis=0)

    def reconstruct(self, frame) -> np.ndarray:
        return phase_of(frame)

    def measure(self, crops: list, k: int) -> np.ndarray:
        return self.reconstruct(self.expose(crops, k))


class WarmStart:
    """The warm start of a reconstruction in a closed loop: frame ``k``'s start is frame ``k - 1``'s
    estimate of its residual minus the change of the mirror's surface since that frame,
    ``start_k = est_{k-1} - (s_k - s_{k-1})`` (``s_k`` the surface the mirror holds during frame ``k``, rad on
    the crop).  Why: the sensor sees the residual ``phi_k - s_k`` (``phi_k`` the turbulence's phase), so
    ``phi_k - s_k = (phi_{k-1} - s_{k-1}) - (s_k - s_{k-1}) + (phi_k - phi_{k-1})``: the previous residual, less
    what the mirror moved (known: the loop sent the commands), plus what the turbulence moved in one frame
    (unknown: what the reconstruction has left to find).  With frozen turbulence and a perfect previous
    estimate the start is the current residual exactly (modulo 2 pi and a piston where the estimate was a
    wrapped phase).  The first frame has no start (None)."""

    def __init__(self):
        self.estimate = self.surface = None

    def start(self, surface: np.ndarray) -> np.ndarray | None:
        """Frame's start given the mirror's ``surface`` during it (None: no previous estimate)."""
        if self.estimate is None:
            return None
        return self.estimate - (np.asarray(surface, np.float64) - self.surface)

    def update(self, estimate: np.ndarray, surface: np.ndarray) -> None:
        """Keep the frame's ``estimate`` and the ``surface`` it was measured behind."""
        self.estimate = np.array(estimate, np.float64)
        self.surface = np.array(surface, np.float64)


class WarmStartSensor:
    """A loop sensor whose reconstruction starts from the previous frame's estimate (:class:`WarmStart`):
    :func:`run_loop` calls ``measure(crops, k, surface=...)`` with the mirror's surface during the frame
    (``warm_start = True``).  Frame 0 starts afresh (a new run, no state kept across runs).  Subclasses give
    ``expose(crops, k)`` and ``reconstruct(frame, start)`` (``start`` None: the cold start); what a loop's
    latency times is :meth:`steady_state`, a warm-started reconstruction (every frame's but the first)."""

    warm_start = True

    def measure(self, crops: list, k: int, surface: np.ndarray | None = None) -> np.ndarray:
        if k == 0 or getattr(self, "_warm", None) is None:
            self._warm = WarmStart()
        surface = np.zeros(np.shape(crops[0])) if surface is None else surface
        self.last_start = self._warm.start(surface)
        est = self.reconstruct(self.expose(crops, k), self.last_start)
        self._warm.update(est, surface)
        return est

    def reconstruct(self, frame, start: np.ndarray | None = None) -> np.ndarray:
        raise NotImplementedError

    def steady_state(self, frame) -> np.ndarray:
        """A warm-started reconstruction of ``frame`` (from a flat start: its cost does not depend on it)."""
        a = self.device.crop.size
        return self.reconstruct(frame, np.zeros((a, a)))


#: the most iterations a latency budget gives the loop's retrieval
MAX_RETRIEVAL_ITERATIONS = 10_000


def budget_iterations(budget_s: float, per_iteration_s: float, overhead_s: float) -> tuple[int, bool]:
    """The iterations of a reconstruction costing ``overhead_s + n per_iteration_s`` that fit ``budget_s``:
    ``floor((budget - overhead) / per_iteration)``, at least 1 and at most :data:`MAX_RETRIEVAL_ITERATIONS`;
    and whether even one iteration exceeds the budget (then 1)."""
    one = overhead_s + per_iteration_s
    if one > budget_s:
        return 1, True
    n = int(np.floor((budget_s - overhead_s) / max(per_iteration_s, 1e-12) + 1e-9))
    return int(min(max(n, 1), MAX_RETRIEVAL_ITERATIONS)), False


class RetrievalLoopSensor(WarmStartSensor, MetasurfaceSensor):
    """Model-based phase-diversity retrieval (:func:`~metadesign.reconstruction.retrieval.retrieve`, the
    ``retrieval`` estimator's context) in the loop, capped by a latency budget: its zonal stage only
    (per-pixel phase and log-amplitude through the twin), ``iterations`` Adam steps per frame, started from
    the previous frame's estimate moved by the mirror (:class:`WarmStart`; the retrieval's API takes a start
    phase: the log-amplitude starts at zero each frame, and so does Adam's state), the first frame from a
    flat phase.  :meth:`calibrate` measures its cost and chooses ``iterations`` for a budget."""

    def __init__(self, device, config: RetrievalConfig, detector=None, seed: int = 0, stream: tuple = (),
                 iterations: int = 1):
        est = make_estimator("retrieval", device, SimpleNamespace(retrieval=config))
        MetasurfaceSensor.__init__(self, device, est, detector, seed, stream)
        self.config, self.iterations = est.config, int(iterations)

    def solve(self, psf: np.ndarray, start: np.ndarray | None, iterations: int) -> np.ndarray:
        """The retrieval's phase (A, A) of one frame's PSFs after ``iterations`` zonal steps from ``start``."""
        import torch

        a = self.device.crop.size
        init = torch.zeros((1, a, a)) if start is None else torch.from_numpy(np.asarray(start, np.float32))[None]
        cfg = replace(self.config, modal_iterations=0, zonal_iterations=int(iterations))
        out = retrieve(torch.from_numpy(np.ascontiguousarray(psf, np.float32)), self.estimator.ctx, cfg, init=init)
        return np.asarray(out["phi"], np.float64)[0]

    def reconstruct(self, frame: dict, start: np.ndarray | None = None) -> np.ndarray:
        return self.solve(frame["psf"], start, self.iterations)

    def calibrate(self, frame: dict, budget_s: float, probe: int = 16, repeats: int = 7,
                  clock: Callable[[], float] = time.perf_counter) -> dict:
        """Measure this machine's cost of the retrieval on ``frame`` (the median of ``repeats`` runs of 1 and
        of ``1 + probe`` iterations after a warm-up: ``per_iteration = (t(1 + probe) - t(1)) / probe``,
        ``overhead = t(1) - per_iteration``, the rendering's set-up and the estimate's return), set
        ``iterations`` to what fits ``budget_s`` (:func:`budget_iterations`) and say so."""
        psf, a = frame["psf"], self.device.crop.size
        start = np.zeros((a, a))
        t = {}
        for n in (1, 1 + probe):
            self.solve(psf, start, n)  # warm-up
            ts = []
            for _ in range(repeats):
                t0 = clock()
                self.solve(psf, start, n)
                ts.append(clock() - t0)
            t[n] = float(np.median(ts))
        per = max((t[1 + probe] - t[1]) / probe, 1e-9)
        overhead = max(t[1] - per, 0.0)
        n, over = budget_iterations(budget_s, per, overhead)
        self.iterations = n
        why = (f"one iteration ({(overhead + per) * 1e3:.3f} ms: {overhead * 1e3:.3f} ms of overhead + "
               f"{per * 1e3:.3f} ms) exceeds the {budget_s * 1e3:g} ms budget: 1 iteration, over budget" if over else
               f"floor(({budget_s * 1e3:g} - {overhead * 1e3:.3f}) ms / {per * 1e3:.3f} ms) = {n} iterations"
               + (f" (at most {MAX_RETRIEVAL_ITERATIONS})" if n == MAX_RETRIEVAL_ITERATIONS else ""))
        return {"budget_ms": budget_s * 1e3, "per_iteration_ms": per * 1e3, "overhead_ms": overhead * 1e3,
                "iterations": n, "exceeds_budget": bool(over), "probe": {"iterations": [1, 1 + probe],
                                                                          "repeats": repeats},
                "why": why}


class RefineWarmSensor(WarmStartSensor, MetasurfaceSensor):
    """The learned refinement (a refiner's ``K`` unrolled steps, the ``refine`` estimator) started from the
    previous frame's estimate moved by the mirror (:class:`WarmStart`) instead of its U-Net's output, so the
    U-Net's latency is skipped; the first frame starts from the U-Net (the refiner's own start)."""

    def __init__(self, device, refiner, detector=None, seed: int = 0, stream: tuple = ()):
        est = make_estimator("refine", device, refiner=refiner)
        MetasurfaceSensor.__init__(self, device, est, detector, seed, stream)

    def reconstruct(self, frame: dict, start: np.ndarray | None = None) -> np.ndarray:
        done = None if start is None else {self.estimator.starts_from: np.asarray(start, np.float32)[None]}
        return np.asarray(self.estimator.estimate(frame, done), np.float64)[0]


def branch_points(field: np.ndarray, mask: np.ndarray) -> int:
    """Phase singularities of ``field`` inside ``mask``: plaquettes (2 x 2 samples, all inside) around which
    the wrapped phase differences sum to a non-zero multiple of 2 pi."""
    ph = np.angle(field)

    def wrap(d):
        return (d + np.pi) % (2 * np.pi) - np.pi

    a, b, c, d = ph[:-1, :-1], ph[:-1, 1:], ph[1:, 1:], ph[1:, :-1]
    circ = wrap(b - a) + wrap(c - b) + wrap(d - c) + wrap(a - d)
    inside = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, 1:] & mask[1:, :-1]
    return int((np.abs(circ[inside]) > np.pi).sum())


def _rms(phi: np.ndarray, mask: np.ndarray) -> float:
    v = phi[mask]
    return float(np.sqrt(np.mean((v - v.mean()) ** 2)))


def pol_rejection_tf(f, fs: float, gain: float, delay_frames: float, leak: float = 1.0) -> np.ndarray:
    """The rejection ``residual / disturbance`` of the pseudo-open-loop controller of :func:`run_loop` (a
    perfect, linear sensor): the integrator's state ``c_{k+1} = (leak - gain) c_k + gain w_k`` driven by the
    pseudo-open-loop disturbance ``w_k``, held ``delay - 1`` frames, so ``1 - gain z^-n ((1 - a) + a z^-1) /
    (1 - (leak - gain) z^-1)`` (``delay = n + a``, ``z = exp(2 pi i f / fs)``); at one frame of delay it is the
    integrator's ``1 / (1 + H_OL)``."""
    d = float(delay_frames)
    n = int(np.floor(d))
    a = d - n
    zi = np.exp(-2j * np.pi * np.asarray(f, float) / fs)
    return 1 - gain * zi ** n * ((1 - a) + a * zi) / (1 - (leak - gain) * zi)


def run_loop(world: LoopWorld, timing: LoopTiming, steps: int, method: str, sensor=None, dm=None,
             controller=None, modes: np.ndarray | None = None, progress=None, *,
             pseudo_open_loop: bool = False) -> dict:
    """``steps`` frames of the loop ``method`` (a closed loop with ``sensor``, ``dm`` and ``controller``, or one
    of :data:`ORACLES`) in ``world``: per step the NPiB, the residual phase's rms (rad, piston removed) and its
    branch points, and with ``modes`` (M, a, a: an orthonormal modal basis on the aperture) the residual's modal
    coefficients (T, M).  Same world, same seed: the same turbulence for every method.

    ``pseudo_open_loop``: the sensor still measures the residual (the field times the mirror's conjugate, as
    the device sees it), but the controller integrates on the pseudo-open-loop disturbance, the residual's fit
    plus the commands the mirror held during the frame (command space,
    :func:`metadesign.optics.control.pseudo_open_loop`): its error is ``w_k - c_k`` (``c_k`` the integrator's
    state), so ``c_{k+1} = (leak - gain) c_k + gain w_k``, the delay line after it as before (at one frame of
    delay this is the plain integrator; see :func:`pol_rejection_tf`)."""
    mask = world.mask
    n = int(mask.sum())
    out = {"npib": np.empty(steps), "residual_rms": np.empty(steps), "branch_points": np.empty(steps, int)}
    if modes is not None:
        out["modal"] = np.empty((steps, len(modes)))
    closed = method not in ORACLES
    if closed and (sensor is None or dm is None or controller is None):
        raise ValueError(f"loop method {method!r}: a closed loop needs a sensor, a mirror and a controller")
    phi_dm = np.zeros(mask.shape)
    held = None  # the commands the mirror holds during the frame (None: none yet)
    for k in range(steps):
        scr = [world.screens_at(j) for j in timing.sub_steps(k)]
        rec = [world.received(s) for s in scr]
        if method == "fitted":
            phi_dm = fitted_oracle(dm, rec[0], mask)
        elif method == "conjugate":
            phi_dm = phase_of(rec[0] * mask) * mask
        corr = cexp(-phi_dm)  # the mirror's conjugate, once per frame
        res = [r * corr for r in rec]  # what the sensor sees during the frame
        res0 = res[0]
        out["npib"][k] = world.npib(phi_dm, scr[0])
        ph = phase_of(res0 * mask) * mask
        out["residual_rms"][k] = _rms(ph, mask)
        out["branch_points"][k] = branch_points(res0, mask)
        if modes is not None:
            out["modal"][k] = modes.reshape(len(modes), -1) @ ph.ravel() / n
        if closed:
            # a warm-started reconstruction moves its last estimate by the mirror's change (WarmStart)
            meas = (sensor.measure(res, k, surface=phi_dm) if getattr(sensor, "warm_start", False)
                    else sensor.measure(res, k))
            e = dm.fit(meas, mask)
            if pseudo_open_loop:
                state = controller.integrator.state
                w = _pol(e, dm.clip(held)) if held is not None else e
                e = w - state if state is not None else w
            held = controller.step(e)
            phi_dm = dm.surface(held)
        if progress:
            progress(k + 1, steps)
    return out

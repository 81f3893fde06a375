"""The loop recipe (``metadesign loop RECIPE``; TOML, keys carry their unit, validated at load, paths relative
to the recipe):

.. code-block:: toml

    [device]                      # the sensor as made, as the pipeline's [beacons] names it
    design = "../layouts/paper-5mm.toml"
    sensor = "paper.toml"
    turbulence = "turbulence.toml"
    model = "models/demo-refine.safetensors"   # a U-Net, or a refiner with its U-Net

    [loop]
    rate_hz = 2000.0
    steps = 400
    substeps = 4                  # exposure sub-steps (the turbulence moves during a frame)
    rytov = 0.5
    gain = 0.4                    # or "optimise": chosen per closed loop (see gain_steps), or a table
                                  # {method = gain, ...} naming every closed loop (a long run at searched gains;
                                  # a loop's entry "optimise": only its gain searched)
    gain_steps = 100              # "optimise": the steps of each trial run (the first seed's first frames)
    pseudo_open_loop = false      # the controller integrates the residual's fit plus the mirror's commands
    seeds = 1                     # independent turbulence realisations (each method runs on every one)
    leak = 0.99
    noise_percent = 5.0           # additive Gaussian noise, % of each frame's peak
    photons_per_frame = 0.0       # shot noise: photo-electrons at each camera frame's peak (0: none)
    read_noise_e = 0.0            # read noise (electrons rms per pixel; with photons_per_frame)
    sh_lenslets = 8               # the Shack-Hartmann's lenslets across, or "auto" (d <= r0)
    readout_frames = 0.0
    dm_frames = 0.0
    latency_ms = {}               # per method; a method not named: measured on this machine
    retrieval_budget_ms = 5.0     # method "retrieval": its iterations capped to fit this latency here
    methods = ["unet", "refine", "shack_hartmann", "ideal", "fitted", "conjugate", "open"]
    seed = 0
    threshold_db = 3.0

    [dm]
    actuators = 12                # across the receiver aperture
    coupling = 0.15
    regularisation = 1e-3
    # stroke_um = 2.0             # surface stroke +- per command (default: none)
    # influence = "dm.npy"        # measured influence functions (default: the Gaussians)
    tip_tilt = false              # true: a separate tip/tilt mirror takes the tilt

    [wind]                        # the turbulence's motion (metadesign.turbulence.frozen)
    speed_m_s = 5.0

The detector (``[loop]``).  Each loop frame is one exposure (its sub-steps' noise-free frames averaged) read
once by the sensing stage's detector (:class:`~metadesign.sensing.detector.Detector`, the model the
datasets and training draw with): ``photons_per_frame`` is its ``photons_at_peak``, the photo-electrons at
the brightest pixel of each camera frame of one loop frame (the ideal camera's two frames, four of the
eight channels each, or a mosaic camera's raw capture, each scaled so its peak holds that many: the
exposure is set on the brightest spot, as in the datasets), Poisson shot noise plus ``read_noise_e``
electrons rms of Gaussian read noise per pixel, then ``noise_percent`` % of the peak of additive Gaussian
noise.  The Shack-Hartmann's detector frame (all its spots, one frame) is read by the same detector, its
peak pixel holding ``photons_per_frame``; its centroid threshold assumes the background noise
``hypot(noise_percent, 100 read_noise_e / photons_per_frame)`` % of the peak.  ``photons_per_frame = 0``
(the default): no shot or read noise (``read_noise_e`` needs photons).

The Shack-Hartmann (``[loop] sh_lenslets``): lenslets across the receiver aperture, an integer in [2, 64]
(default 8, what the loop ran before the key existed), or ``"auto"``: the fewest lenslets whose
sub-apertures are no larger than the path's Fried parameter, ``ceil(D / r0)`` (the spherical-wave r0 of
the loop's path at its Rytov number and the beacon's wavelength), clipped to [2, floor(D / (4 dx))] (at
least 4 received-field samples of pitch ``dx`` per lenslet: a lenslet's spot is the Fourier transform of
its samples).  Why ``d <= r0``: a sub-aperture of ``d`` has a tilt-removed phase variance of
``0.134 (d / r0)^(5/3)`` rad^2 (Noll 1976), at most 0.134 rad^2 here, so each spot is one
diffraction-limited core whose centroid is the sub-aperture's mean gradient; larger sub-apertures break
their spots into speckle and leave more of the phase between the lenslets, smaller ones divide the light
and the pixels among more spots for little gain (Hardy's ``d ~ r0``).  The Rytov number sets r0 on this
path (at Rytov 0.5 on the demo path, D / r0 = 4.9: 5 lenslets).  The report's ``shack_hartmann`` records the
count, the rule and ``d / r0``.  (A loop map builds its sensors at its first Rytov number: ``"auto"``
there is that number's count.)

The warm-started methods (on request: ``methods`` names them; :class:`~metadesign.studies.loop.WarmStart`):
each frame's reconstruction starts from the previous frame's estimate minus the change of the mirror's
surface since that frame (the sensor sees the residual; the loop knows what it sent the mirror), the
first frame afresh.  ``retrieval``: the model-based phase-diversity retrieval (the ``retrieval``
estimator's twin and Gaussian misfit at ``noise_percent``; its zonal stage, per-pixel phase and
log-amplitude) capped by a latency budget: before the runs the study measures on this machine its cost on
one frame (the fixed overhead and the cost per iteration) and gives it the most iterations that fit
``retrieval_budget_ms`` (default 5 ms; one, and the report says so, where even one exceeds it); the
report's ``retrieval`` records the budget, the costs and the count (kept in the resume folder with the
latencies).  ``refine_warm``: the learned refinement of ``[device] model`` (a refiner) with its steps
started from that warm start instead of its U-Net's output, so the U-Net's latency is skipped (the first
frame uses the U-Net).  Each one's delay is its latency measured here (a warm-started frame's, the steady
state) or declared in ``latency_ms``, as for the other methods.

The mirror (``[dm]``).  ``stroke_um``: the mirror's surface stroke, each command clipped to
``+- 4 pi stroke / lambda`` rad of phase at the beacon's wavelength (a reflective mirror; the zonal mirror's
Gaussians peak at 1 rad per unit command, so this bounds each actuator's displacement; a modal corrector's
each mode's rms coefficient); the integrator itself is not clipped (no anti-windup; its leak bounds it).
``influence``: a ``.npy`` of measured influence functions, ``(n, A, A)`` rad of phase per unit command on the
received crop (``A`` samples across, the crop of the turbulence grid holding the receiver aperture), read
without unpickling; in place of the Gaussians (``kind = "zonal"`` only; ``actuators`` and ``coupling`` then
unused).  ``tip_tilt = true``: a separate tip/tilt mirror (:class:`~metadesign.optics.dm.TipTiltSplit`)
takes each estimate's least-squares tilt and the mirror the rest, the mirror's stroke spent on the higher
orders (the tip/tilt mirror's stroke unlimited).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import Param, Section, load_toml, parse
from ..reconstruction.dataset import received_crop
from ..reconstruction.refine import is_refiner
from ..tasks import file_key
from ..turbulence.scenario import load_scenario, wind_from_dict
from ..validation import ConfigError
from .loop import ORACLES

__all__ = ["LoopRecipe", "LoopSection", "DMSection", "METHODS", "DEFAULT_METHODS", "METASURFACE", "REALTIME", "OPTIMISE",
           "load_loop_recipe",
           "loop_recipe_of", "SECTIONS", "AUTO", "SH_LENSLETS", "load_influence"]

#: the value of ``[loop] gain`` that has the study choose each closed loop's gain
OPTIMISE = "optimise"
#: the loop's methods: closed loops (a sensor and its reconstruction) and the references
METHODS = ("unet", "refine", "shack_hartmann", "ideal", "fitted", "conjugate", "open", "linear", "realtime",
           "retrieval", "refine_warm", "realtime_tt", "realtime_peak")
#: the methods of a recipe that names none (``linear``, the push-pull linear reconstructor, ``realtime``, the
#: real-time modal network of ``[device] realtime`` (issue #51), ``retrieval``, the phase-diversity retrieval
#: capped by ``retrieval_budget_ms``, ``refine_warm``, the refinement warm-started from the last frame, and
#: ``realtime_tt`` and ``realtime_peak``, the real-time network with its tip and tilt read by the push-pull linear
#: reconstructor or by the in-focus channel's peak, on request)
DEFAULT_METHODS = tuple(m for m in METHODS if m not in ("linear", "realtime", "retrieval", "refine_warm",
                                                        "realtime_tt", "realtime_peak"))
#: the methods that read the real-time network of ``[device] realtime``
REALTIME = ("realtime", "realtime_tt", "realtime_peak")
#: the metasurface sensor's loops (the verdict's best is among them)
METASURFACE = ("refine", "unet", "linear", "realtime", "realtime_tt", "realtime_peak", "retrieval", "refine_warm")
#: the value of ``[loop] sh_lenslets`` that has the study choose the lenslet count from the path's r0
AUTO = "auto"
#: ``[loop] sh_lenslets``: the default, and the range of a given count
SH_LENSLETS = 8
SH_LENSLETS_RANGE = (2, 64)

SECTIONS = (
    Section("device", (
        Param("design", str), Param("sensor", str), Param("turbulence", str), Param("model", str, None),
        Param("realtime", str, None),
    )),
    Section("loop", (
        Param("rate_hz", float, 2000.0, lo=1, hi=1e6),
        Param("steps", int, 400, lo=2, hi=10_000_000),
        Param("substeps", int, 4, lo=1, hi=64),
        Param("rytov", float, 0.5, lo=0, open_lo=True, hi=5),
        Param("gain_steps", int, 100, lo=2, hi=10_000_000),
        Param("pseudo_open_loop", bool, False),
        Param("seeds", int, 1, lo=1, hi=100_000),
        Param("leak", float, 0.99, lo=0, hi=1),
        Param("noise_percent", float, 5.0, lo=0, hi=100),
        Param("photons_per_frame", float, 0.0, lo=0, hi=1e15,
              help="shot noise: photo-electrons at each camera frame's peak per loop frame (0: none)"),
        Param("read_noise_e", float, 0.0, lo=0, hi=1e6, help="read noise, electrons rms (needs photons_per_frame)"),
        Param("readout_frames", float, 0.0, lo=0, hi=1000),
        Param("dm_frames", float, 0.0, lo=0, hi=1000),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
        Param("threshold_db", float, 3.0, lo=0, open_lo=True, hi=60),
        Param("retrieval_budget_ms", float, 5.0, lo=0, open_lo=True, hi=1e5,
              help="method retrieval: the latency its iterations are capped to on this machine (ms)"),
    ), optional=True),
    Section("dm", (
        Param("kind", str, "zonal", choices=("zonal", "modal"),
              help="zonal: Gaussian influence functions on an actuator grid; modal: Zernike modes Noll 2..modes+1"),
        Param("modes", int, 20, lo=2, hi=300),
        Param("actuators", int, 12, lo=2, hi=256),
        Param("coupling", float, 0.15, lo=0, open_lo=True, hi=0.9),
        Param("regularisation", float, 1e-3, lo=0, hi=1e6),
        Param("stroke_um", float, None, lo=0, open_lo=True, hi=1000,
              help="surface stroke +- per command (um; default: none)"),
        Param("influence", str, None, help=".npy of measured influence functions (n, A, A), rad per command"),
        Param("tip_tilt", bool, False, help="a separate tip/tilt mirror takes the tilt"),
    ), optional=True),
)


@dataclass(frozen=True)
class LoopSection:
    rate_hz: float
    steps: int
    substeps: int
    rytov: float
    gain: float | str | dict  # a number, OPTIMISE, or {closed-loop method: gain}
    leak: float
    noise_percent: float
    readout_frames: float
    dm_frames: float
    methods: tuple
    seed: int
    threshold_db: float
    latency_ms: dict = field(default_factory=dict)
    seeds: int = 1
    gain_steps: int = 100
    pseudo_open_loop: bool = False
    photons_per_frame: float = 0.0  # the detector's photons_at_peak (0: no shot or read noise)
    read_noise_e: float = 0.0
    sh_lenslets: int | str = SH_LENSLETS  # or AUTO
    retrieval_budget_ms: float = 5.0  # method "retrieval": its latency budget on this machine

    @property
    def optimise_gain(self) -> bool:
        """Whether a closed loop's gain is chosen (``gain = "optimise"``, or a table naming it so) rather
        than given."""
        return _searches(self.gain)

    def searched(self, closed: list) -> list:
        """The closed loops among ``closed`` whose gain the study searches."""
        if self.gain == OPTIMISE:
            return list(closed)
        return [m for m in closed if isinstance(self.gain, dict) and self.gain.get(m) == OPTIMISE]

    def given(self, m: str) -> float:
        """The gain the recipe gives closed loop ``m`` (one not searched): the table's entry, or the one gain."""
        g = self.gain.get(m) if isinstance(self.gain, dict) else self.gain
        if g is None or g == OPTIMISE:
            raise ValueError(f"loop.gain: closed loop {m!r} has no given gain ({self.gain!r})")
        return float(g)


@dataclass(frozen=True)
class DMSection:
    kind: str
    modes: int
    actuators: int
    coupling: float
    regularisation: float
    stroke_m: float | None = None  # surface stroke (m), None: none
    influence_sha256: str | None = None  # the measured influence file's content (the file: LoopRecipe.influence)
    tip_tilt: bool = False


@dataclass(frozen=True)
class LoopRecipe:
    name: str
    source: Path
    design: Path
    sensor: Path
    turbulence: Path
    model: Path | None
    loop: LoopSection
    dm: DMSection
    wind: dict
    realtime: Path | None = None  # the real-time modal network (method "realtime")
    influence: Path | None = None  # [dm] influence: measured influence functions (.npy)


#: the [loop] keys read outside the schema (not numbers alone)
_OUTSIDE = ("gain", "methods", "latency_ms", "sh_lenslets")


def _latencies(raw, methods, where: str) -> dict:
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise ConfigError("loop.latency_ms", f"expected a table of method = milliseconds, got {raw!r}")
    out = {}
    for k, v in raw.items():
        if k not in METHODS:
            raise ConfigError("loop.latency_ms", f"unknown method {k!r} (expected some of {', '.join(METHODS)})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0 <= float(v) <= 1e5) or v != v:
            raise ConfigError(f"loop.latency_ms.{k}", f"expected milliseconds in [0, 1e5], got {v!r}")
        out[k] = float(v) * 1e-3
    return out


def _searches(gain) -> bool:
    """Whether a parsed ``[loop] gain`` has some loop's gain searched."""
    return gain == OPTIMISE or (isinstance(gain, dict) and OPTIMISE in gain.values())


def _gain(raw):
    if raw is None:
        return 0.4
    if raw == OPTIMISE:
        return OPTIMISE
    if isinstance(raw, dict):  # per closed loop (the methods are checked against it at load)
        out = {}
        for m, g in raw.items():
            if g == OPTIMISE:  # this loop's gain searched, the others' given
                out[str(m)] = OPTIMISE
                continue
            if isinstance(g, bool) or not isinstance(g, (int, float)) or not (0 <= float(g) <= 2):
                raise ConfigError(f"loop.gain.{m}", f'expected a number in [0, 2] or "{OPTIMISE}", got {g!r}')
            out[str(m)] = float(g)
        return out
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not (0 <= float(raw) <= 2):
        raise ConfigError("loop.gain", f'expected a number in [0, 2] or "{OPTIMISE}", got {raw!r}')
    return float(raw)


def _sh_lenslets(raw):
    if raw is None:
        return SH_LENSLETS
    if raw == AUTO:
        return AUTO
    lo, hi = SH_LENSLETS_RANGE
    if isinstance(raw, bool) or not isinstance(raw, int) or not lo <= raw <= hi:
        raise ConfigError("loop.sh_lenslets", f'expected an integer in [{lo}, {hi}] or "{AUTO}", got {raw!r}')
    return int(raw)


def load_influence(path: Path, size: int) -> np.ndarray:
    """The measured influence functions at ``path`` (a ``.npy``, never unpickled): ``(n, size, size)`` float32,
    finite; else one ConfigError naming ``dm.influence``."""
    try:
        with open(path, "rb") as fh:
            magic = fh.read(6)
        a = np.load(path, allow_pickle=False) if magic == b"\x93NUMPY" else None
    except (OSError, ValueError, EOFError) as exc:
        why = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise ConfigError("dm.influence", f"{path}: not a readable .npy array ({why})") from None
    if a is None:
        raise ConfigError("dm.influence", f"{path}: not a .npy file (np.save writes one)")
    if (not isinstance(a, np.ndarray) or a.ndim != 3 or a.shape[0] < 1 or a.shape[1:] != (size, size)
            or a.dtype.kind not in "fiu"):
        got = f"shape {a.shape} {a.dtype}" if isinstance(a, np.ndarray) else type(a).__name__
        raise ConfigError("dm.influence", f"{path}: expected an (n, {size}, {size}) real array (rad per unit "
                          f"command on the received crop), got {got}")
    if not np.all(np.isfinite(a)):
        raise ConfigError("dm.influence", f"{path}: has NaN or infinite values")
    return a.astype(np.float32)


def load_loop_recipe(path: str | Path) -> LoopRecipe:
    """The loop recipe at ``path``, validated (one line naming the field on the first problem)."""
    return loop_recipe_of(load_toml(path), path)


def loop_recipe_of(raw: dict, path: str | Path) -> LoopRecipe:
    """The loop recipe of a parsed TOML document ``raw`` read from ``path`` (its paths relative to it),
    validated as :func:`load_loop_recipe` does (a recipe that extends this one, e.g. the loop map's, passes
    what remains once it has taken its own sections)."""
    path = Path(path)
    raw = {k: dict(v) if isinstance(v, dict) else v for k, v in raw.items()}
    sections = [s.name for s in SECTIONS] + ["wind"]
    for name in raw:
        if name not in sections:
            raise ConfigError(name, f"unknown section in {path}; allowed: {', '.join(f'[{x}]' for x in sections)}")
    loop = raw.get("loop") if isinstance(raw.get("loop"), dict) else {}
    keys = [p.key for s in SECTIONS if s.name == "loop" for p in s.params] + list(_OUTSIDE)
    for k in loop:
        if k not in keys:
            raise ConfigError(f"loop.{k}", f"unknown key; allowed: {', '.join(keys)}")
    latency, methods = loop.pop("latency_ms", None), loop.pop("methods", list(DEFAULT_METHODS))
    gain = loop.pop("gain", None)
    lenslets = _sh_lenslets(loop.pop("sh_lenslets", None))
    wind = raw.pop("wind", None)
    v = parse(raw, SECTIONS, str(path))
    lp = v["loop"]
    gain = _gain(gain)
    if lp["read_noise_e"] and not lp["photons_per_frame"]:
        raise ConfigError("loop.read_noise_e", "needs loop.photons_per_frame > 0 (read noise is counted in "
                                               f"photo-electrons), got {lp['read_noise_e']:g} with none")
    if _searches(gain) and lp["gain_steps"] > lp["steps"]:
        raise ConfigError("loop.gain_steps", f"expected at most loop.steps ({lp['steps']}), got {lp['gain_steps']}")
    if not isinstance(methods, list) or not all(isinstance(m, str) for m in methods):
        raise ConfigError("loop.methods", f"expected a list of method names, got {methods!r}")
    methods = tuple(methods)
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods or len(set(methods)) != len(methods):
        raise ConfigError("loop.methods", f"expected distinct methods among {', '.join(METHODS)}, got {list(methods)}")
    if isinstance(gain, dict):
        closed = [m for m in methods if m not in ORACLES]
        if set(gain) != set(closed):
            raise ConfigError("loop.gain", f"a table of gains names every closed loop of loop.methods "
                                           f"({', '.join(closed)}), got {', '.join(gain) or 'none'}")
    d = v["device"]

    def rel(p):
        p = Path(p).expanduser()
        return p if p.is_absolute() else path.parent / p

    for k in ("design", "sensor", "turbulence"):
        if not rel(d[k]).exists():
            raise ConfigError(f"device.{k}", f"{rel(d[k])}: no such file")
    model = rel(d["model"]) if d["model"] else None
    if model is None and {"unet", "refine", "refine_warm"} & set(methods):
        raise ConfigError("device.model", "the unet, refine and refine_warm methods need a model")
    if model is not None and not model.exists():
        raise ConfigError("device.model", f"{model}: no such file")
    if model is not None and "refine_warm" in methods and not is_refiner(model):
        raise ConfigError("device.model", f"{model}: the refine_warm method needs a refiner (a U-Net with its "
                          "learned refinement), not a U-Net")
    realtime = rel(d["realtime"]) if d["realtime"] else None
    if realtime is None and set(REALTIME) & set(methods):
        raise ConfigError("device.realtime", f"the {', '.join(REALTIME)} methods need a real-time model (a modal "
                                             "network)")
    if realtime is not None and not realtime.exists():
        raise ConfigError("device.realtime", f"{realtime}: no such file")
    if wind is not None and not isinstance(wind, dict):
        raise ConfigError("wind", "expected a [wind] table")
    wind = dict(wind or {"speed_m_s": 0.0})  # no [wind]: the turbulence stands still
    sc = load_scenario(rel(d["turbulence"]))
    wind_from_dict({"wind": wind}, sc, str(path))  # its values checked now
    dm = dict(v["dm"])
    influence = dm.pop("influence")
    influence = rel(influence) if influence else None
    if influence is not None:
        if dm["kind"] != "zonal":
            raise ConfigError("dm.influence", f'measured influence functions are a zonal mirror\'s (dm.kind = '
                              f'"zonal"), got dm.kind = "{dm["kind"]}"')
        if not influence.is_file():
            raise ConfigError("dm.influence", f"{influence}: no such file")
        load_influence(influence, received_crop(sc)[1])  # its shape and values checked now
    section = LoopSection(**{k: lp[k] for k in ("rate_hz", "steps", "substeps", "rytov", "leak",
                                                "noise_percent", "readout_frames", "dm_frames", "seed",
                                                "threshold_db", "seeds", "gain_steps", "pseudo_open_loop",
                                                "photons_per_frame", "read_noise_e", "retrieval_budget_ms")},
                          gain=gain, methods=methods, latency_ms=_latencies(latency, methods, str(path)),
                          sh_lenslets=lenslets)
    dm_section = DMSection(**{k: dm[k] for k in ("kind", "modes", "actuators", "coupling", "regularisation",
                                                 "tip_tilt")}, stroke_m=dm["stroke_um"],
                           influence_sha256=file_key(influence) if influence is not None else None)
    return LoopRecipe(path.stem, path, rel(d["design"]), rel(d["sensor"]), rel(d["turbulence"]), model, section,
                      dm_section, wind, realtime, influence)

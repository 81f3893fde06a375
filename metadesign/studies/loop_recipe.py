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
    gain = 0.4                    # or "optimise": chosen per closed loop (see gain_steps)
    gain_steps = 100              # "optimise": the steps of each trial run (the first seed's first frames)
    pseudo_open_loop = false      # the controller integrates the residual's fit plus the mirror's commands
    seeds = 1                     # independent turbulence realisations (each method runs on every one)
    leak = 0.99
    noise_percent = 5.0
    readout_frames = 0.0
    dm_frames = 0.0
    latency_ms = {}               # per method; a method not named: measured on this machine
    methods = ["unet", "refine", "shack_hartmann", "ideal", "fitted", "conjugate", "open"]
    seed = 0
    threshold_db = 3.0

    [dm]
    actuators = 12                # across the receiver aperture
    coupling = 0.15
    regularisation = 1e-3

    [wind]                        # the turbulence's motion (metadesign.turbulence.frozen)
    speed_m_s = 5.0
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..config import Param, Section, load_toml, parse
from ..turbulence.scenario import load_scenario, wind_from_dict
from ..validation import ConfigError

__all__ = ["LoopRecipe", "LoopSection", "DMSection", "METHODS", "DEFAULT_METHODS", "OPTIMISE", "load_loop_recipe",
           "loop_recipe_of", "SECTIONS"]

#: the value of ``[loop] gain`` that has the study choose each closed loop's gain
OPTIMISE = "optimise"
#: the loop's methods: closed loops (a sensor and its reconstruction) and the references
METHODS = ("unet", "refine", "shack_hartmann", "ideal", "fitted", "conjugate", "open", "linear", "realtime")
#: the methods of a recipe that names none (``linear``, the push-pull linear reconstructor, and ``realtime``, the
#: real-time modal network of ``[device] realtime`` (issue #51), on request)
DEFAULT_METHODS = tuple(m for m in METHODS if m not in ("linear", "realtime"))

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
        Param("readout_frames", float, 0.0, lo=0, hi=1000),
        Param("dm_frames", float, 0.0, lo=0, hi=1000),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
        Param("threshold_db", float, 3.0, lo=0, open_lo=True, hi=60),
    ), optional=True),
    Section("dm", (
        Param("kind", str, "zonal", choices=("zonal", "modal"),
              help="zonal: Gaussian influence functions on an actuator grid; modal: Zernike modes Noll 2..modes+1"),
        Param("modes", int, 20, lo=2, hi=300),
        Param("actuators", int, 12, lo=2, hi=256),
        Param("coupling", float, 0.15, lo=0, open_lo=True, hi=0.9),
        Param("regularisation", float, 1e-3, lo=0, hi=1e6),
    ), optional=True),
)


@dataclass(frozen=True)
class LoopSection:
    rate_hz: float
    steps: int
    substeps: int
    rytov: float
    gain: float
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

    @property
    def optimise_gain(self) -> bool:
        """Whether each closed loop's gain is chosen (``gain = "optimise"``) rather than given."""
        return self.gain == OPTIMISE


@dataclass(frozen=True)
class DMSection:
    kind: str
    modes: int
    actuators: int
    coupling: float
    regularisation: float


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


def _gain(raw):
    if raw is None:
        return 0.4
    if raw == OPTIMISE:
        return OPTIMISE
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not (0 <= float(raw) <= 2):
        raise ConfigError("loop.gain", f'expected a number in [0, 2] or "{OPTIMISE}", got {raw!r}')
    return float(raw)


def load_loop_recipe(path: str | Path) -> LoopRecipe:
    """The loop recipe at ``path``, validated (one line naming the field on the first problem)."""
    return loop_recipe_of(load_toml(path), path)


def loop_recipe_of(raw: dict, path: str | Path) -> LoopRecipe:
    """The loop recipe of a parsed TOML document ``raw`` read from ``path`` (its paths relative to it),
    validated as :func:`load_loop_recipe` does (a recipe that extends this one, e.g. the loop map's, passes
    what remains once it has taken its own sections)."""
    path = Path(path)
    raw = {k: dict(v) if isinstance(v, dict) else v for k, v in raw.items()}
    loop = raw.get("loop") if isinstance(raw.get("loop"), dict) else {}
    latency, methods = loop.pop("latency_ms", None), loop.pop("methods", list(DEFAULT_METHODS))
    gain = loop.pop("gain", None)
    wind = raw.pop("wind", None)
    v = parse(raw, SECTIONS, str(path))
    lp = v["loop"]
    gain = _gain(gain)
    if gain == OPTIMISE and lp["gain_steps"] > lp["steps"]:
        raise ConfigError("loop.gain_steps", f"expected at most loop.steps ({lp['steps']}), got {lp['gain_steps']}")
    if not isinstance(methods, list) or not all(isinstance(m, str) for m in methods):
        raise ConfigError("loop.methods", f"expected a list of method names, got {methods!r}")
    methods = tuple(methods)
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods or len(set(methods)) != len(methods):
        raise ConfigError("loop.methods", f"expected distinct methods among {', '.join(METHODS)}, got {list(methods)}")
    d = v["device"]

    def rel(p):
        p = Path(p).expanduser()
        return p if p.is_absolute() else path.parent / p

    for k in ("design", "sensor", "turbulence"):
        if not rel(d[k]).exists():
            raise ConfigError(f"device.{k}", f"{rel(d[k])}: no such file")
    model = rel(d["model"]) if d["model"] else None
    if model is None and {"unet", "refine"} & set(methods):
        raise ConfigError("device.model", "the unet and refine methods need a model")
    if model is not None and not model.exists():
        raise ConfigError("device.model", f"{model}: no such file")
    realtime = rel(d["realtime"]) if d["realtime"] else None
    if realtime is None and "realtime" in methods:
        raise ConfigError("device.realtime", "the realtime method needs a real-time model (a modal network)")
    if realtime is not None and not realtime.exists():
        raise ConfigError("device.realtime", f"{realtime}: no such file")
    if wind is not None and not isinstance(wind, dict):
        raise ConfigError("wind", "expected a [wind] table")
    wind = dict(wind or {"speed_m_s": 0.0})  # no [wind]: the turbulence stands still
    wind_from_dict({"wind": wind}, load_scenario(rel(d["turbulence"])), str(path))  # its values checked now
    section = LoopSection(**{k: lp[k] for k in ("rate_hz", "steps", "substeps", "rytov", "leak",
                                                "noise_percent", "readout_frames", "dm_frames", "seed",
                                                "threshold_db", "seeds", "gain_steps", "pseudo_open_loop")},
                          gain=gain, methods=methods, latency_ms=_latencies(latency, methods, str(path)))
    return LoopRecipe(path.stem, path, rel(d["design"]), rel(d["sensor"]), rel(d["turbulence"]), model, section,
                      DMSection(**v["dm"]), wind, realtime)

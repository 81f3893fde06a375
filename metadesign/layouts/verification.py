"""One entry point for checking a written layout against its design: :func:`verify` chooses the method,
runs it and returns one report type, :class:`VerifyReport`, whatever the method.

The methods (each the function behind it, kept as it was):

* ``"readback"`` (:func:`~.reader.read_layout` + :func:`~.reader.verify_against_design` +
  :func:`~.reader.drc_check`): every pillar read back with gdstk (and with KLayout too, with
  ``options.klayout``), compared exactly with the design; the design rules on the atom table and on a
  KLayout window.  The layout's whole index map sits in memory: the method of a whole-array layout.
* ``"tiled"`` (:func:`~.reader.verify_tiled`): for a tiled layout, KLayout counts every pillar per atom
  through the hierarchy and ``options.sample_tiles`` seeded tiles are compared pillar by pillar.
  KLayout holds the whole file: about :data:`KLAYOUT_BYTES_PER_PILLAR` bytes a pillar.
* ``"stream"`` (:func:`~.stream.verify_stream`): the file read once in the memory of a stripe of tiles,
  every pillar, record, signature and neighbour pair checked.

``"auto"`` (the default) takes ``"readback"`` for a whole-array layout, and for a tiled one ``"tiled"``
while KLayout's read fits in the available memory, else ``"stream"`` (the 2.5 cm device: 1.28e9 pillars,
about 11.7 GB through KLayout; streamed in about 1 GB).  :func:`choose_method` makes that choice (and says
why) before any work, after the cheap checks of the path (one-line InputErrors: a folder, a file of
another format, ``"stream"`` on a GDSII file)."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from ..design.store import design_file, load_design
from ..execution import SERIAL, Execution
from ..validation import MEMORY_FRACTION, InputError, available_memory
from .reader import (drc_check, layout_format, layout_tiling, read_layout, read_layout_klayout, verify_against_design,
                     verify_tiled)
from .rules import DESIGN_RULES, DesignRules
from .stream import verify_stream

__all__ = ["METHODS", "VerifyOptions", "VerifyReport", "MethodChoice", "choose_method", "verify",
           "klayout_memory", "KLAYOUT_BYTES_PER_PILLAR"]

#: the methods :func:`verify` knows ("auto" chooses among the other three)
METHODS = ("auto", "readback", "tiled", "stream")
#: peak memory of KLayout's read of a tiled layout, per pillar, and its base (measured with
#: benchmarks/bench_tiled.py, docs/guide/layout.md: 2.5 cm, 1.28e9 pillars, 11.3 GB; 5 mm, 5.1e7, 0.64 GB)
KLAYOUT_BYTES_PER_PILLAR = 9.0
KLAYOUT_BASE_BYTES = 0.2e9
#: OASIS bytes per pillar of a tiled layout, the smaller measured (2.5 cm: 0.40): the most pillars a file
#: of a given size may hold, where its side-car does not say
_MIN_OASIS_BYTES_PER_PILLAR = 0.4


@dataclass(frozen=True)
class VerifyOptions:
    """The options of one method: ``sample_tiles`` and ``seed`` (``"tiled"``: how many tiles are compared
    pillar by pillar, drawn with which seed; None: 8), ``tile`` (``"stream"``: cells per tile side; None: the
    side-car's), ``klayout`` (``"readback"``: read the file with KLayout too and compare)."""

    sample_tiles: int | None = None
    seed: int = 0
    tile: int | None = None
    klayout: bool = False


class MethodChoice(NamedTuple):
    """The method :func:`verify` runs and why (one line)."""

    method: str
    reason: str


@dataclass
class VerifyReport:
    """What :func:`verify` found, whatever the method: ``passed`` (every pillar checked as designed, the
    design rules met), ``pillars`` (in the layout, as the method counted them), ``pillars_design``,
    ``pillars_checked`` (compared one by one with the design), ``drc`` (the method's design-rule report,
    ``passed`` in it), ``seconds``, and ``details``: the method's own report."""

    method: str
    reason: str
    file: str
    design: str | None
    passed: bool
    pillars: int
    pillars_design: int
    pillars_checked: int
    drc: dict
    seconds: float
    rules: DesignRules = DESIGN_RULES
    details: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """The report as JSON (``--json``): the method's own report with the common fields over it."""
        return {**self.details, "method": self.method, "method_reason": self.reason, "file": self.file,
                "passed": self.passed, "pillars_checked": self.pillars_checked, "drc": self.drc,
                "seconds": self.seconds}


def klayout_memory(path: Path) -> float:
    """Bytes KLayout's read of the tiled layout ``path`` needs at its peak (its pillar count from the
    side-car, else the most a file of its size holds)."""
    try:
        pillars = float(json.loads(path.with_suffix(path.suffix + ".json").read_text())["pillars"])
    except (OSError, ValueError, KeyError, TypeError):
        pillars = path.stat().st_size / _MIN_OASIS_BYTES_PER_PILLAR
    return KLAYOUT_BASE_BYTES + KLAYOUT_BYTES_PER_PILLAR * pillars


def _gb(b: float) -> str:
    return f"{b / 1e9:.1f} GB"


def choose_method(path: str | Path, method: str = "auto", options: VerifyOptions = VerifyOptions()) -> MethodChoice:
    """The method :func:`verify` runs on ``path`` and why, after the checks that need no reading (one-line
    InputErrors): the path is a file, OASIS or GDSII by its first bytes, OASIS for ``"stream"``."""
    path = Path(path)
    if method not in METHODS:
        raise InputError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    fmt = layout_format(path)
    if method == "stream" and fmt != "oas":
        raise InputError(f"{path}: a GDSII file; the streaming verifier reads the OASIS files `layout tiled` "
                         "writes")
    if method != "auto":
        return MethodChoice(method, "asked for")
    if options.sample_tiles is not None:
        return MethodChoice("tiled", "sampled tiles asked for")
    tiling = layout_tiling(path)
    if not tiling or tiling.get("hierarchy") != "tiles":
        return MethodChoice("readback", "a whole-array layout: every pillar read back (gdstk) and compared "
                            "with the design")
    need, have = klayout_memory(path), available_memory() * MEMORY_FRACTION
    if need > have:
        return MethodChoice("stream", f"a tiled layout whose KLayout read would need about {_gb(need)}, more "
                            f"than the {_gb(have)} available: every pillar streamed in bounded memory instead")
    return MethodChoice("tiled", f"a tiled layout: KLayout counts every pillar (about {_gb(need)} of the "
                        f"{_gb(have)} available) and sampled tiles are compared pillar by pillar (--stream: "
                        "every pillar)")


def _design_beside(path: Path, design: str | Path | None) -> Path:
    """The design a tiled layout is verified against: ``design``, else the design.npz beside it."""
    found = design_file(design if design else path.parent)
    if not found.exists():
        raise InputError(f"{path}: no design.npz beside it; pass --design DESIGN")
    return found


def _readback(path: Path, design, rules: DesignRules, options: VerifyOptions) -> tuple[dict, str]:
    """Every pillar read back (gdstk; KLayout too with ``options.klayout``) against the design, and the
    design rules: the report and the design's path."""
    lc = read_layout(path)
    if not design and not (path.parent / "design.npz").exists():
        raise InputError(f"{path}: no design.npz beside it; pass --design DESIGN")
    src = design_file(design) if design else path.parent / "design.npz"
    d = load_design(src)
    grid = int(lc.provenance.get("grid_nm", 1)) if "grid_nm" in lc.provenance else 1
    rep = {"file": str(path), "gdstk": verify_against_design(lc, d, grid)}
    if options.klayout:
        rep["klayout"] = verify_against_design(read_layout_klayout(path), d, grid)
    rep["drc"] = drc_check(lc, rules.min_feature_nm, rules.min_gap_nm, rules.window_cells)
    rep["passed"] = bool(rep["gdstk"]["exact"] and rep["drc"]["passed"]
                         and rep.get("klayout", {"exact": True})["exact"])
    return rep, str(src)


def _run(choice: MethodChoice, path: Path, design, rules: DesignRules, options: VerifyOptions,
         run: Execution) -> tuple[dict, str, tuple[int, int, int]]:
    """The chosen method's report, the design it read, and ``(pillars, pillars_design, pillars_checked)``."""
    if choice.method == "readback":
        rep, src = _readback(path, design, rules, options)
        g = rep["gdstk"]
        return rep, src, (g["pillars"], g["expected"], g["pillars"])
    src = _design_beside(path, design)
    if choice.method == "tiled":
        sample = 8 if options.sample_tiles is None else options.sample_tiles
        rep = verify_tiled(path, src, sample, options.seed, rules, run)
        rep["passed"] = bool(rep["exact"] and rep["drc"]["passed"])
        return rep, str(src), (rep["pillars_klayout"], rep["pillars_design"], rep["sampled_pillars"])
    rep = verify_stream(path, src, rules, options.tile, run)
    rep["passed"] = bool(rep["exact"] and rep["drc"]["passed"])
    return rep, str(src), (rep["pillars"], rep["pillars_design"], rep["pillars"])


def verify(path: str | Path, design: str | Path | None = None, method: str | MethodChoice = "auto",
           rules: DesignRules = DESIGN_RULES, options: VerifyOptions = VerifyOptions(),
           run: Execution = SERIAL) -> VerifyReport:
    """Check the layout ``path`` against ``design`` (a design folder or ``design.npz``; None: the one beside
    the layout) under ``rules``, by ``method`` (see the module's docstring; a :class:`MethodChoice` from
    :func:`choose_method` is run as it is): one :class:`VerifyReport`.  ``run``: the stream method's
    workers or Dask scheduler, the progress of the tiled and stream methods, and ``log``, which gets the
    line saying which method runs and why before the work starts."""
    path = Path(path)
    choice = method if isinstance(method, MethodChoice) else choose_method(path, method, options)
    run.log(f"layout verify: {choice.method} ({choice.reason})")
    t0 = time.perf_counter()
    rep, src, (pillars, pillars_design, checked) = _run(choice, path, design, rules, options, run)
    return VerifyReport(choice.method, choice.reason, str(path), src, rep["passed"], int(pillars),
                        int(pillars_design), int(checked), rep["drc"], time.perf_counter() - t0, rules, rep)

"""Shared pieces of the stage CLIs: a parser whose errors are one line,
typed option checks (the same checks as the recipe schema), output-path
checks done before any work, progress bars and JSON-safe summaries."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from .validation import ConfigError, ValidationError, check_int, check_number

__all__ = ["limit_arg", "Parser", "num", "integer", "emit", "progress_bar", "log_to", "out_dir", "out_file", "MAX_WORKERS",
           "json_safe", "workers_arg"]

#: cap on worker processes (-j): more than this is a typo, not a cluster
MAX_WORKERS = max(8, 4 * (os.cpu_count() or 1))


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``metadesign: error: ...`` and exit 2."""

    def error(self, message: str):  # noqa: D401 - argparse API
        print(f"metadesign: error: {self.prog.split(' ', 1)[-1]}: {message}" if " " in self.prog
              else f"metadesign: error: {message}", file=sys.stderr)
        sys.exit(2)


def num(lo=None, hi=None, open_lo=False, open_hi=False, unit: str = ""):
    """argparse ``type=`` for a finite float within bounds (same rule as recipes)."""

    def conv(s: str) -> float:
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
        try:
            return check_number("value", v, lo, hi, open_lo, open_hi, unit)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("value: ")) from None

    conv.__name__ = "number"
    conv.metadesign_numeric = True
    return conv


def integer(lo=None, hi=None):
    """argparse ``type=`` for an integer within bounds."""

    def conv(s: str) -> int:
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
        try:
            return check_int("value", v, lo, hi)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix("value: ")) from None

    conv.__name__ = "integer"
    conv.metadesign_numeric = True
    return conv


#: seeds: what numpy.random.SeedSequence accepts, bounded for JSON/zarr storage
SEED = integer(0, 2**63 - 1)


def limit_arg(p: argparse.ArgumentParser, help: str, **kw) -> None:
    """``--limit N``: at most N samples of an existing split (dest ``samples``).  ``--samples`` has one meaning
    everywhere, how many samples to make (``dataset build``, ``turbulence validate``): given here it is one
    line naming ``--limit``."""
    p.add_argument("--limit", dest="samples", metavar="N", help=help, **kw)
    p.add_argument("--samples", nargs=1, action=_Renamed, help=argparse.SUPPRESS)


class _Renamed(argparse.Action):
    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string} means how many samples to make (dataset build, turbulence validate); "
                     "for at most N samples of an existing split use --limit N")


def workers_arg(p: argparse.ArgumentParser, default: int | None = None, what: str = "worker processes") -> None:
    p.add_argument("-j", "--workers", type=integer(1, MAX_WORKERS), default=default or min(2, os.cpu_count() or 1),
                   help=f"{what}, one thread each (default: 2; at most {MAX_WORKERS})")


def json_safe(obj):
    """Replace NaN/inf by None (strict JSON), numpy scalars/arrays by Python values."""
    import numpy as np

    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def emit(obj: dict, as_json: bool, text: str) -> None:
    if as_json:
        print(json.dumps(json_safe(obj), indent=2, sort_keys=True, allow_nan=False))
    else:
        print(text)


#: seconds between progress lines when the output is not a terminal (a log file, CI); env override
PROGRESS_SECONDS = float(os.environ.get("METADESIGN_PROGRESS_SECONDS", "30"))


def plural(unit: str) -> str:
    """English plural of a progress unit (cell -> cells, patch -> patches)."""
    return unit + ("es" if unit.endswith(("s", "sh", "ch", "x")) else "s")


def progress_bar(desc: str, unit: str = "cell", stream=None, interval: float | None = None, clock=time.monotonic):
    """A progress callback ``(done, total)``: a tqdm bar on a terminal; elsewhere (a log file, CI, where
    tqdm turns itself off) one line every ``interval`` seconds with the rate and the time left, and a last
    line at the end of a run that printed any (short runs stay silent)."""
    stream = sys.stderr if stream is None else stream
    interval = PROGRESS_SECONDS if interval is None else interval
    state: dict = {}
    if getattr(stream, "isatty", lambda: False)():
        from tqdm import tqdm

        def bar_cb(done: int, total: int) -> None:
            bar = state.get("bar")
            if bar is None:
                bar = state["bar"] = tqdm(total=total, desc=desc, unit=unit, file=stream, dynamic_ncols=True)
            bar.n = done
            bar.refresh()
            if done >= total:
                bar.close()

        return bar_cb

    def log_cb(done: int, total: int) -> None:
        now = clock()
        if "t0" not in state:
            state.update(t0=now, last=now, printed=False)
        final = done >= total
        if now - state["last"] < interval and not (final and state["printed"]):
            return
        if final and state.get("closed"):
            return
        el = now - state["t0"]
        rate = done / el if el > 0 else 0.0
        eta = (total - done) / rate if rate > 0 else float("inf")
        left = "done" if final else (f"about {_duration(eta)} left" if eta != float("inf") else "")
        units = plural(unit)
        print(f"{desc}: {done}/{total} {units} ({100 * done / max(total, 1):.0f} %), {_duration(el)} elapsed"
              + (f", {rate:.3g} {units}/s" if rate else "") + (f"; {left}" if left else ""), file=stream, flush=True)
        state.update(last=now, printed=True, closed=final)

    return log_cb


def _duration(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else (f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h")


def log_to(quiet: bool):
    return (lambda s: None) if quiet else (lambda s: print(s, file=sys.stderr))


def _parent_ok(path: Path, what: str) -> None:
    parent = path.resolve().parent
    if not parent.is_dir():
        raise ValidationError(f"{what} {path}: folder {path.parent} does not exist (create it first)")
    if not os.access(parent, os.W_OK):
        raise ValidationError(f"{what} {path}: folder {path.parent} is not writable")


def out_dir(path: str | Path, what: str = "-o/--output") -> Path:
    """An output folder: may exist (as a folder); its parent must exist. Checked before work."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValidationError(f"{what} {path}: exists and is not a folder")
    _parent_ok(path, what)
    return path


def out_file(path: str | Path, what: str = "-o/--output", suffixes: tuple[str, ...] = ()) -> Path:
    """An output file: not a folder; its parent must exist. Checked before work."""
    path = Path(path)
    if path.is_dir():
        raise ValidationError(f"{what} {path}: is a folder, expected a file path")
    if suffixes and path.suffix.lower() not in suffixes:
        raise ValidationError(f"{what} {path}: expected a file ending in {' or '.join(suffixes)}")
    _parent_ok(path, what)
    return path

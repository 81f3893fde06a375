"""One validation layer for the whole package.

Every spec dataclass (``Perturbation``, ``NoiseSpec``, ``SensorSpec``,
``Scenario``, ...) checks its invariants in ``__post_init__`` with the helpers
below, and every recipe field and CLI option goes through the same checks.
A problem raises :class:`ValidationError` (a :class:`ValueError`), whose
message is one line naming the field and what is allowed; the CLI prints it
as ``metadesign: error: ...`` and exits with status 2 before writing
anything.  Core code raises nothing else for bad input.  NaN and infinity are
bad values everywhere.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["ValidationError", "InputError", "ConfigError", "check_number", "check_int", "check_finite_array", "describe_range",
           "check_memory", "available_memory", "MEMORY_FRACTION"]


class ValidationError(ValueError):
    """A user-facing input problem: one line, exit status 2 at the CLI."""


class InputError(ValidationError):
    """An input file or folder that cannot be used: missing, of the wrong kind, damaged, or an output that
    would overwrite what metadesign did not write."""


class ConfigError(ValidationError):
    """A named field (recipe key or option) is missing, unknown, mistyped or out of range."""

    def __init__(self, where: str, message: str):
        self.field = where
        super().__init__(f"{where}: {message}")


def _a(word: str) -> str:
    return ("an " if word[0] in "aeiou" else "a ") + word


def describe_range(lo=None, hi=None, open_lo=False, open_hi=False, unit: str = "", kind: str = "number") -> str:
    if lo is None and hi is None:
        return f"a finite {kind}" + (f" ({unit})" if unit else "")
    if hi is None:
        s = f"{_a(kind)} {'>' if open_lo else '>='} {lo:g}"
    elif lo is None:
        s = f"{_a(kind)} {'<' if open_hi else '<='} {hi:g}"
    else:
        s = f"{_a(kind)} in {'(' if open_lo else '['}{lo:g}, {hi:g}{')' if open_hi else ']'}"
    return s + (f" {unit}" if unit else "")


def check_number(name: str, v: Any, lo=None, hi=None, open_lo=False, open_hi=False, unit: str = "") -> float:
    """``v`` as a float, finite and within the bounds, else :class:`ConfigError` naming ``name``."""
    allowed = describe_range(lo, hi, open_lo, open_hi, unit)
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ConfigError(name, f"expected {allowed}, got {v!r}")
    v = float(v)
    if not math.isfinite(v) or (lo is not None and (v <= lo if open_lo else v < lo)) or \
            (hi is not None and (v >= hi if open_hi else v > hi)):
        raise ConfigError(name, f"expected {allowed}, got {v!r}")
    return v


def check_int(name: str, v: Any, lo=None, hi=None) -> int:
    allowed = describe_range(lo, hi, kind="integer")
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        raise ConfigError(name, f"expected {allowed}, got {v!r}")
    v = int(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ConfigError(name, f"expected {allowed}, got {v!r}")
    return v


def check_finite_array(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind not in "fciub":
        raise ValidationError(f"{name}: expected a numeric array, got dtype {a.dtype}")
    if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        raise ValidationError(f"{name}: contains NaN or infinite values")
    return a


#: share of the machine's available memory a job may plan to use
MEMORY_FRACTION = 0.8


def available_memory() -> int:
    """Bytes of memory available to a new allocation (MemAvailable; total RAM as fallback)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import os

        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def check_memory(what: str, needed_bytes: float, hint: str) -> None:
    """Refuse work whose planned peak memory exceeds what the machine has."""
    have = available_memory() * MEMORY_FRACTION
    if needed_bytes > have:
        raise ValidationError(f"{what} needs about {needed_bytes / 2**30:.1f} GiB of memory, "
                              f"{have / 2**30:.1f} GiB is available: {hint}")

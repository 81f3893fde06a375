"""Recipe (TOML) validation at the edge.

A recipe is parsed against a schema of :class:`Param` entries grouped in
sections.  Every problem raises :class:`ConfigError` whose message is one line
naming the field (``section.key``) and what is allowed; the CLI prints it and
exits with status 2 before anything is written.  Values carry their unit in
the key (``period_um``) and are converted to SI once, here.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from .validation import ConfigError, InputError, ValidationError

__all__ = ["ConfigError", "InputError", "ValidationError", "Param", "Section", "parse", "load_toml", "UNIT_SCALE"]

#: SI scale factors of the unit suffixes used in recipe keys.
UNIT_SCALE = {
    "nm": 1e-9,
    "um": 1e-6,
    "mm": 1e-3,
    "cm": 1e-2,
    "m": 1.0,
    "km": 1e3,
    "rad": 1.0,
    "percent": 1.0,  # a percentage stays one: every noise level in the code is % of the peak, as named
}

_REQUIRED = object()





@dataclass(frozen=True)
class Param:
    """One recipe key.

    ``kind`` is ``float``, ``int``, ``str``, ``bool`` or ``list`` (a list of
    floats, or of float pairs with ``pairs=True``).  ``lo``/``hi`` bound the
    value in the recipe's own unit; ``open_lo``/``open_hi`` make the bound
    strict.  The unit is taken from the key's suffix (``_um`` ...).
    """

    key: str
    kind: type = float
    default: Any = _REQUIRED
    lo: float | None = None
    hi: float | None = None
    open_lo: bool = False
    open_hi: bool = False
    choices: Sequence[str] | None = None
    pairs: bool = False
    rows: bool = False  # a list kind whose items are rows (lists) of numbers, of any length
    span: bool = False  # a float kind that also takes a range [lo, hi]: the value is always (lo, hi)
    help: str = ""

    @property
    def unit(self) -> str | None:
        suffix = self.key.rsplit("_", 1)[-1]
        return suffix if suffix in UNIT_SCALE and "_" in self.key else None

    @property
    def scale(self) -> float:
        return UNIT_SCALE[self.unit] if self.unit else 1.0

    def allowed(self) -> str:
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        lo = "(" if self.open_lo else "["
        hi = ")" if self.open_hi else "]"
        a = "-inf" if self.lo is None else f"{self.lo:g}"
        b = "inf" if self.hi is None else f"{self.hi:g}"
        unit = f" {self.unit}" if self.unit else ""
        if self.lo is None and self.hi is None:
            return f"a {self.kind.__name__}"
        one = f"a {self.kind.__name__} in {lo}{a}, {b}{hi}{unit}"
        return one + " or a range [lo, hi] of them" if self.span else one


@dataclass(frozen=True)
class Section:
    name: str
    params: tuple[Param, ...]
    optional: bool = False
    help: str = ""
    extra: dict = field(default_factory=dict)


def _check_number(where: str, p: Param, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(where, f"expected {p.allowed()}, got {type(v).__name__} {v!r}")
    if p.kind is int and not isinstance(v, int):
        raise ConfigError(where, f"expected {p.allowed()}, got {v!r}")
    if not math.isfinite(v):
        raise ConfigError(where, f"expected {p.allowed()}, got {v!r}")
    bad_lo = p.lo is not None and (v <= p.lo if p.open_lo else v < p.lo)
    bad_hi = p.hi is not None and (v >= p.hi if p.open_hi else v > p.hi)
    if bad_lo or bad_hi:
        raise ConfigError(where, f"expected {p.allowed()}, got {v!r}")
    return v


def _convert(where: str, p: Param, v: Any) -> Any:
    if p.span:
        if not isinstance(v, list):
            x = _check_number(where, p, v) * p.scale
            return (x, x)
        if len(v) != 2:
            raise ConfigError(where, f"expected {p.allowed()}, got {v!r}")
        lo, hi = (_check_number(f"{where}[{i}]", p, x) * p.scale for i, x in enumerate(v))
        if lo > hi:
            raise ConfigError(where, f"expected a range [lo, hi] with lo <= hi, got {v!r}")
        return (lo, hi)
    if p.kind in (float, int):
        v = _check_number(where, p, v)
        return v * p.scale if p.kind is float else int(v)
    if p.kind is bool:
        if not isinstance(v, bool):
            raise ConfigError(where, f"expected true or false, got {v!r}")
        return v
    if p.kind is str:
        if not isinstance(v, str):
            raise ConfigError(where, f"expected a string, got {v!r}")
        if p.choices and v not in p.choices:
            raise ConfigError(where, f"expected {p.allowed()}, got {v!r}")
        return v
    if p.kind is list:
        if not isinstance(v, list):
            raise ConfigError(where, f"expected a list, got {v!r}")
        out = []
        for i, item in enumerate(v):
            w = f"{where}[{i}]"
            if p.pairs:
                if not isinstance(item, list) or len(item) != 2:
                    raise ConfigError(w, f"expected a pair [a, b], got {item!r}")
                out.append(tuple(_check_number(w, p, x) * p.scale for x in item))
            elif p.rows:
                if not isinstance(item, list):
                    raise ConfigError(w, f"expected a row [a, b, ...], got {item!r}")
                out.append(tuple(_check_number(f"{w}[{j}]", p, x) * p.scale for j, x in enumerate(item)))
            else:
                out.append(_check_number(w, p, item) * p.scale)
        return tuple(out)
    raise TypeError(p.kind)  # pragma: no cover - schema bug


def parse(data: Mapping[str, Any], sections: Sequence[Section], source: str = "recipe") -> dict:
    """Validate ``data`` (a parsed TOML document) against ``sections``.

    Returns ``{section: {key_without_unit_or_with: SI value}}`` keyed by the
    recipe key.  Raises :class:`ConfigError` on the first problem.
    """
    known = {s.name: s for s in sections}
    for name in data:
        if name not in known:
            allowed = ", ".join(f"[{s}]" for s in known)
            raise ConfigError(name, f"unknown section in {source}; allowed: {allowed}")
    out: dict[str, dict[str, Any]] = {}
    for sec in sections:
        raw = data.get(sec.name)
        if raw is None:
            if not sec.optional and any(p.default is _REQUIRED for p in sec.params):
                raise ConfigError(f"[{sec.name}]", f"missing section in {source}")
            raw = {}
        if not isinstance(raw, Mapping):
            raise ConfigError(sec.name, "expected a table")
        keys = {p.key: p for p in sec.params}
        for k in raw:
            if k not in keys:
                allowed = ", ".join(keys)
                raise ConfigError(f"{sec.name}.{k}", f"unknown key; allowed: {allowed}")
        vals = {}
        for p in sec.params:
            where = f"{sec.name}.{p.key}"
            if p.key in raw:
                vals[p.key] = _convert(where, p, raw[p.key])
            elif p.default is _REQUIRED:
                raise ConfigError(where, f"missing; expected {p.allowed()}")
            else:
                # defaults are written in the recipe's own units
                vals[p.key] = None if p.default is None else _convert(where, p, p.default)
        out[sec.name] = vals
    return out


def load_toml(path: str | Path) -> dict:
    """Read a TOML file; unreadable or malformed files raise :class:`InputError`."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such recipe file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read recipe ({exc})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None

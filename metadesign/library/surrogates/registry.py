"""Supercell surrogates by name or model file (a registry in the manner of gdsfactory's ``Pdk.get_component``).

``surrogate("lpa", lib)``, ``surrogate("coupling", lib)`` (alias ``"supercell"``, the device's historic name),
``surrogate("peds", lib, partial=..., run=...)``, or ``surrogate(path, lib)``: a model file whose card's
``format`` says which (``metadesign.coupling/1`` weights and card, ``metadesign.peds/1`` card).  A name
that is none of these, a file of another kind, or a file of the wrong kind for ``kind=`` is one line."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Callable

from ...cards import card_format
from ...validation import ValidationError
from ..coupling import CARD_FORMAT
from ..store import UnitCellLibrary
from .base import SupercellSurrogate

__all__ = ["surrogate", "register_surrogate", "surrogate_names", "canonical_name", "ALIASES"]

#: name -> "module:Class" (imported on first use) or a factory ``(lib, path=None, **options) -> surrogate``
_REGISTRY: dict[str, str | Callable] = {"lpa": "lpa:LPA", "coupling": "net:CouplingNet", "peds": "peds:PEDS"}
#: other spellings of a registered name
ALIASES = {"supercell": "coupling"}
#: a model file's card format -> the registered name that loads it
_FORMATS = {CARD_FORMAT: "coupling", "metadesign.peds/1": "peds"}


def register_surrogate(name: str, factory: str | Callable, formats: tuple[str, ...] = ()) -> None:
    """Register a surrogate under ``name`` (a factory ``(lib, path=None, **options)``, or ``"module:Class"``
    of this package), loading model files of card ``formats``."""
    _REGISTRY[name] = factory
    for f in formats:
        _FORMATS[f] = name


def surrogate_names() -> tuple[str, ...]:
    """The registered names, then the aliases."""
    return (*_REGISTRY, *ALIASES)


def canonical_name(name: str) -> str:
    """The registered name of ``name`` (an alias resolved); one line if it is none."""
    n = ALIASES.get(name, name)
    if n not in _REGISTRY:
        raise ValidationError(f"supercell model {name!r}: expected one of {', '.join(map(repr, surrogate_names()))} "
                              "or a model file")
    return n


def _factory(name: str) -> Callable:
    f = _REGISTRY[name]
    if isinstance(f, str):
        mod, cls = f.split(":")
        f = getattr(importlib.import_module(f"{__package__}.{mod}"), cls)
    return f


def surrogate(name_or_path, lib: UnitCellLibrary, *, kind: str | None = None, **options) -> SupercellSurrogate:
    """The supercell surrogate ``name_or_path`` for library ``lib``: a registered name (an alias included), a
    model file (its card's format picks the kind), or a surrogate already made (returned as it is).
    ``kind``: the name the caller expects (a model file of another kind is refused, one line);
    ``options``: the implementation's (PEDS: ``partial``, ``run``, ``stack``, ``taper``)."""
    want = None if kind is None else canonical_name(kind)
    if isinstance(name_or_path, SupercellSurrogate) and not isinstance(name_or_path, (str, Path)):
        s = name_or_path
        if want is not None and canonical_name(s.name) != want:
            raise ValidationError(f"supercell model: a {s.name} model, not a {want} model")
        return s
    key = str(name_or_path)
    if isinstance(name_or_path, str) and ALIASES.get(key, key) in _REGISTRY:
        name = ALIASES.get(key, key)
        if want is not None and name != want:
            raise ValidationError(f"supercell model {key!r}: not a {want} model")
        return _factory(name)(lib, **options)
    path = Path(name_or_path)
    if not path.exists():
        raise ValidationError(f"supercell model {key!r}: expected one of {', '.join(map(repr, surrogate_names()))} "
                              "or a model file (no such file)")
    fmt = card_format(path, "supercell model")
    name = _FORMATS.get(fmt)
    if name is None:
        raise ValidationError(f"{path}: a {fmt} model, not a supercell model (expected "
                              f"{' or '.join(sorted(_FORMATS))})")
    if want is not None and name != want:
        raise ValidationError(f"{path}: a {name} model ({fmt}), not a {want} model")
    return _factory(name)(lib, path, **options)

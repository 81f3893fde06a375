"""One model card type for every learned model (the U-Net, the refiner, the supercell coupling model).

A model is two files: the weights ``NAME.safetensors`` (tensors only, never pickled; the safetensors
header's metadata names the format) and the card ``NAME.safetensors.json``, a JSON object with at least

* ``format``: ``metadesign.<kind>/<version>`` (the product layer recognises the model by it),
* ``weights``: the weights' file name, ``weights_sha256``: their bytes' sha256 (checked on every load),
* ``trained_on``: what the weights were fitted to (a dataset's path, recipe hash and layout, a supercell
  table's path and sha256),

and whatever the model adds (its architecture, metrics, provenance).  A model whose parameters are a few
numbers (the PEDS supercell model) is its card alone, one JSON file (:func:`save_card`): the same ``format``
and ``trained_on``, the parameters in the card, no ``weights``.  :func:`save_card_model` writes both
atomically; :func:`read_card` and :func:`load_weights` turn every damaged file into one line (a card
that is not a JSON object, of another format, whose sha256 differs from the weights', weights that are
unreadable or hold NaN/infinity).  Coupling models written before the card's name settled carry
``NAME.json``: still read.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable

from .io import atomic_path, atomic_write_text
from .tasks import file_key
from .validation import ValidationError

__all__ = ["card_path", "find_card", "save_card_model", "save_card", "read_card", "card_format", "model_card",
           "has_format", "load_weights", "load_into"]


def card_path(weights: str | Path) -> Path:
    """Where the card of ``weights`` is written: ``NAME.safetensors.json``."""
    w = Path(weights)
    return w.with_name(w.name + ".json")


def find_card(weights: str | Path) -> Path:
    """The card of ``weights`` on disk (``NAME.safetensors.json``, else the older ``NAME.json``)."""
    c = card_path(weights)
    if not c.exists() and Path(weights).with_suffix(".json").exists():
        return Path(weights).with_suffix(".json")
    return c


def save_card_model(path: str | Path, state: dict, fmt: str, card: dict, trained_on: dict | None = None,
                    card_file: Path | None = None) -> tuple[Path, Path]:
    """Write ``state`` (name -> tensor) as ``path`` and its card (see the module's docstring); returns both
    paths.  ``card_file``: where the card goes (default :func:`card_path`)."""
    from safetensors.torch import save_file

    path = Path(path)
    state = {k: v.detach().cpu().contiguous() for k, v in state.items()}
    with atomic_path(path) as tmp:
        save_file(state, str(tmp), metadata={"format": fmt})
    full = {**card, "format": fmt, "weights": path.name, "weights_sha256": file_key(path)}
    if trained_on is not None:
        full["trained_on"] = trained_on
    cp = Path(card_file) if card_file is not None else card_path(path)
    atomic_write_text(cp, json.dumps(full, indent=2, sort_keys=True, default=float))
    return path, cp


def save_card(path: str | Path, fmt: str, card: dict, trained_on: dict | None = None, indent: int = 1) -> Path:
    """Write a model held entirely in its card (no weights file) at ``path``: ``{"format": fmt, **card}`` (the
    keys in ``card``'s order), plus ``trained_on`` when given, as indented JSON, atomically."""
    full = {"format": fmt, **{k: v for k, v in card.items() if k != "format"}}
    if trained_on is not None:
        full["trained_on"] = trained_on
    atomic_write_text(path, json.dumps(full, indent=indent, default=float))
    return Path(path)


def _not_a_folder(path: Path, what: str) -> None:
    """A folder given where a model file is expected: one line."""
    if path.is_dir():
        raise ValidationError(f"{path}: a folder, not a {what} (give the model's file: its weights NAME.safetensors "
                              "with the card beside them, or a card-only model's JSON)")


def _a_card(path: Path, what: str) -> None:
    """A JSON file given as a model that is no model card (another product's JSON): one line."""
    if not path.is_file():
        return
    try:
        card = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError, OSError):
        card = None
    if not (isinstance(card, dict) and isinstance(card.get("format"), str)):
        raise ValidationError(f"{path}: not a metadesign {what} card (a JSON file without a card's format)")


def _card_only(path: Path) -> dict | None:
    """The card of a model held in its card alone (a JSON object without ``weights``) at ``path``, else None."""
    if path.suffix == ".safetensors" or not path.is_file():
        return None
    try:
        card = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError, OSError):
        return None
    return card if isinstance(card, dict) and "weights" not in card and "format" in card else None


def card_format(path: str | Path, what: str = "model") -> str:
    """The ``format`` of the model file at ``path`` (its weights, its card, or a card-only model), unchecked
    otherwise; one-line ValidationError when there is no readable card."""
    path = Path(path)
    _not_a_folder(path, what)
    card = _card_only(path)
    if card is not None:
        return str(card["format"])
    w = path
    if path.suffix == ".json":
        w = path.with_suffix("") if path.with_suffix("").suffix == ".safetensors" else path.with_suffix(".safetensors")
    cp = find_card(w)
    try:
        card = json.loads(cp.read_text())
    except (ValueError, UnicodeDecodeError, OSError):
        card = None
    if not isinstance(card, dict) or not isinstance(card.get("format"), str):
        raise ValidationError(f"{path}: not a metadesign {what} (no readable card: neither a JSON model card nor "
                              f"weights with {card_path(w).name} beside them)")
    return card["format"]


def read_card(path: str | Path, formats: str | Iterable[str], what: str = "model") -> tuple[Path, Path, dict]:
    """``(weights, card file, card)`` of the model at ``path`` (the weights or the card), its card checked:
    a JSON object of one of ``formats`` whose sha256 is the weights'.  A model held in its card alone
    (:func:`save_card`): ``(path, path, card)``, its format checked.  One-line ValidationError else."""
    formats = (formats,) if isinstance(formats, str) else tuple(formats)
    path = Path(path)
    _not_a_folder(path, what)
    card = _card_only(path)
    if card is not None:
        if card.get("format") not in formats:
            raise ValidationError(f"{path}: not a metadesign {what} (format {card.get('format')!r}, expected "
                                  f"{' or '.join(formats)})")
        return path, path, card
    if path.suffix == ".json":
        _a_card(path, what)
        path = path.with_suffix("") if path.with_suffix("").suffix == ".safetensors" else \
            path.with_suffix(".safetensors")
    cp = find_card(path)
    if not path.is_file() or not cp.is_file():
        raise ValidationError(f"{path}: no such {what} (expected the weights and {card_path(path).name} beside them)")
    try:
        card = json.loads(cp.read_text())
    except (ValueError, UnicodeDecodeError, OSError) as exc:
        raise ValidationError(f"{cp}: not a metadesign {what} card (not JSON: {exc})") from None
    if not isinstance(card, dict):
        raise ValidationError(f"{cp}: not a metadesign {what} card (a JSON {type(card).__name__}, not an object)")
    if card.get("format") not in formats:
        raise ValidationError(f"{cp}: not a metadesign {what} card (format {card.get('format')!r}, expected "
                              f"{' or '.join(formats)})")
    if file_key(path) != card.get("weights_sha256"):
        raise ValidationError(f"{path}: weights do not match the card's sha256 (truncated or replaced)")
    return path, cp, card


def model_card(path: str | Path, formats: str | Iterable[str] | None = None, what: str = "model") -> dict:
    """The card of the model at ``path`` (its weights, its card, or a card-only model), read and checked by
    :func:`read_card`: the one reader of a card's content, so the weights' sha256 is checked whenever the
    card names weights.  ``formats``: those accepted (default: the one the card names)."""
    return read_card(path, card_format(path, what) if formats is None else formats, what)[2]


def has_format(path: str | Path, formats: str | Iterable[str]) -> bool:
    """Whether the model file at ``path`` names one of ``formats`` in its card: a sniff of the format alone
    (which loader to call); the loader then reads the card through :func:`read_card`, sha256 checked."""
    formats = (formats,) if isinstance(formats, str) else tuple(formats)
    try:
        return card_format(path) in formats
    except ValidationError:
        return False


def load_weights(path: str | Path, device: str = "cpu", what: str = "model") -> dict:
    """The tensors of a safetensors file (never unpickled), every float finite; one line otherwise."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        state = load_file(str(path), device=device)
    except (SafetensorError, OSError, ValueError) as exc:
        raise ValidationError(f"{path}: unreadable safetensors ({str(exc).splitlines()[0] if str(exc) else exc})") \
            from None
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(v.isfinite().all())]
    if bad:
        raise ValidationError(f"{path}: non-finite weights (NaN or infinity in {len(bad)} tensor(s), e.g. {bad[0]}): "
                              f"a diverged or damaged {what}")
    return state


def load_into(module, state: dict, path: str | Path, what: str = "model", strict: bool = True) -> None:
    """``module.load_state_dict(state)``; weights that do not fit the card's architecture are one line."""
    try:
        missing, unexpected = module.load_state_dict(state, strict=False)
    except (RuntimeError, ValueError) as exc:
        raise ValidationError(f"{path}: weights do not fit the card's architecture "
                              f"({str(exc).strip().splitlines()[-1].strip()[:160]})") from None
    if strict and (missing or unexpected):
        raise ValidationError(f"{path}: weights do not fit the card's architecture (missing {list(missing)[:3]}, "
                              f"unexpected {list(unexpected)[:3]})")

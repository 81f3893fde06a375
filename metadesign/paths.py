"""Where the committed products live: the unit-cell libraries, the recipes and the demo models.

In a checkout (an editable install) they are ``library/``, ``layouts/`` and ``sensing/`` beside the
package; an installed wheel carries them as ``metadesign/products/`` (see ``setup.py``).  Everything that
needs one asks :func:`repo_root` (or :func:`product`), so the demo and the default recipes work from any
folder either way.  Outputs are never written here."""

from __future__ import annotations

from pathlib import Path

__all__ = ["repo_root", "default_library_path", "product", "shipped_root"]

_CHECKOUT = Path(__file__).resolve().parents[1]
_SHIPPED = Path(__file__).resolve().parent / "products"


def shipped_root() -> Path:
    """The products inside the installed package (a wheel's copy)."""
    return _SHIPPED


def repo_root() -> Path:
    """The folder holding ``library/``, ``layouts/``, ``sensing/``: the checkout when this package runs from
    one, else the copy the wheel installed with the package."""
    if (_CHECKOUT / "library" / "paper.npz").is_file() and (_CHECKOUT / "sensing").is_dir():
        return _CHECKOUT
    return _SHIPPED


def product(*parts: str) -> Path:
    """A committed product by its path in the checkout, e.g. ``product("sensing", "paper.toml")``."""
    return repo_root().joinpath(*parts)


def default_library_path() -> Path:
    return product("library", "paper.npz")

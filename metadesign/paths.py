"""Where the committed products live: the unit-cell libraries, the recipes and the demo models.

In a checkout (an editable install) they are ``library/``, ``layouts/`` and ``sensing/`` beside the
package; an installed wheel carries them as ``metadesign/products/`` (see ``setup.py``).  Everything that
needs one asks :func:`repo_root` (or :func:`product`), so the demo and the default recipes work from any
folder either way.  Outputs are never written here."""

from __future__ import annotations

from pathlib import Path

__all__ = ["repo_root", "default_library_path", "product", "shipped_root", "recipe_path", "resolve_against"]

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


def resolve_against(base: str | Path | None, p) -> Path | None:
    """A path a recipe names, relative to the recipe's folder ``base`` unless absolute (None: not given)."""
    if not p:
        return None
    q = Path(p)
    return q if q.is_absolute() or base is None else Path(base) / q


def recipe_path(name: str | Path, folder: str) -> Path:
    """A recipe given by path, or by the name of a packaged one (``pipeline-demo`` ->
    ``sensing/pipeline-demo.toml`` of the checkout or the wheel): a path that exists wins."""
    p = Path(name)
    if p.exists() or p.suffix or len(p.parts) > 1:
        return p
    packaged = product(folder, f"{p.name}.toml")
    return packaged if packaged.is_file() else p

"""What made a committed result: the ``made_with`` block every study result (compare, tolerance, transfer)
writes, so a result can be checked against the recipe and model it claims (``tests/test_committed_results``).

* ``model``: the weights' sha256 (the bytes the result was computed with);
* ``dataset``: the dataset's declared recipe key (:meth:`DatasetRecipe.declared_key`, computable from the
  committed recipes without building anything) and, for a built dataset, its recipe hash and name;
* ``recipe``: the study recipe by its parsed content (a comment edit keeps the key).
"""
from __future__ import annotations

import json
from pathlib import Path

from .. import __version__
from ..config import load_toml
from ..reconstruction.dataset_store import decoded_attrs
from ..tasks import content_key, file_key

__all__ = ["made_with", "model_record", "dataset_record", "recipe_record"]


def model_record(path: str | Path | None) -> dict | None:
    if path is None:
        return None
    p = Path(path)
    return {"name": p.name, "weights_sha256": file_key(p)}


def dataset_record(folder: str | Path | None = None, recipe=None) -> dict | None:
    """A built dataset (its attributes) and/or the dataset recipe it was built from."""
    if folder is None and recipe is None:
        return None
    rec: dict = {}
    if folder is not None:
        attrs = decoded_attrs(json.loads((Path(folder) / "zarr.json").read_text()).get("attributes", {}))
        rec.update({"name": attrs.get("name"), "recipe_hash": attrs.get("recipe_hash"),
                    "recipe_key": attrs.get("recipe_key"), "root_seed": attrs.get("root_seed")})
    if recipe is not None:
        rec["recipe_key"] = recipe.declared_key()
    return rec


def recipe_record(path: str | Path | None) -> dict | None:
    if path is None:
        return None
    p = Path(path)
    return {"name": p.name, "key": content_key(load_toml(p))}


def made_with(model=None, dataset=None, dataset_recipe=None, recipe=None, **extra) -> dict:
    """The ``made_with`` block (see the module docstring); ``extra``: further named records."""
    return {"metadesign": __version__, "model": model_record(model),
            "dataset": dataset_record(dataset, dataset_recipe), "recipe": recipe_record(recipe), **extra}

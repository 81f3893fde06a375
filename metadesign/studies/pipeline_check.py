"""The pipeline's up-front check: every input a later stage would refuse, refused before the first stage
writes anything (one line, exit 2 at the CLI).

The recipes it names are parsed (each by its own loader: a recipe of the wrong kind is refused here, not
after five stages), the designs are checked against the library's wavelength and period and the
turbulence scenario's wavelength, the library re-check cells against the table's grid, and each given
model by its card and its weights' safetensors header (the format, the sha256, the tensor sizes against
the dataset's and the scenario's received crop): no network is built."""

from __future__ import annotations

import json
import struct
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

from ..cards import read_card
from ..design.recipe import load_design_recipe
from ..design.store import check_library
from ..library.recipe import load_recipe
from ..library.store import load_library
from ..reconstruction.dataset import dataset_recipe_from_dict, received_crop, split_labels
from ..reconstruction.model import MODEL_FORMAT, UNetConfig, check_sizes
from ..reconstruction.refine import REFINER_FORMAT, is_refiner
from ..reconstruction.train import load_train_recipe
from ..sensing.device import check_wavelengths
from ..sensing.model import load_sensing_recipe
from ..tasks import file_key
from ..turbulence.scenario import load_scenario
from ..validation import ValidationError
from .pipeline_recipe import PipelineRecipe

SPLITS = ("train", "val", "test")  # the dataset's split labels 0, 1, 2

__all__ = ["check_inputs", "check_cells", "card_config"]


def check_inputs(rec: PipelineRecipe) -> None:
    """Refuse, before any stage runs, what a stage of ``rec`` would refuse (see the module's docstring)."""
    p, b, t = rec.pipeline, rec.beacons, rec.train
    scenario = _named("pipeline.turbulence", p.turbulence, load_scenario)
    crop = received_crop(scenario)[1]
    if p.library_recipe is not None:
        lr = _named("pipeline.library_recipe", p.library_recipe, load_recipe)
        stack, grid = lr.stack, (len(lr.widths), len(lr.widths))
    else:
        lib = load_library(p.library)
        stack, grid = lib, (len(lib.wx), len(lib.wy))
    designs = [("pipeline", p.design, p.sensor)] + ([] if b is None else [("beacons", b.design, b.sensor)])
    for section, design, sensor in designs:
        dr = _named(f"{section}.design", design, load_design_recipe)
        check_library(replace(dr, library_path=p.library_source), SimpleNamespace(wavelength=stack.wavelength,
                                                                                  period=stack.period))
        check_wavelengths(dr.spec.wavelength, scenario.wavelength, f"turbulence {p.turbulence}")
        _named(f"{section}.sensor", sensor, load_sensing_recipe)
    check_cells(grid, p.library_recheck)
    if rec.dataset is not None:
        _check_dataset(rec)
    if t is not None and t.recipe is not None:
        _named("train.recipe", t.recipe, load_train_recipe)
    if t is not None and t.model is not None:  # a given model must fit the dataset it will be evaluated on
        check_sizes(card_config(t.model), rec.dataset.tensor_size, crop, f"[train] model {t.model}")
    if b is not None:  # the beacons' model: its output the scenario's crop (its input sets the sensor's tensor)
        c = card_config(b.model)
        check_sizes(c, c.input_size, crop, f"[beacons] model {b.model}")


def _check_dataset(rec: PipelineRecipe) -> None:
    """The ``[dataset]`` section as the dataset build reads it, and the split ``[evaluate]`` reads not empty."""
    d, p = rec.dataset, rec.pipeline
    dr = dataset_recipe_from_dict(d.document(p.design.with_suffix(".oas"), p.sensor, p.turbulence), "dataset")
    if rec.evaluate.split != "all":
        n = int((split_labels(dr.seed, dr.samples, dr.split) == SPLITS.index(rec.evaluate.split)).sum())
        if n == 0:
            raise ValidationError(f"evaluate.split: the {rec.evaluate.split} split of the dataset is empty "
                                  f"(dataset.split {list(d.split)} of {d.samples} samples)")


def _named(field: str, path: Path, load):
    """``load(path)``; a file it refuses (another kind of recipe, a bad value) is one line naming ``field``."""
    try:
        return load(path)
    except ValidationError as exc:
        raise ValidationError(f"{field}: {path}: {exc}") from None


def check_cells(grid: tuple[int, int], cells) -> None:
    """Refuse a re-check cell ``(i, j)`` outside a library of ``grid`` (n_wx, n_wy) cells."""
    for i, j in cells:
        if not (0 <= i < grid[0] and 0 <= j < grid[1]):
            raise ValidationError(f"pipeline.library_recheck: cell [{i}, {j}] is outside the library's "
                                  f"{grid[0]} x {grid[1]} grid")


def card_config(path: Path) -> UNetConfig:
    """The U-Net grids of the model (a U-Net, or a refiner: its U-Net's) at ``path``, from the cards and the
    weights' safetensors headers alone: each card of its format and its weights' sha256, each header
    readable, of the card's format, its tensors within the file.  One line otherwise."""
    path = Path(path)
    if is_refiner(path):
        path, cp, card = read_card(path, REFINER_FORMAT, "refiner")
        _check_header(path, REFINER_FORMAT)
        try:
            ref = card["unet"]
            up = Path(ref["path"])
        except (KeyError, TypeError) as exc:
            raise ValidationError(f"{cp}: not a metadesign refiner card ({exc})") from None
        up = up if up.is_absolute() else path.parent / up
        if not up.is_file() and (path.parent / up.name).is_file():  # copied beside the refiner
            up = path.parent / up.name
        unet_path, _, _ = read_card(up, MODEL_FORMAT, "model")
        if file_key(unet_path) != ref.get("weights_sha256"):
            raise ValidationError(f"{path}: its U-Net {up} is not the one it was trained on (sha256 differs)")
        path = up
    path, cp, card = read_card(path, MODEL_FORMAT, "model")
    _check_header(path, MODEL_FORMAT)
    try:
        if not isinstance(card.get("architecture"), dict):
            raise ValueError("no architecture object")
        return UNetConfig(**card["architecture"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValidationError(f"{cp}: not a metadesign model card ({exc})") from None


def _check_header(path: Path, fmt: str) -> dict:
    """The safetensors header of ``path`` (name -> dtype, shape, offsets), checked: JSON, the card's format
    in its metadata, every tensor's bytes within the file."""
    size = path.stat().st_size
    try:
        with open(path, "rb") as fh:
            (n,) = struct.unpack("<Q", fh.read(8))
            if n > size - 8:
                raise ValueError(f"a header of {n} bytes in a file of {size}")
            head = json.loads(fh.read(n))
        meta = head.pop("__metadata__", None) or {}
        ends = [int(v["data_offsets"][1]) for v in head.values()]
    except (struct.error, ValueError, KeyError, TypeError, AttributeError, IndexError) as exc:
        raise ValidationError(f"{path}: unreadable safetensors ({exc})") from None
    if meta.get("format", fmt) != fmt:
        raise ValidationError(f"{path}: weights of format {meta.get('format')!r}, expected {fmt}")
    if max(ends, default=0) > size - 8 - n:
        raise ValidationError(f"{path}: unreadable safetensors (truncated: its tensors end past the file)")
    return head

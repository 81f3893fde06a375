"""The device a model's deployment contract describes (issue #52), from its dataset or without it.

A model card names the dataset it was trained on by its recipe hash and layout sha256 (``card["dataset"]``).
The export needs that dataset's device (its coarse pupil, sensor and received-field crop) and identity
(design, layout, library, perturbation, the lenses' focal lengths):

* with the dataset (``export --dataset``): its stored device, refused unless its recipe hash and layout are
  the card's;
* without it: the committed dataset recipe of the same name (``sensing/dataset-demo.toml`` for
  ``sensing/dataset-demo``), its device rebuilt as the dataset build makes it (from its layout file when
  present, whose sha256 must be the card's; else from its design recipe, designed in a scratch folder),
  refused unless the recipe hash it gives is the card's.

Both give the same :class:`ContractDevice` (a test holds them equal).  A co-designed model (its card's
``codesign`` block) is deployed on the co-designed device: the dataset's device with each channel's learned
diversity (focal length and Zernike terms, :mod:`metadesign.sensing.diversity`) on its pupil, named after the
committed design recipe that lays it out when there is one."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..config import load_toml
from ..design.recipe import load_design_recipe
from ..design.store import run_design
from ..paths import product as committed
from ..sensing.device import Device, ReceiverCrop
from ..sensing.diversity import diversity_operators, lens_table
from ..sensing.forward import CoarsePupil
from ..sensing.model import AsFabricated
from ..sensing.sensor import SensorSpec
from ..sensing.twin_diversity import DiversityTwin
from ..tasks import content_key, file_key
from ..turbulence.scenario import load_scenario
from ..turbulence.system import build_system
from ..validation import ValidationError
from .codesign import apply_diversity
from .dataset_build import recipe_parts
from .dataset_recipe import load_dataset_recipe, received_crop
from .dataset_store import load_device, open_dataset

__all__ = ["ContractDevice", "codesigned_pupil", "contract_device", "dataset_recipe_of_card"]


@dataclass
class ContractDevice:
    """A model's device for its contract: the :class:`Device` whose flat frames give the calibration
    signature, its identity (``metadesign.device``), its lens table ``(2, 4, 3)`` ``[f, x, y]`` (m), the
    co-designed diversity (None for a device as laid out), and where it came from (for the report)."""

    device: Device
    identity: dict
    lenses: np.ndarray
    diversity: dict | None = None
    source: str = ""
    notes: list = field(default_factory=list)


def _card_record(card: dict) -> dict:
    return card.get("dataset") or card.get("trained_on") or {}


def dataset_recipe_of_card(model_path, card: dict) -> Path:
    """The committed dataset recipe a card's dataset was built from: ``NAME.toml`` beside the dataset folder the
    card names (as the training ran: relative to the working folder, or to the checkout / installed products),
    or in ``sensing/`` of the committed products."""
    rec = _card_record(card)
    path = rec.get("path")
    if not path:
        raise ValidationError(f"{model_path}: its card names no dataset (dataset.path): give --dataset DATASET, the "
                              "dataset it was trained on")
    p = Path(path)
    name = f"{p.name}.toml"
    for c in (p.parent / name, committed(*p.parent.parts, name), Path(model_path).parent.parent / name,
              committed("sensing", name)):
        if c.is_file():
            return c
    raise ValidationError(f"{model_path}: no committed recipe {name} of its dataset {path}: give --dataset {path}")


def _sensor_as_stored(sensor: SensorSpec) -> SensorSpec:
    """The sensor as a dataset stores and reads it back (its provenance's units): the same floats either way."""
    s = sensor.to_dict()
    return SensorSpec(int(s["width_px"]), int(s["height_px"]), float(s["pixel_um"]) * 1e-6, float(s["magnification"]),
                      float(s["distance_mm"]) * 1e-3, int(s["tensor_size"]))


def _check_card(card_rec: dict, recipe_hash: str | None, layout_sha: str | None, what: str) -> None:
    """Refuse a dataset (or recipe) whose recipe hash or layout is not the one the card names."""
    want_r, want_l = card_rec.get("recipe_hash"), card_rec.get("layout_sha256")
    if want_l and layout_sha and layout_sha != want_l:
        raise ValidationError(f"{what}: its layout differs from the one the model was trained on (sha256 "
                              f"{layout_sha[:12]} vs the card's {want_l[:12]})")
    if want_r and recipe_hash is not None and recipe_hash != want_r:
        raise ValidationError(f"{what}: its recipe differs from the one the model was trained on (recipe_hash "
                              f"{str(recipe_hash)[:12]} vs the card's {want_r[:12]})")


def _from_dataset(dataset, card: dict, model_path) -> ContractDevice:
    info = open_dataset(dataset)
    attrs = info.attrs
    if not attrs.get("recipe_hash"):
        raise ValidationError(f"--dataset {dataset}: no recipe hash (a damaged dataset?)")
    if attrs.get("propagation") == "slm":
        raise ValidationError(f"--dataset {dataset}: imported captures, not the dataset the model was trained on")
    prov = attrs.get("provenance") or {}
    _check_card(_card_record(card), attrs.get("recipe_hash"), prov.get("layout_sha256"), f"--dataset {dataset}")
    dev = load_device(dataset)
    ident = {"design": prov.get("design"), "layout_sha256": prov.get("layout_sha256"),
             "library_sha256": prov.get("library_sha256"), "perturbation": prov.get("perturbation"),
             "dataset_recipe_hash": attrs.get("recipe_hash")}
    return ContractDevice(dev, ident, lens_table(prov["channels"]), source=f"dataset {dataset}")


def _from_recipe(model_path, card: dict, log) -> ContractDevice:
    """The device of the committed dataset recipe the card names, built as the dataset build builds it."""
    path = dataset_recipe_of_card(model_path, card)
    recipe = load_dataset_recipe(path)
    card_rec = _card_record(card)
    scenario = load_scenario(recipe.turbulence)
    base = recipe.source.parent if recipe.source else Path.cwd()
    if recipe.layout is not None and recipe.layout.is_file():
        layout_sha = file_key(recipe.layout)
        _check_card(card_rec, None, layout_sha, f"{recipe.layout} (dataset recipe {path})")
        fab, source = AsFabricated.from_files(recipe.layout), f"recipe {path} (layout {recipe.layout})"
    elif recipe.design is not None and recipe.design.is_file():
        layout_sha = card_rec.get("layout_sha256")
        if not layout_sha:
            raise ValidationError(f"{model_path}: its card names no layout_sha256, and {recipe.layout} is not built: "
                                  "give --dataset, or build the layout")
        log(f"export: {recipe.layout or 'the layout'} is not built: the device from its design recipe {recipe.design} "
            "(designed in a scratch folder)")
        with tempfile.TemporaryDirectory(prefix="metadesign-export-") as tmp:
            d, _ = run_design(load_design_recipe(recipe.design), Path(tmp) / "design")
        fab, source = AsFabricated.from_design(d), f"recipe {path} (design {recipe.design})"
    else:
        raise ValidationError(f"{path}: neither its layout {recipe.layout} nor a design recipe exists: give --dataset")
    system = build_system(fab, recipe.sensor, scenario, recipe.fabrication, base, recipe.tensor_size)
    rhash = content_key(recipe_parts(recipe, system, layout_sha))
    _check_card(card_rec, rhash, None, f"dataset recipe {path}")
    c0, a = received_crop(scenario)
    dev = Device(system.pupil(), _sensor_as_stored(system.sensing.sensor), ReceiverCrop.of_scenario(scenario, c0, a))
    prov = fab.layout.provenance
    ident = {"design": prov.get("design"), "layout_sha256": layout_sha, "library_sha256": fab.lib.identity,
             "perturbation": system.perturbation.to_dict(), "dataset_recipe_hash": rhash}
    return ContractDevice(dev, ident, lens_table(prov["channels"]), source=source)


def codesigned_pupil(pupil: CoarsePupil, sensor: SensorSpec, lenses: np.ndarray, diversity: dict) -> CoarsePupil:
    """The coarse pupil of the co-designed device: each channel's block field times ``exp(i psi)``, its
    diversity phase (:mod:`metadesign.sensing.diversity`: the learned focal length and Zernike terms of a
    card's ``codesign`` block), the model the co-design trained through."""
    ops = diversity_operators(pupil, sensor, lenses, None, 1, None, tuple(diversity["zernike_noll"]))
    tw = apply_diversity(DiversityTwin(ops, double=True), diversity)
    with torch.no_grad():
        psi = tw.phases().numpy()
    G = (pupil.G * np.exp(1j * psi)).astype(np.complex64)
    return CoarsePupil(G, pupil.X, pupil.block, pupil.period, pupil.wavelength, pupil.z, pupil.n_clamped)


def _codesign_recipe(diversity: dict) -> Path | None:
    """The committed design recipe (``layouts/*.toml``) whose lenses carry this diversity, if one does."""
    f = np.asarray(diversity["focal_length_mm"], float)
    a = np.asarray(diversity["zernike_rad"], float)
    folder = committed("layouts")
    for p in sorted(folder.glob("*.toml")) if folder.is_dir() else ():
        try:
            d = load_toml(p)
            ok = all(np.allclose(d[s]["focal_lengths_mm"], f[i], atol=1e-6, rtol=0)
                     and list(d[s].get("zernike_noll", [])) == list(diversity["zernike_noll"])
                     and np.allclose(d[s]["zernike_rad"], a[i], atol=1e-6, rtol=0)
                     for i, s in enumerate(("x_pol", "y_pol")))
        except (KeyError, TypeError, ValueError, OSError):
            continue
        if ok:
            return p
    return None


def contract_device(model_path, card: dict, dataset=None, log=lambda s: None) -> ContractDevice:
    """The device of ``model_path``'s contract: from ``dataset`` when given, else from the committed dataset
    recipe its card names (see the module docstring); a co-designed model's with its diversity."""
    cd = _from_dataset(dataset, card, model_path) if dataset is not None else _from_recipe(model_path, card, log)
    div = card.get("codesign")
    if div:
        dev = cd.device
        cd.device = Device(codesigned_pupil(dev.pupil, dev.sensor, cd.lenses, div), dev.sensor, dev.crop)
        f = np.asarray(div["focal_length_mm"], float) * 1e-3
        cd.lenses = np.concatenate([f[..., None], cd.lenses[..., 1:]], axis=-1)
        rec = _codesign_recipe(div)
        cd.diversity = {k: div[k] for k in ("focal_length_mm", "defocus_waves", "zernike_noll", "zernike_rad",
                                            "convention") if k in div}
        base = cd.identity
        cd.identity = {"design": rec.stem if rec is not None else f"{base['design']} + co-designed diversity",
                       "design_recipe": (f"layouts/{rec.name}" if rec is not None else None),
                       "layout_sha256": None, "library_sha256": base["library_sha256"],
                       "perturbation": base["perturbation"], "dataset_recipe_hash": base["dataset_recipe_hash"],
                       "co_designed": True, "diversity": cd.diversity,
                       "base_device": {k: base[k] for k in ("design", "layout_sha256")},
                       "note": "the co-designed device as the model was trained with it: the base device's pupil "
                               "with each channel's diversity (focal length, Zernike terms); design_recipe lays it "
                               "out"}
    return cd

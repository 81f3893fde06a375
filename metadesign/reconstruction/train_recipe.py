"""The training recipe (stage 6b): its TOML tables ``[data]``, ``[model]``, ``[train]``, ``[refine]`` and
``[codesign]`` parsed and checked (:class:`TrainRecipe`); the run itself: :mod:`.train`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..config import ConfigError, Param, Section, load_toml, parse
from .codesign import CodesignConfig
from .losses import LOSSES
from .refine import RefineConfig

__all__ = ["SECTIONS", "TrainRecipe", "train_recipe_from_dict", "load_train_recipe"]


SECTIONS = (
    Section("data", (
        Param("dataset", str, None),
        Param("noise_percent", float, 5.0, lo=0, hi=100, span=True),
        Param("photons_at_peak", float, 0.0, lo=0, hi=1e15, span=True),
        Param("read_noise_e", float, 0.0, lo=0, hi=1e6),
        Param("train_limit", int, 0, lo=0),
        Param("val_limit", int, 0, lo=0),
        Param("loader_workers", int, 0, lo=0, hi=64),
    ), optional=True),
    Section("model", (
        Param("kind", str, "unet", choices=["unet", "modal"]),
        Param("base", int, 64, lo=1, hi=256),
        Param("depth", int, 5, lo=2, hi=8),
        Param("norm", str, "group", choices=["group", "batch", "none"]),
        Param("output", str, "phase", choices=["phase", "field"]),
        Param("basis", str, "zernike", choices=["zernike", "dm"]),
        Param("modes", int, 100, lo=1, hi=2000),
        Param("actuators", int, 12, lo=2, hi=128),
        Param("coupling", float, 0.15, lo=0, hi=1, open_lo=True, open_hi=True),
        Param("stride", int, 4, lo=1, hi=64),
        Param("width", int, 32, lo=1, hi=1024),
        Param("hidden", int, 256, lo=1, hi=8192),
        Param("bin", int, 8, lo=0, hi=4096),
        Param("window", int, 0, lo=0, hi=4096),
        Param("linear_init", bool, True),
    ), optional=True, help="the network: kind = \"unet\" (metadesign.reconstruction.model; output = \"field\": "
                           "the phase of exp(i phi) + a learned field, which can hold branch points) or \"modal\" "
                           "(the real-time metadesign.reconstruction.modal_net: basis, modes | actuators + coupling, "
                           "stride, width, hidden, bin; window: the centred square of each channel it reads, 0 the whole "
                           "tensor; linear_init: its linear path starts as the measured "
                           "least-squares reconstructor)"),
    Section("train", (
        Param("epochs", int, 500, lo=1, hi=100000),
        Param("batch", int, 64, lo=1, hi=65536),
        Param("lr", float, 1e-4, lo=0, open_lo=True, hi=1),
        Param("weight_decay", float, 0.01, lo=0, hi=1),
        Param("lr_halve_every", int, 200, lo=1, hi=100000),
        Param("loss", str, "pib", choices=list(LOSSES)),
        Param("pib_operator", str, "auto", choices=["auto", "split_step", "quadratic", "stored"]),
        Param("pretrain_loss", str, "phase", choices=list(LOSSES)),
        Param("pretrain_epochs", int, 0, lo=0, hi=100000),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
        Param("max_minutes", float, 0.0, lo=0, hi=1e6),
        Param("teacher", str, None),
    ), optional=True),
    Section("refine", (
        Param("unet", str, None),
        Param("steps", int, 3, lo=1, hi=32),  # K = 0 is the U-Net alone: nothing to train
        Param("rebin", int, 4, lo=1, hi=64),
        Param("samples", int, 1, lo=0, hi=16),
        Param("width", int, 32, lo=1, hi=512),
        Param("features", int, 16, lo=1, hi=512),
        Param("step_init", float, 0.05, lo=0, hi=10),
        Param("deep_supervision", float, 0.0, lo=0, hi=10),
        Param("init", str, None),
        Param("output", str, "phase", choices=["phase", "field"]),
    ), optional=True, help="a learned refinement (metadesign.reconstruction.refine) trained on top of a frozen "
                           "U-Net (refine.unet, or --init); samples = 0: every camera pixel"),
    Section("codesign", (
        Param("modes", list, [5, 6, 7, 8, 9, 10, 11], lo=4, hi=66),
        Param("learn_defocus", bool, True),
        Param("lr", float, 1e-2, lo=0, hi=10),
        Param("init", str, "paper", choices=["paper", "random"]),
        Param("init_waves", float, 0.5, lo=0, hi=100),
        Param("init_rad", float, 0.5, lo=0, hi=100),
        Param("defocus_scale", float, 1.0, lo=0, hi=20),
        Param("max_step_rad", float, 0.5, lo=0, open_lo=True, hi=10),
        Param("penalty", float, 1.0, lo=0, hi=1e6),
        Param("rebin", int, 1, lo=1, hi=64),
        Param("samples", int, 0, lo=0, hi=16),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
    ), optional=True, help="co-design (metadesign.reconstruction.codesign): the sensor's diversity (each "
                           "channel's defocus and Zernike terms `modes`, Noll >= 4) trained with the U-Net, the "
                           "PSFs rendered from the dataset's received fields; lr: the diversity's learning rate"),
)


_UNET_KEYS = ("base", "depth", "norm", "output")
_MODAL_KEYS = ("basis", "modes", "actuators", "coupling", "stride", "width", "hidden", "bin", "window")


@dataclass(frozen=True)
class TrainRecipe:
    name: str
    source: Path | None
    dataset: Path | None
    noise_percent: tuple[float, float]  # (lo, hi): the Gaussian level per sample is drawn in this range
    photons_at_peak: tuple[float, float] | None  # shot noise (photo-electrons at each channel's peak), or None
    read_noise_e: float
    train_limit: int
    val_limit: int
    loader_workers: int
    base: int
    depth: int
    norm: str
    epochs: int
    batch: int
    lr: float
    weight_decay: float
    lr_halve_every: int
    loss: str
    pib_operator: str
    pretrain_loss: str
    pretrain_epochs: int
    seed: int
    max_minutes: float
    raw: dict
    refine: object = None  # RefineConfig when the recipe trains a refiner
    refine_unet: Path | None = None
    refine_deep: float = 0.0  # weight of the intermediate steps' losses (deep supervision)
    refine_init: Path | None = None  # a trained refiner to start from
    codesign: object = None  # CodesignConfig when the recipe co-designs the sensor's diversity
    output: str = "phase"  # the U-Net's output (model.UNetConfig.output)
    modal: dict | None = None  # kind = "modal": the ModalNetConfig keys (less the tensor and crop sizes)
    linear_init: bool = False  # kind = "modal": its linear path from the measured reconstructor
    teacher: Path | None = None  # loss "distill": the network whose estimates the model learns
    max_steps: int | None = None  # stop after this many optimiser steps (the CLI's --max-steps; no recipe key)

    def noise(self) -> dict:
        """The PSFDataset noise keywords of this recipe."""
        return {"gaussian_percent": self.noise_percent, "photons_at_peak": self.photons_at_peak,
                "read_noise_e": self.read_noise_e}

    def loss_at(self, epoch: int) -> str:
        return self.pretrain_loss if epoch < self.pretrain_epochs else self.loss

    def derive(self, name: str, data: dict | None = None, **train) -> "TrainRecipe":
        """A training recipe for another run of this architecture (a fine-tune, a retraining): the same
        [model], batch and weight decay, seed 0, the given [data] keys and [train] keys (checked as a
        recipe is)."""
        model = ({"kind": "modal", **self.modal, "linear_init": False} if self.modal is not None else
                 {"base": self.base, "depth": self.depth, "norm": self.norm, "output": self.output})
        raw = {"data": dict(data or {}), "model": model,
               "train": {"batch": self.batch, "weight_decay": self.weight_decay, "seed": 0, **train}}
        return train_recipe_from_dict(raw, name, self.source)


def train_recipe_from_dict(data: dict, name: str = "train", source: Path | None = None) -> TrainRecipe:
    v = parse(data, SECTIONS, str(source) if source else "recipe")
    d, m, t = v["data"], v["model"], v["train"]
    if d["photons_at_peak"][0] == 0 < d["photons_at_peak"][1]:
        raise ConfigError("data.photons_at_peak", f"expected a range in (0, 1e+15] (0 alone: no shot noise), got "
                          f"{list(d['photons_at_peak'])}")
    ds = d["dataset"]
    if ds is not None and not Path(ds).is_absolute():
        ds = (source.parent if source else Path.cwd()) / ds
    refine = refine_unet = refine_init = None
    r = v["refine"]
    if "refine" in data:
        refine = RefineConfig(steps=r["steps"], rebin=r["rebin"], samples=r["samples"] or None, width=r["width"],
                              features=r["features"], step_init=r["step_init"], output=r["output"])

        def rel(q):
            return None if not q else Path(q) if Path(q).is_absolute() else (source.parent if source else Path.cwd()) / q

        refine_unet, refine_init = rel(r["unet"]), rel(r["init"])
    modal = None
    given = set((data.get("model") or {}) if isinstance(data.get("model"), dict) else ())
    if m["kind"] == "modal":
        wrong = sorted(given & set(_UNET_KEYS))
        if wrong:
            raise ConfigError(f"model.{wrong[0]}", "is a U-Net key; a modal network takes " + ", ".join(_MODAL_KEYS))
        modal = {k: m[k] for k in _MODAL_KEYS}  # checked with the tensor's size when the network is built
        w, grid = m["window"], 4 * m["stride"]
        if w and (w % grid or (m["bin"] and w % m["bin"])):
            raise ConfigError("model.window", f"expected 0 (the whole tensor) or a multiple of 4 x stride ({grid})"
                                              + (f" and of bin ({m['bin']})" if m["bin"] else "") + f", got {w}")
        if "refine" in data or "codesign" in data:
            raise ConfigError("model.kind", "a modal network is trained alone (no [refine] or [codesign])")
    else:
        wrong = sorted(given & (set(_MODAL_KEYS) | {"linear_init"}))
        if wrong:
            raise ConfigError(f"model.{wrong[0]}", "applies to kind = \"modal\" only")
    teacher = t["teacher"]
    if teacher is not None and not Path(teacher).is_absolute():
        teacher = (source.parent if source else Path.cwd()) / teacher
    distills = "distill" in (t["loss"], t["pretrain_loss"] if t["pretrain_epochs"] else None)
    if distills and teacher is None:
        raise ConfigError("train.teacher", "the distill loss needs a teacher network (a .safetensors path)")
    if teacher is not None and not distills:
        raise ConfigError("train.teacher", "is read by the distill loss only (train.loss or train.pretrain_loss)")
    if teacher is not None and not Path(teacher).exists():
        raise ConfigError("train.teacher", f"{teacher}: no such file")
    codesign = None
    if "codesign" in data:
        c = v["codesign"]
        if refine is not None:
            raise ConfigError("codesign", "a recipe trains a refiner or co-designs the sensor, not both")
        if d["photons_at_peak"][1] > 0:
            raise ConfigError("data.photons_at_peak", "co-design renders Gaussian sensor noise only (give 0)")
        if any(float(j) != int(j) for j in c["modes"]):
            raise ConfigError("codesign.modes", f"expected Noll indices (integers 4..66), got {c['modes']}")
        if 4 in [int(j) for j in c["modes"]] and c["learn_defocus"]:
            raise ConfigError("codesign.modes", "Noll 4 (defocus) is each lens's focal length already "
                                                "(learn_defocus); leave it out of modes")
        if c["defocus_scale"] != 1.0 and c["init"] != "paper":
            raise ConfigError("codesign.defocus_scale", "scales the paper's defocus ladder (init = \"paper\")")
        codesign = CodesignConfig(tuple(int(j) for j in c["modes"]), c["learn_defocus"], c["lr"], c["init"],
                                  c["init_waves"], c["init_rad"], c["max_step_rad"], c["penalty"], c["rebin"],
                                  c["samples"] or None, c["seed"], c["defocus_scale"])
    return TrainRecipe(codesign=codesign, refine=refine, refine_unet=refine_unet, refine_deep=r["deep_supervision"], refine_init=refine_init,
                       name=name, source=source,
                       dataset=Path(ds) if ds else None,
                       noise_percent=d["noise_percent"],
                       photons_at_peak=None if d["photons_at_peak"][1] == 0 else d["photons_at_peak"],
                       read_noise_e=d["read_noise_e"], train_limit=d["train_limit"], val_limit=d["val_limit"],
                       loader_workers=d["loader_workers"], base=m["base"], depth=m["depth"], norm=m["norm"],
                       teacher=Path(teacher) if teacher else None,
                       output=m["output"], modal=modal, linear_init=modal is not None and m["linear_init"],
                       epochs=t["epochs"], batch=t["batch"], lr=t["lr"], weight_decay=t["weight_decay"],
                       lr_halve_every=t["lr_halve_every"], loss=t["loss"], pib_operator=t["pib_operator"],
                       pretrain_loss=t["pretrain_loss"],
                       pretrain_epochs=t["pretrain_epochs"], seed=t["seed"], max_minutes=t["max_minutes"], raw=data)


def load_train_recipe(path: str | Path) -> TrainRecipe:
    path = Path(path)
    return train_recipe_from_dict(load_toml(path), name=path.stem, source=path)

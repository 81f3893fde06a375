"""Training (stage 6b): a plain Python loop with checkpoint/resume, in the manner of torchvision's
reference scripts.  One process, or DistributedDataParallel under ``torchrun`` (NCCL on GPUs, gloo on
CPU).  Device: CUDA, then MPS, then CPU; mixed precision (bf16 autocast for the U-Net) on CUDA.

A run folder holds ``checkpoint.pt`` (every epoch, atomically: model, optimiser, scheduler, random
states, history; read with ``torch.load(weights_only=True)``), ``metrics.csv``/``metrics.json``,
``curves.png`` and the best model by validation NPiB as ``model.safetensors`` + ``model.safetensors.json``.
The data order and the noise depend only on (seed, epoch, sample), so a run killed with SIGKILL and
restarted with ``--resume`` reproduces the loss curve of an uninterrupted run on CPU.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..cliutil import progress_bar
from ..config import ConfigError, Param, Section, load_toml, parse
from ..io import atomic_path, atomic_write_text, claim
from ..outputs import Input, product
from ..plotting import pyplot, save_figure
from ..validation import ValidationError, check_memory
from .codesign import CodesignConfig, build_codesign, diversity_record
from .data import PSFDataset
from .dataset_store import load_device
from .losses import LOSSES, PiB
from .metrics import captured_fraction, npib_rows
from .model import UNetConfig, build_unet, check_sizes, load_model, save_model, widen_unet
from .operators import has_operators
from .refine import RefineConfig, build_refiner, deepen_refiner, load_refiner, save_refiner

__all__ = ["TrainRecipe", "load_train_recipe", "train_recipe_from_dict", "train", "pick_device"]


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
        Param("base", int, 64, lo=1, hi=256),
        Param("depth", int, 5, lo=2, hi=8),
        Param("norm", str, "group", choices=["group", "batch", "none"]),
        Param("output", str, "phase", choices=["phase", "field"]),
    ), optional=True, help="the U-Net (metadesign.reconstruction.model); output = \"field\": the phase of "
                           "exp(i phi) + a learned field, which can hold branch points"),
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
        raw = {"data": dict(data or {}), "model": {"base": self.base, "depth": self.depth, "norm": self.norm,
                                                 "output": self.output},
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
                       output=m["output"],
                       epochs=t["epochs"], batch=t["batch"], lr=t["lr"], weight_decay=t["weight_decay"],
                       lr_halve_every=t["lr_halve_every"], loss=t["loss"], pib_operator=t["pib_operator"],
                       pretrain_loss=t["pretrain_loss"],
                       pretrain_epochs=t["pretrain_epochs"], seed=t["seed"], max_minutes=t["max_minutes"], raw=data)


def load_train_recipe(path: str | Path) -> TrainRecipe:
    path = Path(path)
    return train_recipe_from_dict(load_toml(path), name=path.stem, source=path)


def pick_device(local_rank: int = 0):
    """CUDA (this process's GPU), then Apple MPS, then CPU."""
    import torch

    if torch.cuda.is_available():
        torch.cuda.set_device(local_rank % torch.cuda.device_count())
        return torch.device("cuda", local_rank % torch.cuda.device_count())
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")


def _dist():
    """(rank, world size, local rank) from torchrun's environment; initialises the process group."""
    import torch
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1, 0
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    return rank, world, local


def _save_checkpoint(path: Path, state: dict) -> None:
    import torch

    buf = io.BytesIO()
    torch.save(state, buf)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())


def _collate(batch):
    import torch

    return {k: torch.stack([b[k] for b in batch]) for k in batch[0]}


def evaluate_split(model, ds, pib, device, batch: int = 16, progress=None) -> dict:
    """Per-sample NPiB of the U-Net, the flat phase (uncorrected) and the phase conjugate on ``ds``."""
    import torch

    out = {"unet": [], "none": [], "phase_conjugate": [], "index": []}
    loader = torch.utils.data.DataLoader(ds, batch_size=batch, shuffle=False, collate_fn=_collate)
    model.eval()
    with torch.no_grad():
        for b in loader:
            scr = b["screens"].to(device)
            x = b[getattr(model, "input_key", "psf")].to(device)  # a co-design model renders its own PSFs
            r = npib_rows(pib, model(x), scr, b["received"].to(device))
            out["unet"].append(r["estimate"].cpu())
            out["none"].append(r["none"].cpu())
            out["phase_conjugate"].append(r["phase_conjugate"].cpu())
            out["index"].append(b["index"])
            if progress:
                progress(sum(len(x) for x in out["index"]), len(ds))
    return {k: torch.cat(v).numpy() for k, v in out.items()}


def train(recipe: TrainRecipe, run: Path, dataset: Path | None = None, resume: bool = False,
          init: Path | None = None, log: Callable[[str], None] = print, progress: bool = True,
          max_steps: int | None = None) -> dict:
    """Train ``recipe`` into the run folder ``run``; returns the final report (rank 0).  Rank 0 holds the
    run folder's lock while it trains: a second run into the same folder is refused."""
    run = Path(run)
    rank = int(os.environ.get("RANK", "0")) if int(os.environ.get("WORLD_SIZE", "1")) > 1 else 0
    inputs = {"the dataset": Input(dataset or recipe.dataset, members=None) if (dataset or recipe.dataset) else None,
              "--init": init, "refine.unet": recipe.refine_unet, "refine.init": recipe.refine_init,
              "the recipe": recipe.source}
    with product(run, "training-run", inputs) if rank == 0 else claim(run):
        return _train(recipe, run, dataset, resume, init, log, progress, max_steps)


def _train(recipe: TrainRecipe, run: Path, dataset: Path | None, resume: bool, init: Path | None,
           log: Callable[[str], None], progress: bool, max_steps: int | None) -> dict:
    import torch

    rank, world, local = _dist()
    device = pick_device(local)
    if device.type == "cpu":
        torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")) or 1)
    dataset = Path(dataset or recipe.dataset or "")
    if not str(dataset) or dataset == Path("."):
        raise ValidationError("train: no dataset (give --dataset DIR or data.dataset in the recipe)")
    if recipe.batch % world:
        raise ConfigError("train.batch", f"{recipe.batch} is not divisible by the {world} processes")
    run = Path(run)
    ckpt = _check_run(run, resume)
    noise = {} if recipe.codesign is not None else recipe.noise()  # co-design: noise on its own renderings
    tr = PSFDataset(dataset, "train", **noise, noise_seed=recipe.seed,
                    limit=recipe.train_limit or None)
    any_pib = any(LOSSES[recipe.loss_at(e)].end_to_end for e in range(recipe.epochs))
    mode = _pib_mode(recipe, tr)
    quadratic = mode == "quadratic" and any_pib
    stored = mode == "stored" and any_pib
    if stored:
        tr.require_operators("train")
    va = PSFDataset(dataset, "val", **noise, noise_seed=recipe.seed + 1,
                    limit=recipe.val_limit or None, screens=True)
    if len(va) == 0:
        raise ValidationError(f"{dataset}: the validation split is empty (training keeps the model with the best "
                              "validation NPiB): give the dataset a validation fraction or more samples")
    if len(tr) < recipe.batch:
        raise ValidationError(f"{dataset}: {len(tr)} training samples, fewer than one batch ({recipe.batch})")
    c0, a = tr.crop()
    if recipe.refine is not None:
        model, init_card = _build_refiner(recipe, dataset, tr.info.tensor_size, a, init, device)
    else:
        model, init_card = _build_model(recipe, tr.info.tensor_size, a, init, device)
        if recipe.codesign is not None:
            model = build_codesign(model, recipe.codesign, dataset, recipe.noise_percent).to(device)
    pib = PiB(tr.scenario(), c0, a, device)
    batch_loss = _BatchLoss(pib, stored, quadratic, device)
    if quadratic:
        n_ap = int(pib.ap.sum())
        check_memory("train.pib_operator = \"quadratic\"", len(tr) * len(pib.bucket) * n_ap * 8,
                     "use pib_operator = \"split_step\" or data.train_limit")
    if recipe.codesign is not None:  # the diversity at its own rate, without weight decay
        groups = [{"params": [p for p in model.unet.parameters() if p.requires_grad]},
                  {"params": [p for p in model.twin.parameters() if p.requires_grad], "lr": recipe.codesign.lr,
                   "weight_decay": 0.0}]
    else:
        groups = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(groups, lr=recipe.lr, weight_decay=recipe.weight_decay)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=recipe.lr_halve_every, gamma=0.5)
    history: list[dict] = []
    best = -math.inf
    start = 0
    if resume:
        history, best, start = _restore(ckpt, model, opt, sched, device)
        sched.step_size = recipe.lr_halve_every  # the recipe's schedule wins over the checkpoint's
        log(f"resumed {run} at epoch {start}")
    ddp_model = model
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP

        ddp_model = DDP(model, device_ids=[device.index] if device.type == "cuda" else None)
    sampler = torch.utils.data.distributed.DistributedSampler(tr, num_replicas=world, rank=rank, shuffle=True,
                                                              seed=recipe.seed, drop_last=True)
    use_amp = device.type == "cuda"
    run.mkdir(parents=True, exist_ok=True) if rank == 0 else None
    t_start = time.perf_counter()
    steps = 0
    for epoch in range(start, recipe.epochs):
        loss_name = recipe.loss_at(epoch)
        e2e = LOSSES[loss_name].end_to_end
        tr.screens = e2e and not stored and not (quadratic and len(batch_loss.ops) >= len(tr))
        tr.operators = stored and e2e
        tr.set_epoch(epoch)
        sampler.set_epoch(epoch)
        if recipe.codesign is not None:  # the rendered noise: the same draws after a resume, per rank
            model.seed_noise(int(np.random.SeedSequence([recipe.seed, epoch, rank]).generate_state(1)[0]))
        loader = torch.utils.data.DataLoader(tr, batch_size=recipe.batch // world, sampler=sampler,
                                             num_workers=recipe.loader_workers, collate_fn=_collate,
                                             drop_last=True, persistent_workers=False)
        ddp_model.train()
        t0 = time.perf_counter()
        tot, nb, npib_tr = 0.0, 0, []
        # a bar on a terminal, a line every 30 s in a log file or CI (cliutil.progress_bar)
        bar = progress_bar(f"epoch {epoch + 1}/{recipe.epochs} ({loss_name})", unit="step") \
            if progress and rank == 0 else None
        for b in loader:
            x = b[getattr(model, "input_key", "psf")].to(device, non_blocking=True)
            rec = b["received"].to(device)
            deep = recipe.refine is not None and recipe.refine_deep > 0
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_amp):
                phi = ddp_model(x, all_steps=True) if deep else ddp_model(x)
            if deep:  # deep supervision: every step's estimate is an estimate (NPiB rises with K; early exit)
                loss, npib = batch_loss(loss_name, phi[-1].float(), b, rec)
                for p_k in phi[1:-1]:
                    loss = loss + recipe.refine_deep * batch_loss(loss_name, p_k.float(), b, rec)[0] / (len(phi) - 2)
            else:
                loss, npib = batch_loss(loss_name, phi.float(), b, rec)
            if recipe.codesign is not None:
                loss = loss + model.penalty()
            if npib is not None:
                npib_tr.append(npib.detach().cpu())
            lv = float(loss.detach())
            if not math.isfinite(lv):
                raise ValidationError(f"train: the {loss_name} loss is {lv} at epoch {epoch + 1}, step {nb + 1} (the "
                                      "run diverged): lower train.lr, or --resume from the last checkpoint")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            tot += lv
            nb += 1
            steps += 1
            if bar is not None:
                bar(nb, len(loader))
            if max_steps is not None and steps >= max_steps:
                break
        sched.step()
        t_train = time.perf_counter() - t0
        rec_row = {"epoch": epoch + 1, "loss_name": loss_name, "train_loss": tot / max(nb, 1),
                   "lr": opt.param_groups[0]["lr"], "train_seconds": t_train,
                   "train_npib": float(torch.cat(npib_tr).mean()) if npib_tr else None}
        stop = max_steps is not None and steps >= max_steps
        if rank == 0:
            best = _end_epoch(rec_row, t0, model, va, pib, device, history, best, run, ckpt, opt, sched, recipe,
                              dataset, tr.info.attrs, init_card, log)
        if world > 1:
            import torch.distributed as dist

            dist.barrier()
        if stop or (recipe.max_minutes and time.perf_counter() - t_start > 60 * recipe.max_minutes):
            break
    report = {"run": str(run), "epochs_done": len(history), "history": history, "best_val_npib": best,
              "world_size": world, "device": str(device), "pib_operator": mode if any_pib else None}
    if world > 1:
        import torch.distributed as dist

        dist.destroy_process_group()
    return report


def _end_epoch(rec_row: dict, t0: float, model, va, pib, device, history: list, best: float, run: Path, ckpt: Path,
               opt, sched, recipe: TrainRecipe, dataset: Path, attrs: dict, init_card, log) -> float:
    """Rank 0 after an epoch: validation (the same noise every epoch), the best model by validation NPiB
    with its card, the checkpoint, metrics and curves; returns the best validation NPiB."""
    import torch

    epoch = rec_row["epoch"] - 1
    va.set_epoch(0)  # the same validation noise every epoch: comparable numbers
    ev = evaluate_split(model, va, pib, device)
    gain = captured_fraction(ev["none"], ev["unet"], ev["phase_conjugate"])
    rec_row |= {"val_npib": float(ev["unet"].mean()), "val_npib_none": float(ev["none"].mean()),
                "val_npib_phase_conjugate": float(ev["phase_conjugate"].mean()),
                "val_captured_fraction": float(gain), "val_loss": float(-np.log(np.maximum(ev["unet"], 1e-12)).mean()),
                "epoch_seconds": time.perf_counter() - t0}
    if not math.isfinite(rec_row["val_npib"]):
        raise ValidationError(f"train: validation NPiB is {rec_row['val_npib']} at epoch {epoch + 1} (non-finite "
                              "model output): lower train.lr, or --resume from the last checkpoint")
    history.append(rec_row)
    is_best = rec_row["val_npib"] > best
    if is_best:
        best = rec_row["val_npib"]
        save = save_model if recipe.refine is None else \
            (lambda m, p, c: save_refiner(m, p, init_card["path"], c))  # noqa: E731
        extra = {}
        if recipe.codesign is not None:  # the U-Net alone (for the co-designed device) and its diversity
            extra = {"codesign": diversity_record(model)}
            atomic_write_text(run / "diversity.json", json.dumps(extra["codesign"], indent=1))
        save(getattr(model, "unet", model) if recipe.codesign is not None else model, run / "model.safetensors", {
            **extra,
            "dataset": {"path": str(dataset), "recipe_hash": attrs.get("recipe_hash"),
                        "layout_sha256": attrs["provenance"].get("layout_sha256")},
            "sensor": attrs["provenance"].get("sensor"),  # the camera the model was trained for
            "recipe": recipe.raw, "epoch": epoch + 1, "metrics": rec_row, "init": init_card,
            "input_normalisation": attrs.get("normalisation"),
            "noise_percent": va.noise.describe()["gaussian_percent"], "noise": va.noise.describe(),
            "received_crop": attrs.get("received_crop"),
            "output": "received phase (vacuum removed) on the A x A receiver-aperture crop, rad; the "
                      "correction applied is its conjugate plus the focusing phase"})
    _save_checkpoint(ckpt, {"model": model.state_dict(), "optimizer": opt.state_dict(),
                            "scheduler": sched.state_dict(), "rng": {"torch": torch.get_rng_state()},
                            "history": json.dumps(history), "best": best, "epoch": epoch,
                            "recipe": json.dumps(recipe.raw, default=str)})
    _write_metrics(run, history)
    log(f"epoch {epoch + 1}/{recipe.epochs} {rec_row['loss_name']}: train {rec_row['train_loss']:.4f}, val NPiB "
        f"{rec_row['val_npib']:.3f} (none {rec_row['val_npib_none']:.3f}, conjugate "
        f"{rec_row['val_npib_phase_conjugate']:.3f}, captured {gain:.2f}), {rec_row['epoch_seconds']:.0f} s"
        + (" *" if is_best else ""))
    return best


def _check_run(run: Path, resume: bool) -> Path:
    """The run's checkpoint path; a fresh run into a finished one, or a resume without one, is refused."""
    ckpt = run / "checkpoint.pt"
    if run.exists() and ckpt.exists() and not resume:
        raise ValidationError(f"{run}: holds a run already; --resume continues it, or choose another -o")
    if resume and not ckpt.is_file():
        raise ValidationError(f"{run}: no checkpoint.pt to resume from")
    return ckpt


def _pib_mode(recipe: TrainRecipe, tr) -> str:
    """How the end-to-end loss meets a sample's screens (``train.pib_operator``):

    * "stored": the bucket operators A stored in the dataset (`metadesign dataset operators`): the loader
      reads A instead of regenerating 13 screens, and the loss is ||A u||^2 (a small matrix product);
    * "quadratic": A computed the first time a sample is drawn and kept in memory (no stored operators);
    * "split_step": the screens regenerated per draw and the split step run forward and back;
    * "auto" (default): "stored" when the dataset's training split has operators, else "split_step".

    All give the same loss (tests); they differ in cost only.  The loader's screens / operators flags are
    set per epoch."""
    if recipe.pib_operator == "auto":
        return "stored" if has_operators(tr.info.attrs, "train") else "split_step"
    return recipe.pib_operator


def _build_refiner(recipe: TrainRecipe, dataset: Path, tensor_size: int, aperture: int, init: Path | None, device):
    """The recipe's refiner around its frozen U-Net (``refine.unet``, else ``--init``), with the twin of
    the dataset's device; its steps seeded."""
    import torch

    if recipe.refine_unet is not None and init is not None:
        raise ValidationError(f"--init {init}: the recipe names the refiner's U-Net already (refine.unet "
                              f"{recipe.refine_unet}); give one of them (refine.init continues a trained refiner)")
    path = recipe.refine_unet or init
    if path is None:
        raise ValidationError("train: a [refine] recipe needs its U-Net (refine.unet in the recipe, or --init)")
    unet, card = load_model(path, str(device))
    check_sizes(unet.config, tensor_size, aperture, f"refine.unet {path}")
    torch.manual_seed(recipe.seed)
    model = build_refiner(unet, recipe.refine, load_device(dataset)).to(device)
    record = {"path": str(path), "weights_sha256": card.get("weights_sha256"), "epoch": card.get("epoch")}
    if recipe.refine_init is not None:  # start from a trained refiner of the same architecture
        src, rcard = load_refiner(recipe.refine_init, str(device))
        k = src.cfg.steps
        if (replace(src.cfg, steps=recipe.refine.steps, output=recipe.refine.output) != recipe.refine
                or k > recipe.refine.steps or (src.cfg.output, recipe.refine.output) == ("field", "phase")):
            raise ValidationError(f"refine.init {recipe.refine_init}: another [refine] architecture (the same "
                                  f"step networks and twin, at most refine.steps = {recipe.refine.steps} steps; "
                                  f"a phase refiner starts a field one, not the reverse)")
        # its step networks always; its U-Net and twin only when they are this recipe's (the same U-Net on
        # the same device: a continued run); another U-Net or device keeps refine.unet and the dataset's twin;
        # a deeper recipe appends identity steps after the trained ones
        transfer = rcard["unet"]["weights_sha256"] != card.get("weights_sha256")
        state = src.state_dict()
        deepen_refiner(model, {k_: v for k_, v in state.items() if k_.startswith("steps.")} if transfer else state, k)
        record.update(refiner=str(recipe.refine_init), refiner_steps_only=transfer)
        if k < recipe.refine.steps:
            record["refiner_deepened_from_steps"] = k
        if src.cfg.output != recipe.refine.output:
            record["refiner_output_from"] = src.cfg.output
    return model, record


def _build_model(recipe: TrainRecipe, tensor_size: int, aperture: int, init: Path | None, device):
    """The recipe's U-Net (seeded), from ``--init`` weights of the same architecture when given; and the
    init's record for the model card."""
    import torch

    cfg = UNetConfig(8, recipe.base, recipe.depth, tensor_size, aperture, recipe.norm, recipe.output)
    torch.manual_seed(recipe.seed)
    model = build_unet(cfg).to(device)
    if init is None:
        return model, None
    src, card = load_model(init)
    record = {"path": str(init), "weights_sha256": card.get("weights_sha256"), "epoch": card.get("epoch")}
    a, b = asdict(src.config), asdict(cfg)
    factor = cfg.base // src.config.base if src.config.base else 0
    if (a != b and factor >= 2 and factor * src.config.base == cfg.base
            and {k: v for k, v in a.items() if k != "base"} == {k: v for k, v in b.items() if k != "base"}):
        # a narrower U-Net of the same shape: widened to the recipe's filters computing the same function,
        # perturbed by 1 % so that the new filters learn (seeded by the recipe)
        src = widen_unet(src, factor, noise=0.01, seed=recipe.seed)
        record["widened_from_base"] = a["base"]
    elif a != b and {**a, "output": b["output"]} == b and a["output"] == "phase":
        # a phase U-Net into a field one: its weights, the field head at zero (the same corrections)
        record["output_from"] = "phase"
        model.load_state_dict({**model.state_dict(), **src.state_dict()})
        return model, record
    elif a != b:
        raise ValidationError(f"--init {init}: architecture {a} differs from the recipe's {b} (a U-Net of the "
                              f"same shape with a whole fraction of its filters is widened; a phase U-Net "
                              f"starts a field one)")
    model.load_state_dict(src.state_dict())
    return model, record


class _BatchLoss:
    """A batch's loss by the name of the epoch's loss (:data:`~.losses.LOSSES`), and its training NPiB for
    the end-to-end one; the bucket operators of the "quadratic" mode are kept here, per sample."""

    def __init__(self, pib, stored: bool, quadratic: bool, device):
        self.pib, self.stored, self.quadratic, self.device = pib, stored, quadratic, device
        self.ops: dict[int, object] = {}

    def __call__(self, name: str, phi, b: dict, rec):
        return LOSSES[name].fn(self, phi, b, rec)


def _restore(ckpt: Path, model, opt, sched, device) -> tuple[list, float, int]:
    """Model, optimiser, scheduler and torch RNG from a checkpoint; returns (history, best, next epoch)."""
    import torch

    st = _load_checkpoint(ckpt, device)
    try:
        model.load_state_dict(st["model"])
        opt.load_state_dict(st["optimizer"])
        sched.load_state_dict(st["scheduler"])
        torch.set_rng_state(st["rng"]["torch"])
        return json.loads(st["history"]), float(st["best"]), int(st["epoch"]) + 1
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ValidationError(f"{ckpt}: does not fit this recipe's model and optimiser (another architecture? "
                              f"{str(exc).strip().splitlines()[-1].strip()[:120]})") from None


def _load_checkpoint(ckpt: Path, device) -> dict:
    """A checkpoint written by :func:`_save_checkpoint` (``weights_only``: nothing is unpickled); a truncated,
    foreign or empty file is one line."""
    import torch

    try:
        st = torch.load(ckpt, map_location=device, weights_only=True)
    except Exception as exc:  # damaged or foreign bytes: torch's weights-only unpickler raises many kinds
        why = (str(exc).strip().splitlines() or [exc.__class__.__name__])[0][:100]
        raise ValidationError(f"{ckpt}: not a readable checkpoint (truncated or foreign: {why})") from None
    if not isinstance(st, dict) or not {"model", "optimizer", "scheduler", "rng", "history", "best", "epoch"} <= set(st):
        raise ValidationError(f"{ckpt}: not a metadesign training checkpoint")
    return st


def _write_metrics(run: Path, history: list[dict]) -> None:
    atomic_write_text(run / "metrics.json", json.dumps(history, indent=1, default=float))
    cols = sorted({k for h in history for k in h})
    with atomic_path(run / "metrics.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols)
            w.writeheader()
            w.writerows(history)
    try:
        _plot_curves(run, history)
    except Exception:  # a figure must never kill a training run
        pass


def _plot_curves(run: Path, history: list[dict]) -> None:
    plt = pyplot()
    ep = [h["epoch"] for h in history]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for name in sorted({h["loss_name"] for h in history}):
        xs = [h["epoch"] for h in history if h["loss_name"] == name]
        a1.plot(xs, [h["train_loss"] for h in history if h["loss_name"] == name], "o-", ms=3, label=f"train ({name})")
    a1.plot(ep, [h["val_loss"] for h in history], "s-", ms=3, label="val (-log NPiB)")
    a1.set(xlabel="epoch", ylabel="loss", title="losses")
    a1.legend(fontsize=8)
    a2.plot(ep, [h["val_npib"] for h in history], "o-", ms=3, label="U-Net")
    a2.plot(ep, [h["val_npib_phase_conjugate"] for h in history], "--", label="phase conjugate")
    a2.plot(ep, [h["val_npib_none"] for h in history], ":", label="uncorrected")
    a2.set(xlabel="epoch", ylabel="mean NPiB (validation)", title="normalised power in bucket")
    a2.legend(fontsize=8)
    save_figure(fig, run / "curves.png")

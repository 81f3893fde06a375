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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..cliutil import progress_bar
from ..config import ConfigError
from ..io import atomic_path, atomic_write_text, claim
from ..outputs import Input, product
from ..plotting import pyplot, save_figure
from ..validation import ValidationError, check_memory
from .codesign import build_codesign, diversity_record
from .data import PSFDataset
from .dataset_store import load_device
from .losses import LOSSES, PiB
from .metrics import captured_fraction, npib_rows
from .linear import LinearReconstructor
from .modal_net import ModalNet, ModalNetConfig, commands_record, crop_to_window, modal_basis, window_reconstructor
from .model import UNetConfig, build_unet, check_sizes, load_model, save_model, widen_unet
from .operators import has_operators
from .refine import build_refiner, deepen_refiner, load_network, load_refiner, save_refiner
from .train_recipe import SECTIONS, TrainRecipe, load_train_recipe, train_recipe_from_dict

__all__ = ["TrainRecipe", "load_train_recipe", "train_recipe_from_dict", "train", "pick_device"]


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
            r = npib_rows(pib, model(x), scr, b["received"].to(device), mirror=b.get("mirror"))
            out["unet"].append(r["estimate"].cpu())
            out["none"].append(r["none"].cpu())
            out["phase_conjugate"].append(r["phase_conjugate"].cpu())
            out["index"].append(b["index"])
            if progress:
                progress(sum(len(x) for x in out["index"]), len(ds))
    return {k: torch.cat(v).numpy() for k, v in out.items()}


def train(recipe: TrainRecipe, run: Path, dataset: Path | None = None, resume: bool = False,
          init: Path | None = None, log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """Train ``recipe`` into the run folder ``run``; returns the final report (rank 0).  Rank 0 holds the
    run folder's lock while it trains: a second run into the same folder is refused.  ``recipe.max_steps``
    (``--max-steps``) stops the run after that many optimiser steps."""
    run = Path(run)
    rank = int(os.environ.get("RANK", "0")) if int(os.environ.get("WORLD_SIZE", "1")) > 1 else 0
    inputs = {"the dataset": Input(dataset or recipe.dataset, members=None) if (dataset or recipe.dataset) else None,
              "--init": init, "refine.unet": recipe.refine_unet, "refine.init": recipe.refine_init,
              "train.teacher": recipe.teacher,
              "the recipe": recipe.source}
    with product(run, "training-run", inputs) if rank == 0 else claim(run):
        return _train(recipe, run, dataset, resume, init, log, progress)


@dataclass
class _Training:
    """A training run between its epochs: the recipe and run folder, the model with its optimiser and
    schedule, the splits, the loss, the process's place (rank, world size), the history and the best
    validation NPiB so far."""

    recipe: TrainRecipe
    run: Path
    ckpt: Path
    dataset: Path
    model: object
    opt: object
    sched: object
    tr: object  # PSFDataset (train)
    va: object  # PSFDataset (val)
    pib: object
    batch_loss: object
    device: object
    init_card: dict | None
    log: Callable[[str], None]
    progress: bool
    stored: bool
    quadratic: bool
    rank: int = 0
    world: int = 1
    history: list = field(default_factory=list)
    best: float = -math.inf
    steps: int = 0


def _train(recipe: TrainRecipe, run: Path, dataset: Path | None, resume: bool, init: Path | None,
           log: Callable[[str], None], progress: bool) -> dict:
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
    tr, va, mode, any_pib = _splits(recipe, dataset)
    quadratic = mode == "quadratic" and any_pib
    stored = mode == "stored" and any_pib
    c0, a = tr.crop()
    if recipe.refine is not None:
        model, init_card = _build_refiner(recipe, dataset, tr.info.tensor_size, a, init, device)
    else:
        model, init_card = _build_model(recipe, tr.info.tensor_size, a, init, device, dataset)
        if recipe.codesign is not None:
            model = build_codesign(model, recipe.codesign, dataset, recipe.noise_percent).to(device)
    pib = PiB(tr.scenario(), c0, a, device)
    if quadratic:
        n_ap = int(pib.ap.sum())
        check_memory("train.pib_operator = \"quadratic\"", len(tr) * len(pib.bucket) * n_ap * 8,
                     "use pib_operator = \"split_step\" or data.train_limit")
    opt, sched = _optimiser(recipe, model)
    teacher = None
    if recipe.teacher is not None:
        teacher, tcard = load_network(recipe.teacher, str(device))
        check_sizes(getattr(teacher, "unet", teacher).config, tr.info.tensor_size, a, f"train.teacher {recipe.teacher}")
        init_card = {**(init_card or {}), "teacher": {"path": str(recipe.teacher),
                                                      "weights_sha256": tcard.get("weights_sha256")}}
    st = _Training(recipe, run, ckpt, dataset, model, opt, sched, tr, va, pib,
                   _BatchLoss(pib, stored, quadratic, device, teacher),
                   device, init_card, log, progress, stored, quadratic, rank, world)
    start = 0
    if resume:
        st.history, st.best, start = _restore(ckpt, model, opt, sched, device)
        sched.step_size = recipe.lr_halve_every  # the recipe's schedule wins over the checkpoint's
        log(f"resumed {run} at epoch {start}")
    ddp_model = model
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel as DDP

        ddp_model = DDP(model, device_ids=[device.index] if device.type == "cuda" else None)
    sampler = torch.utils.data.distributed.DistributedSampler(tr, num_replicas=world, rank=rank, shuffle=True,
                                                              seed=recipe.seed, drop_last=True)
    run.mkdir(parents=True, exist_ok=True) if rank == 0 else None
    t_start = time.perf_counter()
    for epoch in range(start, recipe.epochs):
        stop = _epoch(st, ddp_model, sampler, epoch)
        if world > 1:
            import torch.distributed as dist

            dist.barrier()
        if stop or (recipe.max_minutes and time.perf_counter() - t_start > 60 * recipe.max_minutes):
            break
    report = {"run": str(run), "epochs_done": len(st.history), "history": st.history, "best_val_npib": st.best,
              "world_size": world, "device": str(device), "pib_operator": mode if any_pib else None}
    if world > 1:
        import torch.distributed as dist

        dist.destroy_process_group()
    return report


def _splits(recipe: TrainRecipe, dataset: Path):
    """(train split, validation split, pib operator mode, whether any epoch's loss is end-to-end), checked:
    a validation split, one batch of training samples, the stored operators the mode needs."""
    noise = {} if recipe.codesign is not None else recipe.noise()  # co-design: noise on its own renderings
    tr = PSFDataset(dataset, "train", **noise, noise_seed=recipe.seed,
                    limit=recipe.train_limit or None)
    any_pib = any(LOSSES[recipe.loss_at(e)].end_to_end for e in range(recipe.epochs))
    mode = _pib_mode(recipe, tr)
    if mode == "stored" and any_pib:
        tr.require_operators("train")
    va = PSFDataset(dataset, "val", **noise, noise_seed=recipe.seed + 1,
                    limit=recipe.val_limit or None, screens=True)
    if len(va) == 0:
        raise ValidationError(f"{dataset}: the validation split is empty (training keeps the model with the best "
                              "validation NPiB): give the dataset a validation fraction or more samples")
    if len(tr) < recipe.batch:
        raise ValidationError(f"{dataset}: {len(tr)} training samples, fewer than one batch ({recipe.batch})")
    return tr, va, mode, any_pib


def _optimiser(recipe: TrainRecipe, model):
    """AdamW over the trainable parameters (co-design: the diversity at its own rate, without weight decay)
    and the step schedule that halves the rate."""
    import torch

    if recipe.codesign is not None:  # the diversity at its own rate, without weight decay
        groups = [{"params": [p for p in model.unet.parameters() if p.requires_grad]},
                  {"params": [p for p in model.twin.parameters() if p.requires_grad], "lr": recipe.codesign.lr,
                   "weight_decay": 0.0}]
    else:
        groups = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(groups, lr=recipe.lr, weight_decay=recipe.weight_decay)
    return opt, torch.optim.lr_scheduler.StepLR(opt, step_size=recipe.lr_halve_every, gamma=0.5)


def _epoch(st: _Training, ddp_model, sampler, epoch: int) -> bool:
    """One epoch: its batches, the schedule's step and (rank 0) :func:`_end_epoch`; whether the run stops
    (``max_steps`` reached)."""
    import torch

    recipe, model, tr, rank = st.recipe, st.model, st.tr, st.rank
    loss_name = recipe.loss_at(epoch)
    e2e = LOSSES[loss_name].end_to_end
    tr.screens = e2e and not st.stored and not (st.quadratic and len(st.batch_loss.ops) >= len(tr))
    tr.operators = st.stored and e2e
    tr.set_epoch(epoch)
    sampler.set_epoch(epoch)
    if recipe.codesign is not None:  # the rendered noise: the same draws after a resume, per rank
        model.seed_noise(int(np.random.SeedSequence([recipe.seed, epoch, rank]).generate_state(1)[0]))
    loader = torch.utils.data.DataLoader(tr, batch_size=recipe.batch // st.world, sampler=sampler,
                                         num_workers=recipe.loader_workers, collate_fn=_collate,
                                         drop_last=True, persistent_workers=False)
    ddp_model.train()
    t0 = time.perf_counter()
    tot, nb, npib_tr = 0.0, 0, []
    # a bar on a terminal, a line every 30 s in a log file or CI (cliutil.progress_bar)
    bar = progress_bar(f"epoch {epoch + 1}/{recipe.epochs} ({loss_name})", unit="step") \
        if st.progress and rank == 0 else None
    for b in loader:
        lv, npib = _step(st, ddp_model, b, loss_name)
        if npib is not None:
            npib_tr.append(npib.detach().cpu())
        if not math.isfinite(lv):
            raise ValidationError(f"train: the {loss_name} loss is {lv} at epoch {epoch + 1}, step {nb + 1} (the "
                                  "run diverged): lower train.lr, or --resume from the last checkpoint")
        tot += lv
        nb += 1
        st.steps += 1
        if bar is not None:
            bar(nb, len(loader))
        if recipe.max_steps is not None and st.steps >= recipe.max_steps:
            break
    st.sched.step()
    t_train = time.perf_counter() - t0
    rec_row = {"epoch": epoch + 1, "loss_name": loss_name, "train_loss": tot / max(nb, 1),
               "lr": st.opt.param_groups[0]["lr"], "train_seconds": t_train,
               "train_npib": float(torch.cat(npib_tr).mean()) if npib_tr else None}
    if rank == 0:
        _end_epoch(st, rec_row, t0)
    return recipe.max_steps is not None and st.steps >= recipe.max_steps


def _step(st: _Training, ddp_model, b: dict, loss_name: str):
    """One optimiser step on batch ``b``: (its loss as a float, its training NPiB or None).  A non-finite
    loss is not stepped on (the caller stops the run)."""
    import torch

    recipe, device = st.recipe, st.device
    x = b[getattr(st.model, "input_key", "psf")].to(device, non_blocking=True)
    rec = b["received"].to(device)
    deep = recipe.refine is not None and recipe.refine_deep > 0
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
        phi = ddp_model(x, all_steps=True) if deep else ddp_model(x)
    if deep:  # deep supervision: every step's estimate is an estimate (NPiB rises with K; early exit)
        loss, npib = st.batch_loss(loss_name, phi[-1].float(), b, rec)
        for p_k in phi[1:-1]:
            loss = loss + recipe.refine_deep * st.batch_loss(loss_name, p_k.float(), b, rec)[0] / (len(phi) - 2)
    else:
        loss, npib = st.batch_loss(loss_name, phi.float(), b, rec)
    if recipe.codesign is not None:
        loss = loss + st.model.penalty()
    lv = float(loss.detach())
    if math.isfinite(lv):
        st.opt.zero_grad(set_to_none=True)
        loss.backward()
        st.opt.step()
    return lv, npib


def _end_epoch(st: _Training, rec_row: dict, t0: float) -> None:
    """Rank 0 after an epoch: validation (the same noise every epoch), the best model by validation NPiB
    with its card, the checkpoint, metrics and curves; updates ``st.best`` and ``st.history``."""
    import torch

    recipe, va = st.recipe, st.va
    epoch = rec_row["epoch"] - 1
    va.set_epoch(0)  # the same validation noise every epoch: comparable numbers
    ev = evaluate_split(st.model, va, st.pib, st.device)
    gain = captured_fraction(ev["none"], ev["unet"], ev["phase_conjugate"])
    rec_row |= {"val_npib": float(ev["unet"].mean()), "val_npib_none": float(ev["none"].mean()),
                "val_npib_phase_conjugate": float(ev["phase_conjugate"].mean()),
                "val_captured_fraction": float(gain), "val_loss": float(-np.log(np.maximum(ev["unet"], 1e-12)).mean()),
                "epoch_seconds": time.perf_counter() - t0}
    if not math.isfinite(rec_row["val_npib"]):
        raise ValidationError(f"train: validation NPiB is {rec_row['val_npib']} at epoch {epoch + 1} (non-finite "
                              "model output): lower train.lr, or --resume from the last checkpoint")
    st.history.append(rec_row)
    is_best = rec_row["val_npib"] > st.best
    if is_best:
        st.best = rec_row["val_npib"]
        _save_best(st, rec_row)
    _save_checkpoint(st.ckpt, {"model": st.model.state_dict(), "optimizer": st.opt.state_dict(),
                               "scheduler": st.sched.state_dict(), "rng": {"torch": torch.get_rng_state()},
                               "history": json.dumps(st.history), "best": st.best, "epoch": epoch,
                               "recipe": json.dumps(recipe.raw, default=str)})
    _write_metrics(st.run, st.history)
    st.log(f"epoch {epoch + 1}/{recipe.epochs} {rec_row['loss_name']}: train {rec_row['train_loss']:.4f}, val NPiB "
           f"{rec_row['val_npib']:.3f} (none {rec_row['val_npib_none']:.3f}, conjugate "
           f"{rec_row['val_npib_phase_conjugate']:.3f}, captured {gain:.2f}), {rec_row['epoch_seconds']:.0f} s"
           + (" *" if is_best else ""))


def _save_best(st: _Training, rec_row: dict) -> None:
    """The best model so far as ``model.safetensors`` with its card (co-design: the U-Net alone, and its
    diversity as ``diversity.json``)."""
    recipe, model, attrs, init_card = st.recipe, st.model, st.tr.info.attrs, st.init_card
    save = save_model if recipe.refine is None else \
        (lambda m, p, c: save_refiner(m, p, init_card["path"], c))  # noqa: E731
    extra = {}
    if recipe.codesign is not None:  # the U-Net alone (for the co-designed device) and its diversity
        extra = {"codesign": diversity_record(model)}
        atomic_write_text(st.run / "diversity.json", json.dumps(extra["codesign"], indent=1))
    if isinstance(model, ModalNet):  # a real-time network: what its commands are
        extra = {"commands": commands_record(model.config)}
    save(getattr(model, "unet", model) if recipe.codesign is not None else model, st.run / "model.safetensors", {
        **extra,
        "dataset": {"path": str(st.dataset), "recipe_hash": attrs.get("recipe_hash"),
                    "layout_sha256": attrs["provenance"].get("layout_sha256")},
        "sensor": attrs["provenance"].get("sensor"),  # the camera the model was trained for
        "recipe": recipe.raw, "epoch": rec_row["epoch"], "metrics": rec_row, "init": init_card,
        "input_normalisation": attrs.get("normalisation"),
        "noise_percent": st.va.noise.describe()["gaussian_percent"], "noise": st.va.noise.describe(),
        "received_crop": attrs.get("received_crop"),
        "output": "received phase (vacuum removed) on the A x A receiver-aperture crop, rad; the "
                  "correction applied is its conjugate plus the focusing phase"})


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


def _build_modal(recipe: TrainRecipe, tensor_size: int, aperture: int, init: Path | None, device,
                 dataset: Path | None):
    """The recipe's real-time modal network (seeded); its linear path from the reconstructor measured on the
    dataset's device (``linear_init``; with a window: :func:`~.modal_net.window_reconstructor`) or from
    ``--init`` weights of the same architecture, or of the same one reading a wider square (cropped to the
    window: :func:`~.modal_net.crop_to_window`)."""
    import torch

    cfg = ModalNetConfig(input_size=tensor_size, aperture_size=aperture, **recipe.modal)
    torch.manual_seed(recipe.seed)
    model = ModalNet(cfg)
    record = None
    if init is not None:
        src, card = load_model(init)
        record = {"path": str(init), "weights_sha256": card.get("weights_sha256"), "epoch": card.get("epoch")}
        a, b = asdict(src.config), asdict(cfg)
        if a != b and {**a, "window": b["window"]} == b and b["window"] and src.config.side > cfg.side:
            src = crop_to_window(src, cfg.window)  # the same function on light inside the window
            record["windowed_from"] = a["window"]
        elif a != b:
            raise ValidationError(f"--init {init}: architecture {a} differs from the recipe's {b} (a modal "
                                  f"network reading a wider square starts a windowed one)")
        model.load_state_dict(src.state_dict())
    elif recipe.linear_init and cfg.bin:
        lin = LinearReconstructor.build(load_device(dataset), modal_basis(cfg), bin=cfg.bin)
        R, ref = (window_reconstructor(lin.interaction, lin.reference, cfg, lin.regularisation) if cfg.window
                  else (lin.R, lin.reference))
        model.set_linear(R, ref)
        record = {"linear_init": {"amplitude_rad": lin.amplitude, "regularisation": lin.regularisation,
                                  "bin": lin.bin, "basis": cfg.basis, "commands": lin.n_modes,
                                  "window": cfg.window}}
    return model.to(device), record


def _build_model(recipe: TrainRecipe, tensor_size: int, aperture: int, init: Path | None, device,
                 dataset: Path | None = None):
    """The recipe's network (seeded): a U-Net from ``--init`` weights of the same architecture when given
    (or the modal network, :func:`_build_modal`); and the init's record for the model card."""
    import torch

    if recipe.modal is not None:
        return _build_modal(recipe, tensor_size, aperture, init, device, dataset)
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

    def __init__(self, pib, stored: bool, quadratic: bool, device, teacher=None):
        self.pib, self.stored, self.quadratic, self.device = pib, stored, quadratic, device
        self.ops: dict[int, object] = {}
        self.teacher = teacher  # the distill loss's network (eval mode), and its estimates by sample index
        self.targets: dict[int, object] = {}

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

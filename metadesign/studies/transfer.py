"""Fab-to-lab transfer learning on captured frames (the paper's Fig. 4 protocol, at demo scale).

``metadesign transfer RECIPE`` runs, resuming whatever is finished:

1. **device + SLM screens**: a dataset recipe with a ``[fabrication]`` section renders the 'lab' device (the
   design as made: bias, jitter, corner rounding); its received phases are the screens the SLM shows;
2. **captures**: :func:`metadesign.studies.captures.synth_captures` through that device onto a misaligned
   camera (shift, rotation, magnification), with shot and read noise, dark offset and hot pixels, 16-bit;
   flat and dark frames; a manifest;
3. **import** against the nominal synthetic dataset the model was trained on (the user's reference):
   :func:`metadesign.reconstruction.captures.import_captures` (``propagation = "slm"``);
4. three models on the imported test split: the synthetic model **unadapted**, **fine-tuned** from it
   (``train --init``) on the small imported training split, and **from scratch** on that same split;
   NPiB of each, the uncorrected beam and the phase conjugate (1 through the SLM screen), captured fraction.

A finished step leaves its product (``OUT/device-dataset``, ``OUT/captures``, ``OUT/imported``,
``OUT/finetune/result.json``, ``OUT/scratch/result.json``); training resumes from its checkpoint."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..config import ConfigError, Param, Section, load_toml, parse
from .madewith import dataset_record, made_with, recipe_record
from ..io import atomic_write_text
from ..plotting import pyplot, save_figure
from ..execution import Execution
from ..reconstruction.captures import ImportOptions, import_captures
from ..reconstruction.dataset import build_dataset, dataset_recipe_from_dict, open_dataset
from ..reconstruction.evaluate import evaluate_model
from ..reconstruction.losses import LOSSES
from ..reconstruction.metrics import captured_fraction
from ..reconstruction.model import check_fits, load_model
from ..reconstruction.train import load_train_recipe, train
from ..sensing.camera import Alignment, CameraSpec
from ..tasks import TaskFolder, content_key, file_key
from .captures import CaptureSession, synth_captures
from .tolerance import check_architecture

__all__ = ["run_transfer", "load_transfer_recipe"]

SECTIONS = (
    Section("dataset", ()),  # a dataset recipe's [dataset] (+ [fabrication]), checked by that recipe
    Section("fabrication", (), optional=True),
    Section("captures", (
        Param("reference", str, None, help="the nominal synthetic dataset the model was trained on"),
        Param("shift_px", list, [0.0, 0.0], lo=-200, hi=200),
        Param("rotation_deg", float, 0.0, lo=-10, hi=10),
        Param("scale", float, 1.0, lo=0.8, hi=1.25),
        Param("peak_counts", float, 40000.0, lo=1, hi=65535),
        Param("photons_at_peak", float, 20000.0, lo=0, hi=1e9),
        Param("read_noise_e", float, 5.0, lo=0, hi=1e4),
        Param("dark_counts", float, 100.0, lo=0, hi=65535),
        Param("hot_pixels", int, 20, lo=0, hi=100000),
        Param("format", str, "png", choices=["png", "tiff", "npy"]),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
    )),
    Section("evaluate", (Param("model", str, None),)),
    Section("finetune", (
        Param("train", str, None, help="training recipe whose [model] matches the model"),
        Param("epochs", int, 6, lo=1, hi=100000),
        Param("lr", float, 3e-4, lo=0, open_lo=True, hi=1),
        Param("loss", str, "pib", choices=list(LOSSES)),
        Param("noise_percent", float, 0.0, lo=0, hi=100),
    )),
    Section("scratch", (
        Param("epochs", int, 24, lo=1, hi=100000),
        Param("pretrain_epochs", int, 20, lo=0, hi=100000),
        Param("lr", float, 1e-3, lo=0, open_lo=True, hi=1),
    )),
)


@dataclass(frozen=True)
class TransferRecipe:
    source: Path
    raw: dict
    captures: dict
    reference: Path
    model: Path
    train: Path
    finetune: dict
    scratch: dict


def load_transfer_recipe(path: str | Path) -> TransferRecipe:
    path = Path(path)
    raw = load_toml(path)
    v = parse({k: x for k, x in raw.items() if k not in ("dataset", "fabrication")} | {"dataset": {}},
              SECTIONS, str(path))
    c, e, f = v["captures"], v["evaluate"], v["finetune"]
    for key, val in (("captures.reference", c["reference"]), ("evaluate.model", e["model"]),
                     ("finetune.train", f["train"])):
        if val is None:
            raise ConfigError(key, "missing")
    if len(c["shift_px"]) != 2:
        raise ConfigError("captures.shift_px", f"expected [dx, dy], got {c['shift_px']}")
    if "fabrication" not in raw:
        raise ConfigError("fabrication", "missing: the lab device is the design as made (bias_x_nm, ...)")
    if v["scratch"]["pretrain_epochs"] >= v["scratch"]["epochs"] and f["loss"] == "pib":
        raise ConfigError("scratch.pretrain_epochs", "must be < scratch.epochs (the last epochs use the PiB loss)")
    base = path.parent
    f = dict(f)
    return TransferRecipe(path, {"dataset": raw["dataset"], "fabrication": raw["fabrication"]}, c,
                          base / c["reference"], base / e["model"], base / f["train"], f, v["scratch"])


def _metrics(res: dict) -> dict:
    r = res["rows"][next(iter(res["rows"]))]
    none, unet, pc = (np.asarray(r[k]) for k in ("none", "unet", "phase_conjugate"))
    return {"n": int(len(unet)), "npib_none": float(none.mean()), "npib_unet": float(unet.mean()),
            "npib_unet_median": float(np.median(unet)), "npib_phase_conjugate": float(pc.mean()),
            "captured_fraction": captured_fraction(none, unet, pc),
            "npib_per_sample": [float(x) for x in unet]}


def run_transfer(recipe: TransferRecipe, out: Path, workers: int = 2, log: Callable[[str], None] = print,
                 progress=None) -> dict:
    out = Path(out)
    # every input checked before the device dataset is built (minutes)
    model, _ = load_model(recipe.model)
    check_fits(model, open_dataset(recipe.reference), f"model {recipe.model}")
    check_architecture(model.config, load_train_recipe(recipe.train), recipe.model, recipe.train)
    out.mkdir(exist_ok=True)
    rec_ds = dataset_recipe_from_dict(json.loads(json.dumps(recipe.raw)), "transfer-device", recipe.source)
    dev = out / "device-dataset"
    log("1/4 device (as made) and SLM screens ...")
    build_dataset(rec_ds, dev, workers=workers, log=log)
    cap = out / "captures"
    c = recipe.captures
    steps = TaskFolder(out / ".steps")
    # each step reruns exactly when what shapes it changed: the device dataset (its recipe hash), the camera
    k_cap = content_key(open_dataset(dev).attrs.get("recipe_hash"), c, __version__)

    def do_captures():
        log("2/4 synthetic captures ...")
        if cap.exists():  # captures of an interrupted step (ours: inside this study's folder)
            shutil.rmtree(cap)
        cam = CameraSpec(peak_counts=c["peak_counts"], photons_at_peak=c["photons_at_peak"],
                         read_noise_e=c["read_noise_e"], dark_counts=c["dark_counts"], hot_pixels=c["hot_pixels"],
                         seed=c["seed"])
        synth_captures(dev, dev, cap, Alignment(c["shift_px"][0], c["shift_px"][1], c["rotation_deg"], c["scale"]),
                       cam, CaptureSession(fmt=c["format"], seed=c["seed"]), progress=progress)
        return {}

    steps.step("captures", k_cap, do_captures, [cap / "manifest.csv"], clear=[cap])
    imp = out / "imported"
    k_imp = content_key(k_cap, file_key(Path(recipe.reference) / "zarr.json"))

    def do_import():
        log("3/4 import ...")
        rep_imp = import_captures(cap, imp, cap / "flat.csv", recipe.reference, sorted((cap / "dark").glob("*")),
                                  ImportOptions(overwrite=True), Execution(log=log))
        imp_rep = {k: rep_imp[k] for k in ("samples", "listed", "saturated", "calibration", "split_counts")}
        atomic_write_text(out / "import.json", json.dumps(imp_rep, indent=1))
        return imp_rep

    imp_rep, _ = steps.step("import", k_imp, do_import, [imp / "zarr.json"], clear=[imp])
    truth = json.loads((cap / "truth.json").read_text())
    log("4/4 models ...")
    res0 = evaluate_model(recipe.model, imp, "test", [0.0])
    rows = {"unadapted": _metrics(res0)}
    log(f"  unadapted: NPiB {rows['unadapted']['npib_unet']:.3f} (none {rows['unadapted']['npib_none']:.3f})")
    base = load_train_recipe(recipe.train)
    f, s = recipe.finetune, recipe.scratch
    runs = {
        "finetuned": ({"epochs": f["epochs"], "lr": f["lr"], "lr_halve_every": max(1, f["epochs"]), "loss": f["loss"],
                       "pretrain_epochs": 0}, recipe.model),
        "scratch": ({"epochs": s["epochs"], "lr": s["lr"], "lr_halve_every": max(1, s["epochs"] // 2),
                     "loss": f["loss"], "pretrain_loss": "phase", "pretrain_epochs": s["pretrain_epochs"]}, None),
    }
    curves = {}
    for name, (tr, init) in runs.items():
        run = out / name
        k_run = content_key(k_imp, tr, f["noise_percent"], file_key(recipe.train),
                            file_key(init) if init is not None else None)

        def do_run(name=name, tr=tr, init=init, run=run):
            tr_rec = base.derive(f"transfer-{name}", {"noise_percent": f["noise_percent"], "val_limit": 0}, **tr)
            resume = (run / "checkpoint.pt").exists()
            rep = train(tr_rec, run, dataset=imp, resume=resume,
                        init=None if (resume or init is None) else init, log=log, progress=True)
            r = _metrics(evaluate_model(run / "model.safetensors", imp, "test", [0.0]))
            r["epochs"] = rep["epochs_done"]
            r["train_samples"] = int(len(open_dataset(imp).indices("train")))
            atomic_write_text(run / "result.json", json.dumps(r, indent=1))  # for a reader of the folder
            return json.loads(json.dumps(r, default=float))

        r, _ = steps.step(name, k_run, do_run, [run / "model.safetensors"], clear=[run])
        rows[name] = r
        hist = run / "metrics.json"
        if hist.exists():
            curves[name] = json.loads(hist.read_text())
        log(f"  {name}: NPiB {r['npib_unet']:.3f}")
    rep = {"rows": {k: {kk: vv for kk, vv in v.items() if kk != "npib_per_sample"} for k, v in rows.items()},
           "truth_alignment": truth["alignment"], "fitted_alignment": imp_rep["calibration"]["alignment"],
           "import": imp_rep, "model": str(recipe.model), "fabrication": recipe.raw["fabrication"],
           "made_with": made_with(recipe.model, dataset_recipe=rec_ds, recipe=recipe.source,
                                  reference=dataset_record(recipe.reference),
                                  train_recipe=recipe_record(recipe.train))}
    atomic_write_text(out / "transfer.json", json.dumps(rep, indent=1))
    rep["figure"] = str(plot_transfer(rows, curves, out / "transfer.png", rep))
    return rep


def plot_transfer(rows: dict, curves: dict, path: Path, rep: dict) -> Path:
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    names = [("unadapted", "synthetic model,\nunadapted"), ("scratch", "from scratch\n(same captures)"),
             ("finetuned", "fine-tuned from\nthe synthetic model")]
    data = [rows[k]["npib_per_sample"] for k, _ in names if k in rows]
    a1.boxplot(data, showmeans=True)
    a1.set_xticks(range(1, len(data) + 1), [lab for k, lab in names if k in rows])
    none = next(iter(rows.values()))["npib_none"]
    a1.axhline(none, color="k", ls=":", label=f"uncorrected ({none:.3f})")
    a1.axhline(1.0, color="g", ls=":", label="phase conjugate (1 through the SLM)")
    for i, (k, _) in enumerate([n for n in names if n[0] in rows], 1):
        a1.text(i, 1.02, f"{rows[k]['npib_unet']:.3f}", ha="center", fontsize=9)
    a1.set(ylabel="NPiB (imported test split)", ylim=(0, 1.1),
           title=f"transfer to captured frames ({rows['unadapted']['n']} test captures)")
    a1.legend(fontsize=8, loc="lower right")
    for name, hist in curves.items():
        ep = [h["epoch"] for h in hist]
        a2.plot(ep, [h["val_npib"] for h in hist], "o-", ms=3, label=name)
    a2.axhline(rows["unadapted"]["npib_unet"], color="k", ls="--", lw=1, label="unadapted")
    al = rep["fitted_alignment"]
    a2.set(xlabel="epoch", ylabel="validation NPiB",
           title=f"relay fitted: ({al['shift_x_px']:+.2f}, {al['shift_y_px']:+.2f}) px, "
                 f"{al['rotation_deg']:+.2f} deg, x{al['scale']:.4f}")
    a2.legend(fontsize=8)
    return save_figure(fig, path)

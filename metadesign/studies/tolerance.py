"""Reconstruction-level fabrication tolerance: how much of the wavefront-sensing performance of a model
trained on the nominal device survives each fabrication error, and how much a short fine-tune recovers.

One-at-a-time sweeps around the nominal device (width bias, jitter, corner rounding: the knobs of
:class:`~metadesign.sensing.transmission.Perturbation`).  For every case a dataset is rendered through the
perturbed layout with the **same root seed** (the same turbulence, Rytov numbers and splits in every case;
a root seed other than the nominal model's training set, so no test sample was seen in training).  The
nominal model is evaluated on the case's test split (NPiB of the U-Net, the uncorrected beam and the phase
conjugate, captured fraction, gain), then fine-tuned from its weights on the case's small training split
(``train --init``: the recovery a fab engineer can buy with one short retraining) and evaluated again.

Finished cases are kept (``OUT/case-*/result.json``); a re-run resumes the rest (datasets and training
resume by themselves)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..config import ConfigError, Param, Section, load_toml, parse
from .madewith import made_with, recipe_record
from ..io import atomic_path, atomic_write_text
from ..plotting import pyplot, save_figure
from ..reconstruction.dataset import build_dataset, dataset_recipe_from_dict, expected_sizes, open_dataset
from ..reconstruction.evaluate import evaluate_model
from ..reconstruction.losses import LOSSES
from ..reconstruction.metrics import captured_fraction, gain
from ..reconstruction.model import check_sizes, load_model
from ..reconstruction.train import load_train_recipe, train
from ..paths import resolve_against
from ..tasks import TaskFolder, content_key, file_key, path_key
from ..validation import ValidationError

__all__ = ["run_tolerance", "load_tolerance_recipe", "TOLERANCE_SECTIONS"]

TOLERANCE_SECTIONS = (
    Section("dataset", ()),  # a dataset recipe's [dataset], checked by that recipe
    Section("cases", (
        Param("bias_nm", list, [-10.0, -5.0, 0.0, 5.0, 10.0], lo=-200, hi=200),
        Param("jitter_nm", list, [], lo=0, hi=100),
        Param("corner_nm", list, [], lo=0, hi=500),
        Param("height_nm", list, [], lo=-500, hi=500, help="etch depth errors (need fab_library)"),
        Param("sidewall_deg", list, [], lo=60, hi=90, help="sidewall angles (need fab_library)"),
        Param("height_gradient_nm", list, [], lo=-500, hi=500,
              help="across-wafer etch depth gradients: the error at the aperture's +x edge (need fab_library)"),
        Param("sidewall_gradient_deg", list, [], lo=-30, hi=30, help="across-wafer sidewall gradients"),
        Param("fab_library", str, None, help="library with height / sidewall axes (relative to the recipe)"),
        Param("supercell", bool, False, help="add the case 'supercell': the nominal widths with the pillars' "
                                             "supercell coupling (the model fitted against the library)"),
        Param("seed", int, 0, lo=0, hi=2**63 - 1),
    )),
    Section("evaluate", (
        Param("model", str, None, help="the nominal model (relative to the recipe)"),
        Param("noise_percent", float, 5.0, lo=0, hi=100),
    )),
    Section("finetune", (
        Param("train", str, None, help="training recipe whose [model] matches the model and whose [train] is used"),
        Param("epochs", int, 3, lo=0, hi=100000),
        Param("lr", float, 3e-4, lo=0, open_lo=True, hi=1),
        Param("loss", str, "pib", choices=list(LOSSES)),
        Param("bias_nm", list, None, lo=-200, hi=200, help="cases to fine-tune (default: every non-nominal one)"),
    )),
)


@dataclass(frozen=True)
class ToleranceRecipe:
    source: Path
    dataset: dict  # raw [dataset] section
    cases: list  # [(label, bias_nm, jitter_nm, corner_nm, height_nm, sidewall_deg, height_grad_nm, sidewall_grad_deg)]
    seed: int
    model: Path
    noise_percent: float
    train: Path
    epochs: int
    lr: float
    loss: str
    finetune_bias: list | None
    fab_library: str | None = None


def load_tolerance_recipe(path: str | Path) -> ToleranceRecipe:
    path = Path(path)
    raw = load_toml(path)
    v = parse({k: x for k, x in raw.items() if k != "dataset"} | {"dataset": {}}, TOLERANCE_SECTIONS, str(path))
    c, e, f = v["cases"], v["evaluate"], v["finetune"]
    for key, sec in (("evaluate.model", e["model"]), ("finetune.train", f["train"])):
        if sec is None:
            raise ConfigError(key, "missing")
    # lengths load in metres (config units), percentages stay percent; cases are kept in nm for the tables
    nm = [round(float(b) * 1e9, 6) for b in c["bias_nm"]]
    z = (0.0, 90.0, 0.0, 0.0)  # no etch depth / sidewall perturbation
    cases = [("nominal", 0.0, 0.0, 0.0, *z)]
    cases += [(f"bias{b:+g}nm", b, 0.0, 0.0, *z) for b in nm if b != 0]
    cases += [(f"jitter{j * 1e9:g}nm", 0.0, round(j * 1e9, 6), 0.0, *z) for j in c["jitter_nm"] if j != 0]
    cases += [(f"corner{r * 1e9:g}nm", 0.0, 0.0, round(r * 1e9, 6), *z) for r in c["corner_nm"] if r != 0]
    cases += [(f"height{h * 1e9:+g}nm", 0.0, 0.0, 0.0, round(h * 1e9, 6), 90.0, 0.0, 0.0)
              for h in c["height_nm"] if h != 0]
    cases += [(f"sidewall{a:g}deg", 0.0, 0.0, 0.0, 0.0, float(a), 0.0, 0.0) for a in c["sidewall_deg"] if a != 90]
    cases += [(f"heightgrad{g * 1e9:+g}nm", 0.0, 0.0, 0.0, 0.0, 90.0, round(g * 1e9, 6), 0.0)
              for g in c["height_gradient_nm"] if g != 0]
    cases += [(f"sidewallgrad{g:+g}deg", 0.0, 0.0, 0.0, 0.0, 90.0, 0.0, float(g))
              for g in c["sidewall_gradient_deg"] if g != 0]
    if c["supercell"]:
        cases.append(("supercell", 0.0, 0.0, 0.0, *z))
    if any(x[4] or x[5] != 90 or x[6] or x[7] for x in cases) and not c["fab_library"]:
        raise ConfigError("cases.fab_library", "missing: height_nm / sidewall_deg cases need a library with fab axes")
    base = path.parent
    ft = None if f["bias_nm"] is None else [round(float(b) * 1e9, 6) for b in f["bias_nm"]]
    return ToleranceRecipe(path, {"dataset": raw.get("dataset", {})}, cases, c["seed"], base / e["model"],
                           e["noise_percent"], base / f["train"], f["epochs"], f["lr"], f["loss"], ft,
                           c["fab_library"])


def _metrics(res: dict, key: str) -> dict:
    r = res["rows"][key]
    none, unet, pc = r["none"], r["unet"], r["phase_conjugate"]
    return {"n": int(len(unet)), "npib_none": float(np.mean(none)), "npib_unet": float(np.mean(unet)),
            "npib_phase_conjugate": float(np.mean(pc)),
            "captured_fraction": captured_fraction(none, unet, pc), "gain_median": float(np.median(gain(none, unet)))}


def check_architecture(cfg, train_recipe, model_path, train_path) -> None:
    """The fine-tuning recipe must build the model's architecture (``train --init`` refuses otherwise)."""
    want = (train_recipe.base, train_recipe.depth, train_recipe.norm)
    have = (cfg.base, cfg.depth, cfg.norm)
    if want != have:
        raise ValidationError(f"{train_path}: [model] base/depth/norm {want} differ from the model {model_path}'s {have}")


def _file_or_name(recipe: ToleranceRecipe, p) -> dict | None:
    """A path of the recipe by its content (its name when absent)."""
    q = resolve_against(recipe.source.parent, p)
    return None if q is None else path_key(q)


def run_tolerance(recipe: ToleranceRecipe, out: Path, workers: int = 2, log: Callable[[str], None] = print) -> dict:
    out = Path(out)
    base_train = load_train_recipe(recipe.train)
    # every input checked before the first dataset is built (minutes each)
    model, _ = load_model(recipe.model)
    ds0 = dataset_recipe_from_dict(json.loads(json.dumps(recipe.dataset)), "tolerance-check", recipe.source)
    check_sizes(model.config, *expected_sizes(ds0), f"model {recipe.model}")
    check_architecture(model.config, base_train, recipe.model, recipe.train)
    out.mkdir(exist_ok=True)
    rows = []
    steps = TaskFolder(out / ".steps")
    model_key = file_key(recipe.model)
    for label, b, j, c, hh, sw, hg, sg in recipe.cases:
        case = out / f"case-{label}"
        fab = {"bias_x_nm": b, "bias_y_nm": b, "jitter_nm": j, "corner_nm": c, "seed": recipe.seed}
        if label == "supercell":
            fab["coupling"] = "supercell"
        if hh or sw != 90 or hg or sg:
            fab.update({"height_nm": hh, "sidewall_deg": sw, "height_gradient_nm": hg, "sidewall_gradient_deg": sg,
                        "fab_library": recipe.fab_library})
        # the case reruns exactly when what shapes it changed (a recipe edit no longer reuses a stale case)
        key = content_key({"fabrication": {k: (_file_or_name(recipe, v) if k == "fab_library" else v)
                                           for k, v in fab.items()},
                           "layout": _file_or_name(recipe, ds0.layout),
                           "dataset": json.loads(json.dumps(recipe.dataset, default=str)), "model": model_key,
                           "noise_percent": recipe.noise_percent, "epochs": recipe.epochs, "lr": recipe.lr,
                           "loss": recipe.loss, "finetune_bias": recipe.finetune_bias, "train": file_key(recipe.train)},
                          __version__)

        def run_case(label=label, b=b, j=j, c=c, hh=hh, sw=sw, hg=hg, sg=sg, fab=fab, case=case):
            case.mkdir(exist_ok=True)
            ds_rec = ds0.with_fabrication(f"tolerance-{label}", **fab)
            log(f"{label}: dataset ...")
            build_dataset(ds_rec, case / "dataset", workers=workers, log=log, overwrite=True)
            res = evaluate_model(recipe.model, case / "dataset", "test", [recipe.noise_percent])
            key0 = next(iter(res["rows"]))
            row = {"case": label, "bias_nm": b, "jitter_nm": j, "corner_nm": c, "before": _metrics(res, key0),
                   "coupling": "supercell" if label == "supercell" else "lpa"}
            if hh or sw != 90 or hg or sg:
                row.update({"height_nm": hh, "sidewall_deg": sw, "height_gradient_nm": hg,
                            "sidewall_gradient_deg": sg})
            log(f"{label}: nominal model NPiB {row['before']['npib_unet']:.3f} "
                f"(captured {row['before']['captured_fraction']:.2f})")
            fine = label != "nominal" and recipe.epochs > 0 and (
                recipe.finetune_bias is None or b in recipe.finetune_bias or label == "supercell")
            if fine:
                tr_rec = base_train.derive(f"finetune-{label}", {"noise_percent": recipe.noise_percent,
                                                                 "val_limit": 0},
                                           epochs=recipe.epochs, lr=recipe.lr, lr_halve_every=max(1, recipe.epochs),
                                           loss=recipe.loss, pretrain_epochs=0)
                run = case / "finetune"
                resume = (run / "checkpoint.pt").exists()
                rep = train(tr_rec, run, dataset=case / "dataset",
                            resume=resume, init=None if resume else recipe.model, log=log, progress=True)
                res2 = evaluate_model(run / "model.safetensors", case / "dataset", "test", [recipe.noise_percent])
                row["after"] = _metrics(res2, next(iter(res2["rows"])))
                row["finetune"] = {"epochs": rep["epochs_done"], "loss": recipe.loss, "lr": recipe.lr,
                                   "train_samples": int(len(open_dataset(case / "dataset").indices("train")))}
                log(f"{label}: fine-tuned NPiB {row['after']['npib_unet']:.3f}")
            atomic_write_text(case / "result.json", json.dumps(row, indent=2))  # for a reader of the folder
            return row

        row, skipped = steps.step(f"case-{label}", key, run_case, clear=[case])
        if skipped:
            log(f"{label}: done before")
        rows.append(row)
    rep = {"rows": rows, "noise_percent": recipe.noise_percent, "model": str(recipe.model),
           "made_with": made_with(recipe.model, dataset_recipe=ds0, recipe=recipe.source,
                                  train_recipe=recipe_record(recipe.train))}
    atomic_write_text(out / "tolerance.json", json.dumps(rep, indent=2))
    _write_csv(rows, out / "tolerance.csv")
    rep["figure"] = str(plot_tolerance(rows, out / "tolerance.png", recipe.noise_percent))
    return rep


def _write_csv(rows, path: Path) -> None:
    import csv

    cols = ["npib_none", "npib_unet", "npib_phase_conjugate", "captured_fraction", "gain_median"]
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["case", "bias_nm", "jitter_nm", "corner_nm", "n"] + cols + [f"finetuned_{k}" for k in cols])
            for r in rows:
                a = r.get("after", {})
                w.writerow([r["case"], r["bias_nm"], r["jitter_nm"], r["corner_nm"], r["before"]["n"]]
                           + [f"{r['before'][k]:.5f}" for k in cols] + [f"{a[k]:.5f}" if k in a else "" for k in cols])


def plot_tolerance(rows, out: Path, noise: float) -> Path:
    plt = pyplot()
    bias = sorted([r for r in rows if r["jitter_nm"] == 0 and r["corner_nm"] == 0 and "height_nm" not in r
                   and r["case"] != "supercell"], key=lambda r: r["bias_nm"])
    other = [r for r in rows if r["jitter_nm"] or r["corner_nm"] or "height_nm" in r or r["case"] == "supercell"]
    nom = next((r for r in rows if r["case"] == "nominal"), None)
    tuned = any("after" in r for r in rows)
    if len(bias) < 2:  # no bias sweep to draw: the nominal device is one more bar
        fig, a2 = plt.subplots(figsize=(1.6 * (len(bias) + len(other)) + 3, 4.5), constrained_layout=True)
        other = bias + other
    else:
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True,
                                     gridspec_kw={"width_ratios": [3, 2]})
        x = [r["bias_nm"] for r in bias]
        a1.plot(x, [r["before"]["npib_unet"] for r in bias], "o-", label="U-Net trained on the nominal device")
        if tuned:
            fit = [r for r in bias if "after" in r or r["case"] == "nominal"]
            a1.plot([r["bias_nm"] for r in fit], [r.get("after", r["before"])["npib_unet"] for r in fit], "s--",
                    label="after fine-tuning on the perturbed device")
        a1.plot(x, [r["before"]["npib_phase_conjugate"] for r in bias], "g:", label="phase conjugate")
        a1.plot(x, [r["before"]["npib_none"] for r in bias], "k:", label="uncorrected")
        a1.set(xlabel="pillar width bias [nm] (both axes)", ylabel="mean NPiB (test split)",
               title=f"reconstruction-level fab tolerance (noise {noise:g} %)")
        a1.legend(fontsize=8)
    if other:
        lab = [r["case"] for r in other]
        xx = np.arange(len(other))
        if tuned:
            a2.bar(xx - 0.2, [r["before"]["npib_unet"] for r in other], 0.4, label="nominal model")
            a2.bar(xx + 0.2, [r.get("after", r["before"])["npib_unet"] for r in other], 0.4, label="fine-tuned")
        else:  # no case was fine-tuned (finetune.epochs = 0): one bar each, nothing called fine-tuned
            a2.bar(xx, [r["before"]["npib_unet"] for r in other], 0.5, label="nominal model")
        if nom:
            a2.axhline(nom["before"]["npib_unet"], color="k", ls="--", lw=1, label="nominal device")
            a2.axhline(nom["before"]["npib_phase_conjugate"], color="g", ls=":", lw=1, label="phase conjugate")
            a2.axhline(nom["before"]["npib_none"], color="k", ls=":", lw=1, label="uncorrected")
        a2.set_xticks(xx, lab, rotation=20)
        a2.set(ylabel="mean NPiB (test split)", title=f"fab cases (noise {noise:g} %)")
        a2.legend(fontsize=8, loc="lower right")
    else:
        a2.axis("off")
    return save_figure(fig, out)

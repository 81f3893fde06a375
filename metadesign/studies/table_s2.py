"""Table S2 (loss selection): the same data and U-Net trained end to end (PiB) and with the MSE phase
loss, each evaluated on its train and test splits."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from ..cards import model_card
from ..config import Param, Section, load_toml, parse
from ..io import atomic_write_text
from ..reconstruction.dataset import build_dataset, dataset_recipe_from_dict
from ..reconstruction.evaluate import evaluate_model
from ..reconstruction.model import UNetConfig, build_unet, save_model
from ..reconstruction.train import train, train_recipe_from_dict

__all__ = ["run_table_s2"]

SECTIONS = (
    Section("dataset", ()),  # the keys of a dataset recipe's [dataset], checked by that recipe
    Section("model", (Param("base", int, 8, lo=1, hi=256), Param("depth", int, 4, lo=2, hi=8))),
    Section("train", (
        Param("epochs", int, lo=1, hi=100000), Param("batch", int, 16, lo=1, hi=65536),
        Param("lr", float, 1e-3, lo=0, open_lo=True, hi=1), Param("weight_decay", float, 0.01, lo=0, hi=1),
        Param("lr_halve_every", int, 200, lo=1, hi=100000), Param("noise_percent", float, 0.0, lo=0, hi=100),
    )),
)


def run_table_s2(recipe_path: str | Path, out: Path, workers: int = 2, log: Callable[[str], None] = print) -> dict:
    recipe_path = Path(recipe_path)
    raw = load_toml(recipe_path)
    ds_raw = {"dataset": raw.get("dataset", {})}
    rest = {k: v for k, v in raw.items() if k != "dataset"}
    v = parse(rest | {"dataset": {}}, SECTIONS, str(recipe_path))
    ds_rec = dataset_recipe_from_dict(ds_raw, "table-s2-dataset", recipe_path)
    out = Path(out)
    out.mkdir(exist_ok=True)
    log("dataset ...")
    build_dataset(ds_rec, out / "dataset", workers=workers, log=log)
    t = v["train"]
    rows = []
    for name, loss in (("E2E", "pib"), ("MSE", "mse")):
        tr_raw = {"model": {"base": v["model"]["base"], "depth": v["model"]["depth"]},
                  "train": {"epochs": t["epochs"], "batch": t["batch"], "lr": t["lr"], "weight_decay": t["weight_decay"],
                            "lr_halve_every": t["lr_halve_every"], "loss": loss, "pretrain_epochs": 0, "seed": 0},
                  "data": {"noise_percent": t["noise_percent"]}}
        run = out / f"run-{name.lower()}"
        if (run / "checkpoint.pt").exists():
            rep = train(train_recipe_from_dict(tr_raw, name), run, dataset=out / "dataset", resume=True, log=log,
                        progress=True)
        else:
            rep = train(train_recipe_from_dict(tr_raw, name), run, dataset=out / "dataset", log=log, progress=True)
        # the last epoch's weights: Table S2 compares train and test of the trained model, not a val-selected one
        import torch

        st = torch.load(run / "checkpoint.pt", weights_only=True)
        m = build_unet(UNetConfig(**model_card(run / "model.safetensors")["architecture"]))
        m.load_state_dict(st["model"])
        save_model(m, run / "final.safetensors", {"loss": loss, "epochs": rep["epochs_done"]})
        for split in ("train", "test"):
            res = evaluate_model(run / "final.safetensors", out / "dataset", split, [0.0],
                                 limit=None if split == "test" else 400)
            r = res["rows"]["gaussian:0"]
            rows.append({"model": name, "split": split, "n": int(len(r["unet"])),
                         "pib_ratio": float(np.mean(r["unet"] / np.maximum(r["phase_conjugate"], 1e-12))),
                         "pib_ratio_of_means": float(np.mean(r["unet"]) / np.mean(r["phase_conjugate"])),
                         "npib_unet": float(np.mean(r["unet"])), "npib_none": float(np.mean(r["none"])),
                         "npib_phase_conjugate": float(np.mean(r["phase_conjugate"]))})
            log(f"{name} {split}: PiB ratio {rows[-1]['pib_ratio']:.3f}")
    rep = {"rows": rows, "samples": ds_rec.samples, "rytov": list(ds_rec.rytov_values or ds_rec.rytov_range),
           "epochs": t["epochs"], "paper": {"E2E": [0.963, 0.960], "MSE": [0.946, 0.715]}}
    atomic_write_text(out / "table-s2.json", json.dumps(rep, indent=2))
    return rep

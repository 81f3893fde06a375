"""Evaluation (stage 6c): per-sample normalised power in bucket of the uncorrected beam, the U-Net's
correction, the phase conjugate (true received phase, flat amplitude) and the complex conjugate, with
the same bucket and normalisation as the turbulence stage; residual phase RMS; summaries by Rytov bin
and noise level; Fig. 3b-d."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Callable

import numpy as np

from ..io import atomic_path
from ..optics.phase import branch_points, irrotational_phase
from ..plotting import pyplot, save_figure
from ..validation import ValidationError
from .codesign import codesign_for_evaluation
from .data import PSFDataset
from .frame_orientation import check_orientation_record
from .losses import PiB
from .metrics import EVAL_NOISE_SEED, captured_fraction, gain, npib_rows
from .model import check_fits
from .refine import load_network
from .train import _collate, pick_device

__all__ = ["evaluate_model", "summarise", "residual_rms", "plot_fig3"]

RYTOV_BINS = (0.0, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 10.0)


def residual_rms(phi_pred: np.ndarray, received: np.ndarray, ap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(RMS of the residual phase with piston and tip/tilt removed, RMS of its tip/tilt part), rad, per
    sample.  The residual ``phi_pred - angle(received)`` is taken on the unit circle (branch points make
    the received phase unwrappable): the piston is the angle of the mean phasor, the residual is then
    wrapped to (-pi, pi] and tip/tilt is its least-squares plane."""
    a = ap.shape[-1]
    yy, xx = np.mgrid[0:a, 0:a] - (a - 1) / 2
    X = np.stack([xx[ap], yy[ap]], 1).astype(np.float64)
    pinv = np.linalg.pinv(X)
    rms, tt = [], []
    for p, r in zip(phi_pred, received):
        d = np.exp(1j * (p[ap] - np.angle(r[ap])))
        d = np.angle(d * np.conj(d.mean()))
        coef = pinv @ d
        plane = X @ coef
        rms.append(np.sqrt(np.mean((d - plane) ** 2)))
        tt.append(np.sqrt(np.mean(plane**2)))
    return np.array(rms), np.array(tt)


def _noise_words(key: str) -> str:
    kind, _, v = key.partition(":")
    return f"sensor noise {v} % of peak" if kind == "gaussian" else f"{v} photo-electrons at the peak"


def training_noise(card: dict) -> str:
    """The training noise a model card records, for a title: "5 %" or "0-10 %"."""
    v = card.get("noise_percent", "?")
    return f"{v[0]:g}-{v[1]:g} %" if isinstance(v, list) else f"{v:g} %" if isinstance(v, (int, float)) else f"{v} %"


#: samples per evaluation batch
EVAL_BATCH = 16


def noise_levels_of(gaussian_percent=(0.0,), photons=None) -> list:
    """The ``noise_levels`` of :func:`evaluate_model` from the CLI's lists: Gaussian levels (% of peak),
    then shot + read noise levels (photo-electrons at the peak) as ``("photons", level)`` pairs."""
    return [*gaussian_percent, *(("photons", p) for p in (photons or []))]


def _levels(noise_levels) -> list[tuple[str, float]]:
    """``(kind, level)`` of each noise level: a number is a Gaussian level, a pair names its kind."""
    out = [(str(x[0]), float(x[1])) if isinstance(x, (tuple, list)) else ("gaussian", float(x)) for x in noise_levels]
    bad = next((k for k, _ in out if k not in ("gaussian", "photons")), None)
    if bad is not None:
        raise ValidationError(f"noise level kind {bad!r}: expected gaussian or photons")
    return out


def evaluate_model(model_path, dataset, split: str = "test", noise_levels=(0.0,), limit: int | None = None,
                   device: str | None = None, progress: Callable[[int, int], None] | None = None) -> dict:
    """Per-sample results for every noise level: a number is Gaussian sensor noise (% of each channel's
    peak), a pair ``("photons", n)`` shot + read noise instead (``n`` photo-electrons at the peak;
    :func:`noise_levels_of`)."""
    import torch

    dev = torch.device(device) if device else pick_device()
    model, card = load_network(model_path, device=str(dev))
    refines = "refine" in card  # rows: "unet" the refiner's estimate, "start" its U-Net's
    cd = None
    if card.get("codesign"):  # a co-design U-Net: its PSFs rendered by its own diversity from the received fields
        if any(kind == "photons" for kind, _ in _levels(noise_levels)):
            raise ValidationError(f"{model_path}: a co-design model is evaluated with Gaussian sensor noise only "
                                  "(its twin renders the noise the datasets draw); leave out --photons")
        cd = codesign_for_evaluation(model, card["codesign"], dataset, dev)
    rows: dict = {}
    levels = _levels(noise_levels)
    total = 0
    base = PSFDataset(dataset, split, limit=limit, screens=True)
    if len(base) == 0:
        raise ValidationError(f"{dataset}: the {split} split is empty")
    if base.loop_residuals:
        raise ValidationError(f"{dataset}: the {split} split holds {base.loop_residuals} closed-loop residual "
                              "beacons ([closed_loop]); evaluate on the test split (open loop)")
    check_orientation_record(base.info.attrs, dataset)  # captures: their flat's orientation checked at import
    check_fits(model, base.info, str(model_path))
    c0, a = base.crop()
    pib = PiB(base.scenario(), c0, a, dev)
    ap = pib.ap.cpu().numpy().astype(bool)
    n_total = len(base) * len(levels)
    examples: dict = {"phi": [], "received": []}
    for kind, level in levels:
        if cd is not None:  # the noise on the twin's renderings, the same draws at every evaluation
            cd.noise_percent = (level, level)
            cd.eval()
        ds = PSFDataset(dataset, split, gaussian_percent=level if kind == "gaussian" and cd is None else 0.0,
                        photons_at_peak=level if kind == "photons" else None,
                        read_noise_e=3.0 if kind == "photons" else 0.0, noise_seed=EVAL_NOISE_SEED, limit=limit,
                        screens=True)
        loader = torch.utils.data.DataLoader(ds, batch_size=EVAL_BATCH, shuffle=False, collate_fn=_collate)
        acc = {k: [] for k in ("index", "rytov", "rytov_measured", "none", "unet", "phase_conjugate",
                               "complex_conjugate", "residual_rms", "residual_tiptilt_rms", "vortex_free",
                               "branch_points")
               + (("start",) if refines else ())}
        with torch.no_grad():
            for b in loader:
                scr = b["screens"].to(dev)
                rec = b["received"].to(dev)
                if refines:  # a refiner: its U-Net's estimate (K = 0) is recorded too, from the same pass
                    traj = model.trajectory(b["psf"].to(dev))
                    phi = traj[-1] * model.mask
                    acc["start"].append(pib.npib_phase(traj[0] * model.mask, scr).cpu().numpy())
                elif cd is not None:
                    phi = cd(rec)
                else:
                    phi = model(b["psf"].to(dev))
                if not rows and len(examples["phi"]) < 4:
                    examples["phi"] += list(phi.cpu().numpy()[:4 - len(examples["phi"])])
                    examples["received"] += list(rec.cpu().numpy()[:4 - len(examples["received"])])
                if not rows:  # the references do not depend on the sensor noise: once, at the first level
                    ref = npib_rows(pib, phi, scr, rec, complex_conjugate=True)
                    acc["unet"].append(ref["estimate"].cpu().numpy())
                    for k in ("none", "phase_conjugate", "complex_conjugate"):
                        acc[k].append(ref[k].cpu().numpy())
                    # the received phase without its branch points: what a vortex-free estimate can reach
                    wrapped = torch.angle(rec).cpu().numpy()
                    vf = torch.as_tensor(irrotational_phase(wrapped, ap), dtype=torch.float32, device=dev)
                    acc["vortex_free"].append(pib.npib_phase(vf, scr).cpu().numpy())
                    acc["branch_points"].append(np.abs(branch_points(wrapped, ap)).sum(axis=(-2, -1)))
                else:
                    acc["unet"].append(pib.npib_phase(phi, scr).cpu().numpy())
                r, t = residual_rms(phi.cpu().numpy(), rec.cpu().numpy(), ap)
                acc["residual_rms"].append(r)
                acc["residual_tiptilt_rms"].append(t)
                acc["index"].append(b["index"].numpy())
                acc["rytov"].append(b["rytov"].numpy())
                acc["rytov_measured"].append(b["rytov_measured"].numpy())
                total += len(b["index"])
                if progress:
                    progress(total, n_total)
        first = next(iter(rows.values()), None)
        rows[f"{kind}:{level:g}"] = {k: (np.concatenate(v) if v else first[k]) for k, v in acc.items()}
    return {"rows": rows, "card": card, "split": split, "n": len(base), "crop": (c0, a), "examples": examples,
            "aperture": ap}


def summarise(r: dict) -> dict:
    """Means, medians, gains (per-sample mean, median, ratio of means), captured fraction, by Rytov bin."""
    none, unet, pc = r["none"], r["unet"], r["phase_conjugate"]
    g = gain(none, unet)

    def block(m):
        if not np.any(m):
            return None
        return {"n": int(m.sum()),
                "npib": {k: float(np.mean(r[k][m])) for k in ("none", "unet", "phase_conjugate", "complex_conjugate")},
                "npib_median": {k: float(np.median(r[k][m])) for k in ("none", "unet", "phase_conjugate",
                                                                         "complex_conjugate")},
                "gain": {"mean": float(np.mean(g[m])), "median": float(np.median(g[m])),
                         "ratio_of_means": float(np.mean(unet[m]) / max(np.mean(none[m]), 1e-12))},
                "captured_fraction": captured_fraction(none[m], unet[m], pc[m]),
                "residual_rms_rad": float(np.mean(r["residual_rms"][m])),
                "residual_tiptilt_rms_rad": float(np.mean(r["residual_tiptilt_rms"][m])),
                **({"vortex_free": {"npib": float(np.mean(r["vortex_free"][m])),
                                    "captured_fraction": captured_fraction(none[m], r["vortex_free"][m], pc[m]),
                                    "branch_points_mean": float(np.mean(r["branch_points"][m]))}}
                   if "vortex_free" in r else {})}

    out = block(np.ones(len(none), bool))
    if "start" in r:  # a refiner's evaluation: its U-Net alone on the same inputs
        out["start"] = {"npib": float(np.mean(r["start"])),
                        "captured_fraction": captured_fraction(none, r["start"], pc)}
    out["by_rytov"] = {}
    x = r["rytov_measured"]
    for lo, hi in zip(RYTOV_BINS[:-1], RYTOV_BINS[1:]):
        b = block((x >= lo) & (x < hi))
        if b:
            out["by_rytov"][f"{lo:g}-{hi:g}"] = b
    if not np.isfinite(x).all():  # captures imported without a Rytov number
        out["by_rytov"]["unknown"] = block(~np.isfinite(x))
    return out


def write_results(res: dict, out: Path) -> list[Path]:
    files = []
    for key, r in res["rows"].items():
        p = out / f"per-sample-{key.replace(':', '-')}.csv"
        with atomic_path(p) as tmp:
            with open(tmp, "w", newline="") as fh:
                w = csv.writer(fh)
                cols = list(r)
                w.writerow(cols)
                for i in range(len(r["index"])):
                    w.writerow([f"{r[c][i]:.6g}" if r[c].dtype.kind == "f" else int(r[c][i]) for c in cols])
        files.append(p)
    return files


def _plot_branch_points(plt, r: dict, net: str, path: Path, noise: str) -> Path:
    """Captured fraction by Rytov bin of the estimate(s) and of the vortex-free phase conjugate, with the
    branch points per sample: where a smooth phase stops."""
    x = r["rytov_measured"]
    bins = [(lo, hi) for lo, hi in zip(RYTOV_BINS[:-1], RYTOV_BINS[1:]) if np.any((x >= lo) & (x < hi))]
    masks = [(x >= lo) & (x < hi) for lo, hi in bins]
    fig, ax = plt.subplots(figsize=(7.5, 4.2), constrained_layout=True)
    pos = np.arange(len(bins))
    series = [("vortex_free", "vortex-free phase conjugate", "d--")]
    series += [("start", "U-Net alone", "s-"), ("unet", net, "o-")] if "start" in r else [("unet", net, "o-")]
    for k, lab, st in series:
        ax.plot(pos, [captured_fraction(r["none"][m], r[k][m], r["phase_conjugate"][m]) for m in masks], st, label=lab)
    ax.axhline(1.0, color="k", lw=0.5, ls=":")
    ax.set_xticks(pos, [f"{lo:g}-{hi:g}\nn={int(m.sum())}\n{np.mean(r['branch_points'][m]):.1f} bp"
                        for (lo, hi), m in zip(bins, masks)], fontsize=7)
    ax.set(xlabel="Rytov bin (samples, mean branch points per sample)", ylabel="captured fraction of the phase conjugate",
           title=f"Branch points: what a vortex-free phase can capture ({noise})")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_fig3(res: dict, out: Path, model=None, dataset=None) -> list[Path]:
    """Fig. 3b (NPiB vs per-sample Rytov number) at the first noise level, Fig. 3c/d (box plots vs
    noise level), and predicted vs true phase for a few samples."""
    plt = pyplot()
    figs = []
    keys = list(res["rows"])
    r = res["rows"][keys[0]]
    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    net = "U-Net + refinement" if "start" in r else "U-Net"
    series = [("complex_conjugate", "complex conjugate (oracle)", "^"), ("phase_conjugate", "phase conjugate (oracle)", "s")]
    series += [("vortex_free", "vortex-free phase conjugate (its branch points dropped)", "d")] if "vortex_free" in r else []
    series += [("start", "U-Net alone", "."), ("unet", net, "o")] if "start" in r else [("unet", net, "o")]
    for k, lab, mk in series + [("none", "uncorrected", "x")]:
        ax.scatter(r["rytov_measured"], r[k], s=10, marker=mk, alpha=0.6, label=f"{lab} (mean {np.mean(r[k]):.3f})")
    top = max(1.05, 1.02 * max(float(np.max(r[k])) for k in ("complex_conjugate", "phase_conjugate", "unet")))
    ax.axhline(1.0, color="k", lw=0.5, ls=":")
    ax.set(xlabel="Rytov number of the sample (measured log-amplitude variance)",
           ylabel="NPiB (power in bucket / a vacuum beam's)",
           title=f"Fig. 3b: {res['split']} split, {res['n']} samples, {_noise_words(keys[0])}", ylim=(0, top))
    ax.text(0.99, 0.01, "NPiB > 1: a sample whose turbulence focuses more power into the bucket than vacuum",
            transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.3")
    ax.legend(fontsize=8)
    figs.append(save_figure(fig, out / "fig-3b.png"))
    if "vortex_free" in r:
        figs.append(_plot_branch_points(plt, r, net, out / "fig-branch-points.png", _noise_words(keys[0])))
    pkeys = [k for k in keys if k.startswith("photons:")]
    if pkeys:
        ph = [float(k.split(":")[1]) for k in pkeys]
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
        a1.semilogx(ph, [np.mean(res["rows"][k]["unet"]) for k in pkeys], "o-", label="U-Net")
        a1.axhline(np.mean(r["phase_conjugate"]), ls="--", c="g", label="phase conjugate")
        a1.axhline(np.mean(r["none"]), ls=":", c="k", label="uncorrected")
        a1.set(xlabel="photo-electrons at the PSF peak (+3 e- read noise)", ylabel="mean NPiB", title="NPiB vs photons")
        a1.legend(fontsize=8)
        a2.semilogx(ph, [np.mean(res["rows"][k]["residual_rms"]) for k in pkeys], "o-", label="piston, tip/tilt removed")
        a2.semilogx(ph, [np.mean(res["rows"][k]["residual_tiptilt_rms"]) for k in pkeys], "s--", label="tip/tilt")
        a2.set(xlabel="photo-electrons at the PSF peak", ylabel="residual phase RMS [rad]",
               title="error vs photons (focal-plane sensors' curve)")
        a2.legend(fontsize=8)
        figs.append(save_figure(fig, out / "fig-photons.png"))
    gkeys = [k for k in keys if k.startswith("gaussian:")]
    if len(gkeys) > 1:
        keys = gkeys
        fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
        keys = sorted(keys, key=lambda k: float(k.split(":")[1]))
        data = [res["rows"][k]["unet"] for k in keys]
        ax.boxplot(data, tick_labels=[k.split(":")[1] for k in keys], showfliers=False)
        if "start" in res["rows"][keys[0]]:  # a refiner: its U-Net alone beside it
            ax.plot(range(1, len(keys) + 1), [np.mean(res["rows"][k]["start"]) for k in keys], "D--", color="tab:blue",
                    ms=5, label="U-Net alone (mean)")
            ax.plot(range(1, len(keys) + 1), [np.mean(res["rows"][k]["unet"]) for k in keys], "P-", color="tab:cyan",
                    ms=7, label="U-Net + refinement (mean)")
        ax.axhline(np.mean(res["rows"][keys[0]]["none"]), ls=":", c="k", label="uncorrected (mean)")
        ax.axhline(np.mean(res["rows"][keys[0]]["phase_conjugate"]), ls="--", c="g", label="phase conjugate (mean)")
        ax.set(xlabel="sensor noise in the test inputs [% of each channel's peak]", ylabel=f"NPiB, {net}",
               title=f"Fig. 3c/d: model trained with {training_noise(res['card'])} noise")
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)  # below: the boxes fill the axes
        figs.append(save_figure(fig, out / "fig-3cd.png"))
    ex, ap = res["examples"], res["aperture"]
    if ex["phi"]:
        k = len(ex["phi"])
        fig, axs = plt.subplots(3, k, figsize=(3.2 * k, 8.6), constrained_layout=True, squeeze=False)
        for j in range(k):
            true = np.angle(ex["received"][j])
            pred = ex["phi"][j]
            d = np.exp(1j * (pred - true))
            res_ = np.angle(d * np.conj(d[ap].mean()))
            piston = np.angle(np.mean(np.exp(1j * (pred - true))[ap]))
            for row, (img, title) in enumerate(((true, "true received phase"),
                                                (np.angle(np.exp(1j * (pred - piston))), f"{net} (piston matched)"),
                                                (res_, "residual"))):
                h = axs[row, j].imshow(np.where(ap, img, np.nan), cmap="twilight", vmin=-np.pi, vmax=np.pi)
                axs[row, j].set_xticks([])
                axs[row, j].set_yticks([])
                axs[row, j].set_title(title, fontsize=8)
        fig.colorbar(h, ax=axs, shrink=0.6, label="rad (wrapped)")
        figs.append(save_figure(fig, out / "fig-3a-phases.png"))
    return figs

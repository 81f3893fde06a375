"""The local-periodic approximation's error on a real design, measured with supercell RCWA.

The as-fabricated model looks every pillar up in a library of infinite arrays of identical pillars (the
LPA) and the sensor sees the supercell-averaged field: for a 2 x 2 supercell (period ``2 p < lambda``,
only the 0th order propagates in air) the LPA predicts the 0th-order transmission ``mean(t_1..t_4)``.
:func:`lpa_check` samples supercells of a layout at random (seeded) inside its clear aperture, solves each
full supercell (four different pillars, both polarisations; :func:`metadesign.library.supercell.
solve_supercell`) and compares.  The LPA reference is computed twice: with unit cells solved at the
supercell's own truncation (the even harmonics of the supercell's set: the pure LPA error) and from the
library (what the as-fabricated model uses: the LPA error plus the library's truncation and interpolation).

The complex relative error ``eps = t_supercell / t_LPA - 1`` (per polarisation) is reported as magnitude
and phase distributions, and against the supercell's width contrast (the RMS deviation of its four
widths along the polarisation).  Downstream (:func:`perturbed_pupil`): each coarse-pupil block of the
device gets a factor ``1 + eps``, drawn from the measured errors under two bounding models,
``independent`` (every supercell its own draw: a block averages hundreds, so only the mean error
survives) and ``correlated`` (one draw per block: neighbouring supercells err alike), and the channel
metrics (focusing efficiency, Strehl, crosstalk) and the NPiB of a model are compared with the nominal."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..design.store import load_design
from ..execution import SERIAL, Execution
from ..io import atomic_write_text
from ..library.rcwa import SolverSettings, solve_cell
from ..library.supercell import solve_supercell
from ..library.supercells import matched_unit_harmonics
from ..parallel import WorkerPool
from ..plotting import pyplot, save_figure
from ..reconstruction.data import PSFDataset, apply_noise
from ..reconstruction.dataset import load_device, normalise_psf
from ..reconstruction.losses import PiB
from ..reconstruction.metrics import npib_rows
from ..reconstruction.model import check_fits, load_model
from ..sensing.device import Device
from ..sensing.forward import CoarsePupil
from ..sensing.model import AsFabricated, channel_metrics
from ..sensing.sampled import jackknife_bias, jackknife_se, sampled_frames
from ..sensing.sensor import psf_tensor
from ..sensing.transmission import interpolate_t
from ..sensing.twin import crop_to_pupil
from ..validation import ValidationError

__all__ = ["LpaSettings", "Downstream", "downstream_of", "lpa_study", "lpa_check", "sample_supercells",
           "perturbed_pupil", "lpa_downstream", "pupil_downstream", "plot_lpa"]


@dataclass(frozen=True)
class LpaSettings:
    """The LPA check's sample: ``supercells`` drawn with ``seed``, solved at ``harmonics`` (requested), the
    first ``check`` of them again at 1.5x the harmonics (the truncation's certification)."""

    supercells: int = 32
    harmonics: int = 800
    seed: int = 0
    check: int = 2


@dataclass(frozen=True)
class Downstream:
    """A downstream NPiB study: the U-Net ``model`` on at most ``samples`` test samples of ``dataset``
    (whose device pupil the devices share) at ``noise_percent`` noise, the noise drawn from ``seed``."""

    dataset: Any
    model: Any
    samples: int = 64
    noise_percent: float = 5.0
    seed: int = 0


def downstream_of(dataset, model, samples: int = 64, noise_percent: float = 5.0, seed: int = 0, *,
                  what: str = "the downstream NPiB") -> Downstream | None:
    """The downstream study of a dataset and a model (None without them); one of them alone is refused
    (ValidationError: ``what`` needs both)."""
    if (dataset is None) != (model is None):
        raise ValidationError(f"--dataset and --model go together ({what} needs both)")
    return None if dataset is None else Downstream(dataset, model, samples, noise_percent, seed)


def lpa_study(src: str | Path, out: Path, settings: LpaSettings = LpaSettings(),
              downstream: Downstream | None = None, run: Execution = SERIAL) -> dict:
    """The LPA check of the layout or design folder ``src`` (:func:`lpa_check`, inside its clear aperture
    when that is a circle) and, with ``downstream``, the channel metrics and NPiB with the measured error
    (:func:`lpa_downstream`); writes ``out/lpa.json`` and ``out/lpa.png`` (the report's ``figure``)."""
    src = Path(src)
    if src.is_dir():
        fab = AsFabricated.from_design(load_design(src))
    else:
        fab = AsFabricated.from_files(src)
    im, w = fab.layout.index_map, fab.layout.atom_widths_nm
    mask = None
    if (fab.aperture or {}).get("kind") == "circle":
        n2 = im.shape[0] // 2
        x = (np.arange(n2) - (n2 - 1) / 2) * 2 * fab.period
        mask = x[None, :] ** 2 + x[:, None] ** 2 <= (im.shape[0] * fab.period / 2) ** 2 * 0.98
    run.log(f"lpa-check: {settings.supercells} supercells of {src} (period {fab.period * 1e6:.3f} um, 2 x 2) ...")
    rep = lpa_check(im, w, fab.lib, settings, mask, run)
    eps = rep.pop("_eps")
    rep.pop("_contrast"), rep.pop("_spread")
    if downstream is not None:
        run.log("downstream: channel metrics and NPiB with the measured error ...")
        rep["downstream"] = lpa_downstream(eps, fab, downstream, run.log)
    atomic_write_text(out / "lpa.json", json.dumps(rep, indent=1))
    rep["figure"] = str(plot_lpa(rep, out / "lpa.png"))
    return rep


def sample_supercells(index_map: np.ndarray, n: int, seed: int, mask: np.ndarray | None = None) -> np.ndarray:
    """(n, 2) supercell indices (row I, column J: pillars rows 2I..2I+1, cols 2J..2J+1) drawn at random
    among supercells whose four pillars exist (and lie in ``mask``, (rows/2, cols/2) bool)."""
    H, W = index_map.shape[0] // 2, index_map.shape[1] // 2
    rng = np.random.default_rng(seed)
    out: list = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > 1000 * n:
            raise ValueError("could not find enough supercells with four pillars")
        I, J = int(rng.integers(H)), int(rng.integers(W))
        if mask is not None and not mask[I, J]:
            continue
        if (index_map[2 * I:2 * I + 2, 2 * J:2 * J + 2] >= 0).all() and (I, J) not in out:
            out.append((I, J))
    return np.array(out, np.int64)


def _solve_one(args):
    widths, stack, n_super, n_unit = args
    sc = solve_supercell(widths, stack, n_super)
    units = [solve_cell(wx, wy, stack, SolverSettings(n_unit)) for wx, wy in np.asarray(widths).reshape(4, 2)]
    return sc, units


def lpa_check(index_map: np.ndarray, atom_widths_nm: np.ndarray, lib, settings: LpaSettings = LpaSettings(),
              mask: np.ndarray | None = None, run: Execution = SERIAL) -> dict:
    """Measured LPA error on ``settings.supercells`` random supercells (inside ``mask``); ``settings.check`` of
    them are re-solved at 1.5x the harmonics (the certification of the supercell truncation); on
    ``run.workers`` processes, ``run.progress`` called per supercell."""
    n, n_super, seed, check = settings.supercells, settings.harmonics, settings.seed, settings.check
    workers, progress = run.workers, run.progress
    stack = lib.stack
    ns, nu = matched_unit_harmonics(n_super, stack)
    cells = sample_supercells(index_map, n, seed, mask)
    widths = np.array([[[atom_widths_nm[index_map[2 * I + r, 2 * J + c]] * 1e-9 for c in range(2)] for r in range(2)]
                       for I, J in cells])  # (n, 2, 2, 2): [r][c] = (wx, wy)
    jobs = [(w, stack, ns, nu) for w in widths]
    t0 = time.perf_counter()
    pool = WorkerPool(workers)
    try:
        it = pool.map(_solve_one, jobs, ordered=True)
        res = []
        for k, r in enumerate(it):
            res.append(r)
            if progress:
                progress(k + 1, n + check)
        ns2, _ = matched_unit_harmonics(int(1.5 * n_super), stack)
        conv_jobs = [(w, stack, ns2, nu) for w in widths[:check]]
        conv = []
        it2 = pool.map(_solve_one, conv_jobs, ordered=True)
        for k, r in enumerate(it2):
            conv.append(r[0])
            if progress:
                progress(n + k + 1, n + check)
    finally:
        pool.close()
    seconds = time.perf_counter() - t0
    t_sc = np.array([r[0].jones[[0, 1], [0, 1]] for r in res])  # (n, 2)
    t_units = np.array([[u.jones[[0, 1], [0, 1]] for u in r[1]] for r in res])  # (n, 4, 2)
    t_lib, _, _ = interpolate_t(lib, widths[..., 0].reshape(n, 4), widths[..., 1].reshape(n, 4))
    lpa = t_units.mean(axis=1)
    lpa_lib = t_lib.astype(complex).mean(axis=1)
    eps = t_sc / lpa - 1
    eps_lib = t_sc / lpa_lib - 1
    contrast = np.stack([widths[..., 0].reshape(n, 4).std(axis=1), widths[..., 1].reshape(n, 4).std(axis=1)], 1)
    # the four pillars' spread in the complex plane (the LPA's own measure of 'how different')
    spread = np.abs(t_units - lpa[:, None, :]).mean(axis=1) / np.abs(lpa)
    t_conv = np.array([c.jones[[0, 1], [0, 1]] for c in conv])
    conv_err = np.abs(t_conv / t_sc[:check] - 1) if check else np.zeros((0, 2))

    unit_rms = np.sqrt((np.abs(t_units) ** 2).mean(axis=1))  # (n, 2): the pillars' own transmission scale

    def stats(e):
        mag, ph = np.abs(e), np.angle(1 + e)
        dev = np.abs(e) * np.abs(t_sc / (1 + e)) / unit_rms  # |t_sc - t_LPA| / rms |t_i|
        return {"abs_error_over_unit_rms_mean": dev.mean(0).tolist(),
                "abs_error_over_unit_rms_median": np.median(dev, 0).tolist(),"rel_magnitude_mean": mag.mean(0).tolist(), "rel_magnitude_median": np.median(mag, 0).tolist(),
                "rel_magnitude_p90": np.percentile(mag, 90, 0).tolist(), "rel_magnitude_max": mag.max(0).tolist(),
                "phase_rms_rad": np.sqrt((ph**2).mean(0)).tolist(), "phase_mean_rad": ph.mean(0).tolist(),
                "amplitude_ratio_mean": np.abs(1 + e).mean(0).tolist(),
                "mean_complex": [[float(v.real), float(v.imag)] for v in e.mean(0)]}

    def corr(a, b):
        return [float(np.corrcoef(a[:, p], b[:, p])[0, 1]) if np.std(a[:, p]) > 0 and np.std(b[:, p]) > 0 else None
                for p in range(2)]

    return {
        "supercells": n, "seed": seed, "n_harmonics_supercell": int(res[0][0].n_harmonics),
        "n_harmonics_unit": int(res[0][1][0].n_harmonics), "n_harmonics_check": int(conv[0].n_harmonics) if check else None, "library_n_harmonics": lib.meta.get("solver", {}).get("n_harmonics"),
        "convergence_rel_change_max": conv_err.max(0).tolist() if check else None,
        "seconds": seconds, "workers": workers,
        "lpa": stats(eps), "lpa_library": stats(eps_lib),
        "corr_error_vs_width_contrast": corr(np.abs(eps), contrast),
        "corr_error_vs_t_spread": corr(np.abs(eps), spread),
        "rows": [{"I": int(I), "J": int(J), "widths_nm": (widths[k] * 1e9).round(3).tolist(),
                  "t_supercell": [[float(v.real), float(v.imag)] for v in t_sc[k]],
                  "t_lpa": [[float(v.real), float(v.imag)] for v in lpa[k]],
                  "t_lpa_library": [[float(v.real), float(v.imag)] for v in lpa_lib[k]],
                  "eps": [[float(v.real), float(v.imag)] for v in eps[k]],
                  "width_contrast_nm": (contrast[k] * 1e9).tolist(), "t_spread": spread[k].tolist()}
                 for k, (I, J) in enumerate(cells)],
        "_eps": eps, "_contrast": contrast, "_spread": spread,
    }


def perturbed_pupil(cp, eps: np.ndarray, model: str, seed: int = 0, supercells_per_block: int | None = None):
    """A copy of the coarse pupil with a factor ``1 + e`` per block and polarisation (all four channels of a
    block share it), ``e`` drawn from the measured ``eps`` (n, 2): ``correlated``: one measured error per
    block; ``independent``: the mean of ``supercells_per_block`` draws per block."""
    rng = np.random.default_rng(seed)
    N = cp.G.shape[-1]
    if model == "correlated":
        idx = rng.integers(len(eps), size=(N, N))
        f = 1 + eps[idx]  # (N, N, 2)
    elif model == "independent":
        m = int(supercells_per_block or 1)
        # the mean of m draws: the measured mean plus a random part shrunk by sqrt(m) (CLT)
        mu = eps.mean(0)
        idx = rng.integers(len(eps), size=(N, N))
        f = 1 + mu + (eps[idx] - mu) / np.sqrt(m)
    else:
        raise ValueError(model)
    G = cp.G * np.moveaxis(f, -1, 0)[:, None].astype(np.complex64)
    return CoarsePupil(G.astype(np.complex64), cp.X, cp.block, cp.period, cp.wavelength, cp.z, cp.n_clamped)


def lpa_downstream(eps: np.ndarray, fab, downstream: Downstream, log=lambda s: None) -> dict:
    """Channel metrics and the model's NPiB with the device pupil of ``downstream.dataset`` (nominal LPA) and
    with the measured LPA error applied (both bounding models)."""
    cp = load_device(downstream.dataset).pupil
    per_block = max(1, (cp.block // 2) ** 2)
    seed = downstream.seed
    pupils = {"nominal": cp,
              "independent": perturbed_pupil(cp, eps, "independent", seed, per_block),
              "correlated": perturbed_pupil(cp, eps, "correlated", seed)}
    out = pupil_downstream(pupils, downstream, fab, log)
    out["supercells_per_block"] = per_block
    return out


def pupil_downstream(pupils: dict, downstream: Downstream, fab, log=lambda s: None, sampled: dict | None = None) -> dict:
    """Channel metrics and the U-Net's NPiB through each of ``pupils`` (name -> coarse pupil on the grid of
    ``dataset``'s device): the test samples are re-rendered from their received fields through each pupil
    (same path, same noise draws) and corrected through their own screens.  ``sampled``: name -> (a name
    of ``pupils``, its replicate correction pupils): a device known by sampling
    (:func:`~metadesign.sensing.sampled.sampled_frames`), its NPiB with the jackknife's standard error and
    bias estimate over the replicates (the same noise draws in every leave-one-out pass)."""
    import torch

    dataset, model_path, samples = downstream.dataset, downstream.model, downstream.samples
    noise_percent, seed = downstream.noise_percent, downstream.seed
    dev = load_device(dataset)
    sensor = dev.sensor
    c0, a, ng, dx, d2 = dev.geometry
    model, _ = load_model(model_path)
    model.eval()
    ds = PSFDataset(dataset, "test", limit=samples, screens=True)
    check_fits(model, ds.info, str(model_path))
    if len(ds) == 0:  # a dataset without a test split (tiny ones): every sample
        ds = PSFDataset(dataset, "all", limit=samples, screens=True)
    pib = PiB(ds.scenario(), c0, a)
    items = [ds.get(j) for j in range(len(ds))]
    N = dev.pupil.G.shape[-1]
    e_in = [crop_to_pupil(s["received"], ng, dx, d2, c0, N) for s in items]
    scr = torch.from_numpy(np.stack([s["screens"] for s in items]))
    out = {"samples": len(items), "noise_percent": noise_percent}

    def noisy(psfs, s):  # the network's input: the same noise draws for a sample whatever its PSFs
        t, _ = normalise_psf(psfs)
        return apply_noise(t, np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(s["index"],))),
                           noise_percent)

    def npib_of(x):
        with torch.no_grad():
            return float(pib.npib_phase(model(torch.from_numpy(np.stack(x))), scr).numpy().mean())

    for name, p in pupils.items():
        if p.G.shape[-1] != N:
            raise ValueError(f"pupil {name}: grid {p.G.shape[-1]} differs from the dataset's {N}")
        log(f"  downstream: {name} pupil ...")
        m = channel_metrics(p, sensor, fab)
        dv = Device(p, sensor)
        out[name] = {"npib_unet": npib_of([noisy(dv.psfs(e), s) for s, e in zip(items, e_in)]),
                     "channels": [{k: r[k] for k in ("pol", "k", "focusing_efficiency", "strehl", "crosstalk",
                                                     "focal_shift_mm")} for r in m]}
    for name, (base, deltas) in (sampled or {}).items():
        log(f"  downstream: {name} (sampled, {len(deltas)} replicates) ...")
        x = []  # per sample: the full estimate's input, then each leave-one-out's
        for s, e in zip(items, e_in):
            full, loo = sampled_frames(pupils[base], deltas, sensor, e)
            x.append([noisy(psf_tensor(f, sensor), s) for f in (full, *loo)])
        npib = npib_of([v[0] for v in x])
        loo_means = [npib_of([v[j + 1] for v in x]) for j in range(len(deltas))]
        out[name] = {"npib_unet": npib, "npib_unet_se": jackknife_se(loo_means),
                     "npib_unet_bias": jackknife_bias(npib, loo_means), "replicates": len(deltas)}
    rec = torch.from_numpy(np.stack([s["received"] for s in items]))
    ref = npib_rows(pib, torch.zeros(len(items), a, a), scr, rec)
    out["npib_none"] = float(ref["none"].mean())
    out["npib_phase_conjugate"] = float(ref["phase_conjugate"].mean())
    return out


def plot_lpa(rep: dict, out):
    """LPA error: |eps| and phase histograms per polarisation, |eps| vs width contrast, downstream bars."""
    plt = pyplot()
    rows = rep["rows"]
    eps = np.array([[complex(*e) for e in r["eps"]] for r in rows])
    con = np.array([r["width_contrast_nm"] for r in rows])
    d = rep.get("downstream")
    fig, axs = plt.subplots(1, 4 if d else 3, figsize=(17 if d else 13, 3.8), constrained_layout=True)
    for p, c in enumerate(("C0", "C1")):
        axs[0].hist(np.abs(eps[:, p]), bins=20, alpha=0.6, color=c, label=f"{'xy'[p]}-pol")
        axs[1].hist(np.angle(1 + eps[:, p]), bins=20, alpha=0.6, color=c, label=f"{'xy'[p]}-pol")
        axs[2].plot(con[:, p], np.abs(eps[:, p]), "o", ms=4, color=c, label=f"{'xy'[p]}-pol")
    axs[0].set(xlabel="|t_supercell / t_LPA - 1|", ylabel="supercells",
               title=f"LPA error, {len(rows)} supercells (nG {rep['n_harmonics_supercell']})")
    axs[1].set(xlabel="arg(t_supercell / t_LPA) [rad]", title="phase error")
    axs[2].set(xlabel="width contrast in the supercell (RMS, nm)", ylabel="|eps|", title="error vs contrast")
    for ax in axs[:3]:
        ax.legend(fontsize=8)
    if d:
        names = ("nominal", "independent", "correlated")
        keys = ("focusing_efficiency", "strehl", "npib_unet")
        vals = np.array([[np.mean([c[k] for c in d[m]["channels"]]) if k != "npib_unet" else d[m][k]
                          for k in keys] for m in names])
        x = np.arange(len(keys))
        for i, m in enumerate(names):
            axs[3].bar(x + (i - 1) * 0.27, vals[i] / vals[0], 0.27, label=m)
        axs[3].set_xticks(x, ["focusing eff.", "Strehl", "U-Net NPiB"])
        rel = vals / vals[0]
        axs[3].set(ylabel="relative to the nominal LPA device", ylim=(0, max(1.1, rel.max() * 1.08)),
                   title="downstream (measured error on the pupil)")
        axs[3].legend(fontsize=8)
    return save_figure(fig, out)

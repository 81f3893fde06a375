"""The loop study's report (``loop.json``, ``loop.png``): what :func:`~metadesign.studies.loop_study.run_loop_study`
computes, put into words and figures.

From the tasks' series (each method's runs on each turbulence realisation, in a fixed order) it computes per
method the pooled NPiB statistics, the fades (:func:`pooled_fades`), the modal temporal spectra and the
measured rejection against theory (:func:`method_report`), the headline (:func:`loop_verdict`), what made
the report (:func:`loop_provenance`), and draws ``loop.png`` (:func:`plot_loop`).  ``loop.json`` opens with
the verdict, then the provenance, then the numbers.  Functions of the numbers and of the recipe's files: the
loop's physics lives in :mod:`~metadesign.studies.loop`, its orchestration in
:mod:`~metadesign.studies.loop_study`."""

from __future__ import annotations

import os
import platform
import time
from importlib import metadata
from pathlib import Path

import numpy as np

from .. import __version__
from ..cards import find_card
from ..config import load_toml
from ..optics.control import rejection_tf
from ..plotting import pyplot, save_figure
from ..tasks import content_key, file_key
from .loop import ORACLES, REALISATION_TAG, LoopTiming, pol_rejection_tf
from .loop_recipe import METASURFACE, LoopRecipe
from .loop_stats import cdf_points, fade_statistics, welch_psd
from .pipeline_report import _git_commit

__all__ = ["LABELS", "method_report", "pooled_fades", "mean_psd", "loop_verdict", "loop_report", "loop_provenance",
           "plot_loop", "VERSIONS"]

LABELS = {"unet": "metasurface + U-Net", "refine": "metasurface + learned refinement",
          "shack_hartmann": "Shack-Hartmann", "ideal": "ideal phase sensor", "fitted": "DM-fitted oracle (no delay)",
          "conjugate": "phase conjugate", "open": "open loop", "linear": "metasurface + linear reconstructor",
          "realtime": "metasurface + real-time modal net",
          "realtime_tt": "metasurface + net, linear tip/tilt",
          "realtime_peak": "metasurface + net, peak tip/tilt", "retrieval": "metasurface + budget retrieval",
          "refine_warm": "metasurface + warm refinement"}


#: the packages whose versions the provenance records (None: not installed)
VERSIONS = ("numpy", "scipy", "torch", "onnxruntime", "matplotlib", "dask", "distributed")


def loop_report(rec: LoopRecipe, runs: dict, timings: dict, latency: dict, gains: dict, search: dict,
                temporal: dict, t_start: float, grid: tuple = (), refine: tuple = (), log=lambda s: None,
                provenance: dict | None = None) -> tuple:
    """The report of a loop study: ``runs`` ``{method: [series of each realisation]}`` (``"open"`` among
    them), ``timings`` ``{method: LoopTiming}``, ``latency`` ``{method: s}``, ``gains`` ``{closed loop: gain}``,
    ``search`` the gain search's trials (``{}``: none; ``grid`` and ``refine`` its gains), ``temporal`` the
    turbulence's temporal summary, ``t_start`` the study's start (``time.perf_counter``), ``provenance``
    :func:`loop_provenance`'s block.  Returns the report (the verdict its first key, the provenance its second;
    no figures yet), the first realisation's series and the pooled NPiB of each method."""
    lp = rec.loop
    order = list(runs)
    reports, firsts, pooled = {}, {}, {}
    for m in order:
        reports[m] = method_report(m, runs[m], latency.get(m, 0.0), timings[m], rec, gains.get(m),
                                   runs["open"] if m != "open" else None)
        if m in search:
            reports[m]["gain_search"] = search[m]
        firsts[m], pooled[m] = runs[m][0], np.concatenate([s["npib"] for s in runs[m]])
        log(f"  {LABELS[m]:<34} NPiB {reports[m]['npib_mean']:.3f}, P(fade {lp.threshold_db:g} dB) "
            f"{reports[m]['fades']['probability']:.3g}, delay {reports[m]['delay_frames']:.2f} frames "
            f"({reports[m]['seconds']:.0f} s)")
    rep = {"format": "metadesign.loop/1", "recipe": str(rec.source), "loop": {**lp.__dict__, "methods": list(lp.methods)},
           "dm": rec.dm.__dict__, "turbulence": {**temporal, "rytov": lp.rytov, "wind": rec.wind},
           "methods": {m: reports[m] for m in lp.methods if m in reports} | ({"open": reports["open"]}),
           "seconds": time.perf_counter() - t_start}
    if search:
        rep["gain_search"] = {"objective": f"mean NPiB over the first {lp.gain_steps} steps of the first seed",
                              "grid": list(grid), "refine": list(refine),
                              "chosen": {m: v["gain"] for m, v in search.items()}}
    rep = {"verdict": loop_verdict(rep), "provenance": provenance, **rep}
    return rep, {m: firsts[m] for m in rep["methods"]}, {m: pooled[m] for m in rep["methods"]}


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def loop_provenance(rec: LoopRecipe, out: Path, latency_measured: list, workers: int = 1,
                    scheduler: str | None = None) -> dict:
    """What made a loop report: the recipe (its path relative to the report's folder ``out``, its bytes'
    sha256 and its parsed content's key, :func:`metadesign.tasks.content_key`, which a comment edit keeps),
    the files it names (paths relative to the recipe's folder, as the recipe writes them, and sha256s; a
    model with its card's sha256), the seeds (the turbulence realisations' and the detector noise's streams),
    which latencies were measured on this machine (``latency_measured``; the others declared), how it ran
    (``workers`` local processes or a Dask ``scheduler``: the numbers do not depend on it), the code
    (version, commit, the packages of :data:`VERSIONS`), the machine and the date."""
    src = Path(rec.source).resolve()
    base = src.parent

    def named(p):
        p = Path(p).resolve()
        return {"path": os.path.relpath(p, base), "sha256": file_key(p) if p.is_file() else None}

    def model(p):
        if p is None:
            return None
        card = find_card(p)
        return {**named(p), "card": named(card) if card.is_file() else None}

    lp = rec.loop
    return {"recipe": {"path": os.path.relpath(src, Path(out).resolve()), "relative_to": "report",
                       "sha256": file_key(src), "key": content_key(load_toml(src))},
            "design": named(rec.design), "sensor": named(rec.sensor), "turbulence": named(rec.turbulence),
            "model": model(rec.model), "realtime": model(rec.realtime),
            "seeds": {"seed": lp.seed, "realisations": lp.seeds,
                      "turbulence": f"realisation 0: the seed; r >= 1: SeedSequence(seed, spawn_key=({REALISATION_TAG}, "
                                    "r, 0))",
                      "noise": f"realisation 0: SeedSequence(seed, spawn_key=(11 or 12, frame)); r >= 1: "
                               f"SeedSequence(seed, spawn_key=({REALISATION_TAG}, r, 1, 11 or 12, frame))"},
            "latency_measured": sorted(latency_measured),
            "execution": {"scheduler": scheduler} if scheduler is not None else {"workers": int(workers)},
            "metadesign": __version__, "commit": _git_commit(),
            "versions": {"python": platform.python_version(), **{k: _version(k) for k in VERSIONS}},
            "machine": f"{platform.node()} ({platform.system()} {platform.machine()}, {os.cpu_count()} cores)",
            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z")}


def plot_loop(rep: dict, series: dict, pooled: dict, out: Path) -> list[Path]:
    """``loop.png``: the first realisation's NPiB in time, the pooled CDF, the measured and theoretical
    rejection; below them (a loop of >= 64 steps: the report has its spectra) the modal temporal PSDs of the
    open loop and each closed loop, log-log, for tip (Noll 2) and the highest mode measured, and each mode's
    variance (the PSD integrated over frequency).  One colour per method in every panel."""
    plt = pyplot()
    lp, ms = rep["loop"], rep["methods"]
    colour = {m: f"C{i % 10}" for i, m in enumerate(ms)}
    spectra = [m for m, r in ms.items() if "modal_psd" in r and (m == "open" or m not in ORACLES)]
    rows = 2 if "open" in spectra else 1
    fig, axs = plt.subplots(rows, 3, figsize=(16, 4.2 * rows), constrained_layout=True, squeeze=False)
    top = axs[0]
    t = np.arange(lp["steps"]) / lp["rate_hz"] * 1e3
    for m, s in series.items():
        top[0].plot(t, s["npib"], lw=0.8, color=colour[m], label=LABELS[m])
        v, p = cdf_points(pooled[m])
        top[1].semilogy(v, p, lw=1, color=colour[m], label=LABELS[m])
    seeds = f" (first of {lp['seeds']} seeds)" if lp["seeds"] > 1 else ""
    top[0].set(xlabel="time (ms)", ylabel="NPiB",
               title=f"{lp['rate_hz']:g} Hz loop, f_G {rep['turbulence']['greenwood_hz']:.0f} Hz{seeds}")
    top[1].set(xlabel="NPiB", ylabel="P(NPiB <= x)", title="CDF of the power in the bucket")
    for m, r in ms.items():
        if "rejection" in r:
            f, db = np.array(r["rejection"]["f_hz"]), np.array(r["rejection"]["measured_db"])
            top[2].semilogx(f[1:], db[1:], lw=1, color=colour[m], label=f"{LABELS[m]} (measured)")
            top[2].semilogx(f[1:], np.array(r["rejection"]["theory_db"])[1:], "--", lw=0.8, color=colour[m])
    top[2].set(xlabel="f (Hz)", ylabel="|RTF|^2 (dB)", title="rejection: measured (solid), theory (dashed)")
    if rows == 2:
        noll = ms["open"]["modal_psd"]["noll"]
        for ax, k in zip(axs[1][:2], (0, len(noll) - 1)):
            for m in spectra:
                psd = ms[m]["modal_psd"]
                f, P = np.array(psd["f_hz"]), np.array(psd["psd_rad2_hz"][k])
                ax.loglog(f[1:], P[1:], lw=1.6 if m == "open" else 0.9, color=colour[m], label=LABELS[m])
            ax.set(xlabel="f (Hz)", ylabel="PSD (rad^2/Hz)",
                   title=f"temporal PSD of Zernike Noll {noll[k]}{' (tip)' if noll[k] == 2 else ''}: "
                         "open vs closed loops")
        ax = axs[1][2]
        for m in spectra:
            psd = ms[m]["modal_psd"]
            f, P = np.array(psd["f_hz"]), np.array(psd["psd_rad2_hz"])
            ax.semilogy(psd["noll"], P.sum(axis=1) * (f[1] - f[0]), "o-", ms=3, lw=1.6 if m == "open" else 0.9,
                        color=colour[m], label=LABELS[m])
        ax.set(xlabel="Zernike mode (Noll)", ylabel="variance (rad^2, mean removed)",
               title="each mode's variance (its PSD integrated over f)")
    for a in axs.flat:
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    return [save_figure(fig, out / "loop.png")]


def pooled_fades(runs: list, dt: float, threshold_db: float) -> dict:
    """:func:`~metadesign.studies.loop_stats.fade_statistics` of the realisations' series pooled: the reference
    their common mean, the fades counted in each series (none across two), the probability and the rate
    over all the samples (one series: exactly its own statistics)."""
    p = [np.asarray(s["npib"], float) for s in runs]
    ref = float(np.mean(np.concatenate(p)))
    each = [fade_statistics(x, dt, threshold_db, reference=ref) for x in p]
    level = each[0]["threshold"]
    prob = float((np.concatenate(p) < level).mean())
    n_fades = int(sum(f["fades"] for f in each))
    rate = n_fades / (sum(len(x) for x in p) * dt)
    return {"threshold_db": float(threshold_db), "reference": ref, "threshold": level, "probability": prob,
            "fades": n_fades, "fades_per_s": rate,
            "mean_duration_s": float(prob / rate) if rate > 0 else float("nan"),
            "max_duration_s": max(f["max_duration_s"] for f in each)}


def mean_psd(runs: list, fs: float, segment: int) -> tuple[np.ndarray, np.ndarray]:
    """Welch PSDs of the realisations' modal series, averaged over them."""
    psds = [welch_psd(s["modal"], fs, segment) for s in runs]
    return psds[0][0], sum(P for _, P in psds) / len(psds)


def method_report(m: str, runs: list, lat: float, timing: LoopTiming, rec: LoopRecipe, gain, open_runs) -> dict:
    """Method ``m``'s report from its series on each realisation (pooled: means and percentiles over every
    sample, fades by :func:`pooled_fades`, spectra averaged over the realisations)."""
    lp = rec.loop
    npib = np.concatenate([s["npib"] for s in runs])
    closed = m not in ORACLES
    r = {"label": LABELS[m], "latency_ms": lat * 1e3, "delay_frames": timing.delay_frames if closed else 0.0,
         "npib_mean": float(np.mean(npib)), "npib_p01": float(np.percentile(npib, 1)),
         "residual_rms_rad": float(np.mean(np.concatenate([s["residual_rms"] for s in runs]))),
         "branch_points_mean": float(np.mean(np.concatenate([s["branch_points"] for s in runs]))),
         "fades": pooled_fades(runs, timing.dt, lp.threshold_db)}
    if closed:
        r["gain"] = float(gain)
    r["seeds"] = len(runs)
    r["seconds"] = float(sum(float(s["seconds"]) for s in runs))
    steps = len(runs[0]["npib"])
    # each realisation is one task on one worker (one core): its wall seconds per second of link time
    r["core_s_per_link_s"] = r["seconds"] / (steps * len(runs) / lp.rate_hz)
    segment = min(256, steps // 2)
    if closed and open_runs is not None and steps >= 64:
        f, pc = mean_psd(runs, lp.rate_hz, segment)
        _, po = mean_psd(open_runs, lp.rate_hz, segment)
        rtf = pc.sum(axis=1) / np.maximum(po.sum(axis=1), 1e-300)
        tf = (pol_rejection_tf(f, lp.rate_hz, gain, timing.delay_frames, lp.leak) if lp.pseudo_open_loop else
              rejection_tf(f, lp.rate_hz, gain, timing.delay_frames, lp.leak))
        theory = np.abs(tf) ** 2
        r["rejection"] = {"f_hz": f.tolist(), "measured_db": (10 * np.log10(np.maximum(rtf, 1e-30))).tolist(),
                          "theory_db": (10 * np.log10(np.maximum(theory, 1e-30))).tolist()}
    if steps >= 64:
        f, P = mean_psd(runs, lp.rate_hz, segment)
        r["modal_psd"] = {"f_hz": f.tolist(), "noll": list(range(2, 2 + P.shape[1])), "psd_rad2_hz": P.T.tolist()}
    return r


def loop_verdict(rep: dict) -> dict:
    """The headline: the metasurface loops' mean NPiB against the ideal-phase loop's and the Shack-Hartmann
    loop's (the issue's goals: >= 0.8 of the ideal, >= 2x the Shack-Hartmann)."""
    ms = rep["methods"]
    best = max((m for m in METASURFACE if m in ms), key=lambda m: ms[m]["npib_mean"], default=None)
    out = {"best_metasurface": best}
    if best is None:
        return out
    v = ms[best]["npib_mean"]
    if "ideal" in ms:
        out["vs_ideal"] = v / ms["ideal"]["npib_mean"] if ms["ideal"]["npib_mean"] > 0 else None
    if "shack_hartmann" in ms:
        out["vs_shack_hartmann"] = v / ms["shack_hartmann"]["npib_mean"] if ms["shack_hartmann"]["npib_mean"] > 0 else None
    return out

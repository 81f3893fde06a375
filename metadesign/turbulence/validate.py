"""Validation statistics of the turbulence model against theory (Figs. S5, S6) and their plots (the
scenario recipe: :mod:`.scenario`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..plotting import pyplot, save_figure
from .path import Scenario
from .propagate import Turbulence
from .screens import ScreenGrid, log_amplitude_variance_theory, screens, structure_function_theory

__all__ = ["structure_function_check", "log_amplitude",
           "coherence", "wave_structure_theory", "validate", "plot_validation"]

def structure_function_check(sc: Scenario, n_screens: int = 300, seed: int = 0, r0: float = 0.05,
                             seps=(2, 4, 8, 16, 32, 64, 128)) -> dict:
    """Ensemble phase structure function of screens vs the theory of the same PSD."""
    g = ScreenGrid(sc.n_grid, sc.dx, sc.inner_scale, sc.outer_scale, sc.subharmonics)
    seps = [s for s in seps if s <= sc.n_grid // 2]
    D = np.zeros(len(seps))
    ss = np.random.SeedSequence(seed).spawn((n_screens + 1) // 2)
    for s in ss:
        for a in screens(g, [r0, r0], s):
            for i, r in enumerate(seps):
                D[i] += 0.5 * (np.mean((a[:, r:] - a[:, :-r]) ** 2) + np.mean((a[r:, :] - a[:-r, :]) ** 2))
    D /= 2 * len(ss)
    r = np.array(seps) * sc.dx
    th = structure_function_theory(r, r0, sc.inner_scale, sc.outer_scale)
    return {"r_m": r.tolist(), "measured": D.tolist(), "theory": th.tolist(), "ratio": (D / th).tolist()}


def log_amplitude(tb: Turbulence, field: np.ndarray) -> np.ndarray:
    """chi = ln(|U| / |U_vacuum|) on the receiver aperture."""
    return np.log(np.abs(field[tb.aperture]) / np.abs(tb.vacuum[tb.aperture]))


def coherence(tb: Turbulence, fields: list[np.ndarray], max_sep: int | None = None,
              floor: bool = False) -> tuple[np.ndarray, ...]:
    """Modulus of the ensemble coherence factor of the collimated aperture
    field vs separation (m), from separations along x and y.

    With ``floor``, also the finite ensemble's floor.  Beyond r0, where theory goes to 0, each beacon's own
    field stays partly coherent across the aperture (its tilt and low orders: a phase difference nearly
    constant over the aperture), with a random phase from beacon to beacon; the ensemble mean of N such
    terms of magnitude c does not vanish but has the expected modulus c sqrt(pi / (4 N)).  The floor is
    that, with c measured per beacon: the plateau of Fig. S5b, which falls as 1 / sqrt(N) (test)."""
    n = tb.sc.n_grid
    max_sep = max_sep or int(tb.sc.receiver_aperture / tb.sc.dx * 0.75)
    m = tb.aperture.astype(np.float64)
    G = np.zeros(max_sep + 1, complex)
    I1 = np.zeros(max_sep + 1)
    single = np.zeros(max_sep + 1)  # sum over beacons of each beacon's own |coherence|
    for f in fields:
        u = tb.collimated(f)
        g = np.zeros(max_sep + 1, complex)
        i1 = np.zeros(max_sep + 1)
        for s in range(max_sep + 1):
            for a, b, ma, mb in ((u[:, s:], u[:, :n - s], m[:, s:], m[:, :n - s]),
                                 (u[s:, :], u[:n - s, :], m[s:, :], m[:n - s, :])):
                w = ma * mb
                g[s] += np.sum(a * np.conj(b) * w) / max(w.sum(), 1)
                i1[s] += np.sqrt(np.sum(np.abs(a) ** 2 * w) * np.sum(np.abs(b) ** 2 * w)) / max(w.sum(), 1)
        G += g
        I1 += i1
        single += np.abs(g) / np.maximum(i1, 1e-300)
    sep = np.arange(max_sep + 1) * tb.sc.dx
    if not floor:
        return sep, np.abs(G) / I1
    return sep, np.abs(G) / I1, single / len(fields) * np.sqrt(np.pi / (4 * len(fields)))


def wave_structure_theory(tb: Turbulence, r: np.ndarray) -> np.ndarray:
    """Spherical-wave structure function of the discrete path: a screen at z_i
    (from the source) contributes its phase structure function at r z_i / L."""
    sc = tb.sc
    out = np.zeros_like(np.asarray(r, float))
    for zi, r0 in zip(sc.z, tb.path.r0_screens):
        if np.isfinite(r0) and zi > 0:
            out += structure_function_theory(np.maximum(r * zi / sc.length, 1e-9), r0, sc.inner_scale, sc.outer_scale)
    return out


def mtf_long_exposure(tb: Turbulence, fields: list[np.ndarray], pad: int = 4):
    """Long-exposure MTF of the collimated aperture fields (PSF averaged, then
    |FT|) against pupil separation (m), and the diffraction-limited MTF."""
    n = tb.sc.n_grid
    big = np.zeros((pad * n, pad * n), np.complex64)
    psf = np.zeros((pad * n, pad * n))
    for f in fields:
        big[:n, :n] = tb.collimated(f)
        psf += np.abs(np.fft.fft2(big)) ** 2
    otf = np.fft.ifft2(psf)
    big[:n, :n] = tb.aperture
    dl = np.fft.ifft2(np.abs(np.fft.fft2(big)) ** 2)
    k = int(tb.sc.receiver_aperture / tb.sc.dx) + 2
    sep = np.arange(k) * tb.sc.dx
    mtf = np.abs(otf[0, :k]) / np.abs(otf[0, 0])
    mdl = np.abs(dl[0, :k]) / np.abs(dl[0, 0])
    return sep, mtf, mdl


def validate(sc: Scenario, rytovs=(0.1, 0.3, 0.5, 0.7), samples: int = 40, seed: int = 0,
             pib_samples: int | None = None, progress: Callable[[int, int], None] | None = None) -> dict:
    """Every check of Figs. S5/S6 for a scenario at several Rytov numbers."""
    out = {"scenario": sc.__dict__ | {}, "structure_function": structure_function_check(sc, seed=seed), "levels": []}
    total = len(rytovs) * samples
    done = 0
    for ry in rytovs:
        tb = Turbulence(replace(sc, rytov=ry))
        chi_var, fields, pib = [], [], {"complex": [], "phase": [], "none": []}
        for s in range(samples):
            smp = tb.sample(int(np.random.SeedSequence([seed, int(ry * 1e6), s]).generate_state(1)[0]))
            chi = log_amplitude(tb, smp.field)
            chi_var.append(chi)
            fields.append(smp.field)
            if s < (pib_samples if pib_samples is not None else samples):
                for mode in pib:
                    pib[mode].append(tb.power_in_bucket(smp.field, mode, smp.screens))
            done += 1
            if progress:
                progress(done, total)
        chis = np.array(chi_var)
        sep, mu, mu_floor = coherence(tb, fields, floor=True)
        D = wave_structure_theory(tb, sep)
        msep, mtf, mdl = mtf_long_exposure(tb, fields)
        Dm = wave_structure_theory(tb, msep)
        d = np.array([zi * (1 - zi / sc.length) for zi in sc.z])
        out["levels"].append({
            "rytov_nominal": ry,
            "rytov_measured": float(chis.var()),
            "rytov_per_sample": chis.var(axis=1).tolist(),
            "rytov_weak_theory_inner_scale": log_amplitude_variance_theory(tb.path.r0_screens, d, sc.wavelength,
                                                                           sc.inner_scale, sc.outer_scale),
            "r0_m": tb.path.r0, "D_over_r0": sc.receiver_aperture / tb.path.r0,
            "coherence": {"sep_m": sep.tolist(), "measured": mu.tolist(), "theory": np.exp(-D / 2).tolist(),
                          "estimator_floor": mu_floor.tolist()},
            "mtf": {"sep_m": msep.tolist(), "measured": mtf.tolist(), "diffraction": mdl.tolist(),
                    "theory": (mdl * np.exp(-Dm / 2)).tolist()},
            "npib": pib,
        })
    return out


def plot_validation(res: dict, out_dir: Path) -> list[Path]:
    plt = pyplot()
    out_dir = Path(out_dir)
    figs = []
    lv = res["levels"]
    # 2 x 2 (a report or a slide scales a figure to its width: four panels in a row made the text unreadable)
    fig, axs = plt.subplots(2, 2, figsize=(12, 9), constrained_layout=True)
    ax = axs.ravel()
    sf = res["structure_function"]
    ax[0].loglog(sf["r_m"], sf["theory"], "k-", label="theory (same PSD)")
    ax[0].loglog(sf["r_m"], sf["measured"], "o", label="screens (ensemble)")
    ax[0].set(xlabel="separation [m]", ylabel="phase structure function D_phi [rad^2]",
              title="phase structure function of single screens (r0 = 5 cm)")
    ax[0].legend()
    nom = [l_["rytov_nominal"] for l_ in lv]
    ax[1].boxplot([l_["rytov_per_sample"] for l_ in lv], positions=nom, widths=0.05, manage_ticks=False)
    ax[1].plot(nom, [l_["rytov_measured"] for l_ in lv], "o", color="tab:blue", label="ensemble")
    ax[1].plot(nom, [l_["rytov_weak_theory_inner_scale"] for l_ in lv], "s", mfc="none", color="tab:green",
               label="weak theory with inner scale")
    lim = [0, max(nom) * 1.15]
    ax[1].plot(lim, lim, "k--", lw=0.8, label="nominal")
    ax[1].set(xlim=lim, xlabel="nominal Rytov", ylabel="measured sigma_chi^2", title="(S5a) log-amplitude variance")
    ax[1].legend(fontsize=8)
    for l_ in lv:
        c = l_["coherence"]
        x = np.array(c["sep_m"]) / l_["r0_m"]
        h = ax[2].plot(x, c["theory"], "-")[0]
        ax[2].plot(x, c["measured"], "o", ms=3, color=h.get_color(), label=f"Rytov {l_['rytov_nominal']:g}")
        if "estimator_floor" in c:  # where theory has gone (the floor describes the plateau, not the core)
            far = np.asarray(c["theory"]) < 0.1
            ax[2].plot(x[far], np.asarray(c["estimator_floor"])[far], ":", color=h.get_color(), lw=1.2)
        m = l_["mtf"]
        x = np.array(m["sep_m"]) / res["scenario"]["receiver_aperture"]
        h = ax[3].plot(x, m["theory"], "-")[0]
        ax[3].plot(x, m["measured"], "o", ms=3, color=h.get_color(), label=f"Rytov {l_['rytov_nominal']:g}")
    ax[2].set(xlabel="r / r0", ylabel="|mu|", title="(S5b) coherence factor\n(lines: theory; dotted: the finite ensemble's floor)",
              xlim=(0, 3))
    ax[2].legend(fontsize=8)
    ax[3].plot(x, lv[0]["mtf"]["diffraction"], "k:", label="diffraction limit")
    ax[3].set(xlabel="separation / D (normalised frequency)", ylabel="MTF", title="(S5c) long-exposure MTF")
    ax[3].legend(fontsize=8)
    figs.append(save_figure(fig, out_dir / "turbulence-fig-s5.png"))
    fig, ax = plt.subplots(figsize=(7, 4.6), constrained_layout=True)
    for mode, col, dx in (("complex", "tab:blue", -0.012), ("phase", "tab:red", 0.012), ("none", "0.5", 0.0)):
        data = [l_["npib"][mode] for l_ in lv]
        if not data[0]:
            continue
        b = ax.boxplot(data, positions=np.array(nom) + dx, widths=0.02, manage_ticks=False, patch_artist=True)
        for p in b["boxes"]:
            p.set_facecolor(col)
        label = {"complex": "complex-field conjugate", "phase": "phase-only conjugate", "none": "uncorrected"}[mode]
        ax.plot(np.array(nom) + dx, [np.mean(d) for d in data], "^", color=col, label=label + " (triangle: mean)")
    ax.axhline(1.0, color="k", lw=0.6, ls=":")
    ax.set(xlabel="nominal Rytov number", ylabel="NPiB (power in bucket / vacuum beam's)")
    ax.set_title("(S6) correction by back-propagation", fontsize=11, pad=30)
    ax.text(0.5, 1.01, "boxes: quartiles over the samples. NPiB > 1: that sample's turbulence focuses\nmore power "
            "into the bucket than vacuum does", transform=ax.transAxes, fontsize=7.5, ha="center", va="bottom")
    ax.legend(fontsize=8, loc="center right")
    figs.append(save_figure(fig, out_dir / "turbulence-fig-s6.png"))
    return figs

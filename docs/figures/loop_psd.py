"""The temporal spectra of the committed demo loop, plotted from its record (no loop is re-run).

``sensing/loop-demo-gain-out/loop.json`` (``metadesign loop loop-demo-gain``: the paper device, Rytov 0.5,
plane-wave f_G 99 Hz, 2 kHz, 400 frames, each closed loop at the gain its search chose) holds, per method,
the Welch PSDs of the residual's Zernike coefficients (Noll 2-11, rad rms each, on the receiver aperture).
This script sums them into tip/tilt (Noll 2, 3) and the higher orders (Noll 4-11) and marks each closed
loop's -3 dB bandwidth (:func:`metadesign.optics.control.closed_loop_bandwidth` of its gain, delay and
leak).  The loop guide (``docs/guide/loop.md``) shows the figure and quotes the band powers
(``docs/_ext/measured.py``: ``loopg_psd_*``, from the same record).

    python docs/figures/loop_psd.py        # writes docs/figures/loop-psd.png
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from metadesign.optics.control import closed_loop_bandwidth
from metadesign.plotting import pyplot, save_figure

REPO = Path(__file__).resolve().parents[2]
RECORD = REPO / "sensing" / "loop-demo-gain-out" / "loop.json"
OUT = Path(__file__).resolve().with_name("loop-psd.png")
GROUPS = (("tip/tilt (Noll 2, 3)", lambda j: j <= 3), ("higher orders (Noll 4-11)", lambda j: j >= 4))


def spectra(rep: dict) -> dict:
    """Per method: ``(f (Hz), {group: summed PSD (rad^2 / Hz)})`` from a loop report's ``modal_psd``."""
    out = {}
    for m, r in rep["methods"].items():
        p = r.get("modal_psd")
        if p is None:
            continue
        psd, noll = np.asarray(p["psd_rad2_hz"], float), np.asarray(p["noll"])
        out[m] = (np.asarray(p["f_hz"], float), {g: psd[[sel(j) for j in noll]].sum(axis=0) for g, sel in GROUPS})
    return out


def figure(rep: dict):
    plt = pyplot()
    fs, leak = rep["loop"]["rate_hz"], rep["loop"]["leak"]
    fig, axs = plt.subplots(1, 2, figsize=(12, 4.2), constrained_layout=True, sharey=True)
    for m, (f, groups) in spectra(rep).items():
        r = rep["methods"][m]
        closed = "gain" in r
        label = r["label"] + (f" (gain {r['gain']:.3g}, {r['delay_frames']:.2f} frames)" if closed else "")
        for ax, (g, _) in zip(axs, GROUPS):
            line, = ax.loglog(f[1:], groups[g][1:], color="k" if not closed else None, lw=1.2, label=label)
            if closed:
                ax.axvline(closed_loop_bandwidth(fs, r["gain"], r["delay_frames"], leak), color=line.get_color(),
                           ls=":", lw=1)
    for ax, (g, _) in zip(axs, GROUPS):
        ax.set(xlabel="f (Hz)", title=g)
    axs[0].set_ylabel("PSD, modes summed (rad^2 / Hz)")
    axs[1].legend(fontsize=8, loc="lower left", title="dotted: each closed loop's -3 dB bandwidth",
                  title_fontsize=8)
    fig.suptitle(f"modal temporal spectra, {fs:.0f} Hz loop, f_G {rep['turbulence']['greenwood_hz']:.0f} Hz, "
                 f"Rytov {rep['loop']['rytov']}")
    return fig


def main() -> Path:
    return save_figure(figure(json.loads(RECORD.read_text())), OUT)


if __name__ == "__main__":
    print(main())

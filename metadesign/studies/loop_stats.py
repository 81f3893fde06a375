"""Statistics of a loop's time series: power-in-bucket fades and temporal spectra (pure functions on arrays).

Fades (Andrews and Phillips, *Laser Beam Propagation through Random Media*, ch. 11): a fade is an interval in
which the normalised power ``p(t)`` stays below a threshold ``F_T`` dB under a reference ``<p>`` (the
series' mean, or a given one): ``p < <p> 10^(-F_T / 10)``.  From a series sampled every ``dt`` seconds:
the probability of fade ``P(p < p_T)`` (the fraction of samples below), the expected number of fades per
second ``<n>`` (downward crossings per second) and the mean fade duration ``<t> = P / <n>``.  For a
lognormal ``p`` with log-irradiance variance ``s2`` (weak fluctuations, ``s2 = ln(1 + sigma_I^2)``) the
probability of fade is ``0.5 [1 + erf((ln(p_T / <p>) + s2 / 2) / sqrt(2 s2))]`` (:func:`lognormal_fade_probability`).

Spectra: one-sided power spectral densities by Welch's method (Hann windows, half overlap) of a series
(or of each column of a modal coefficient series), and the measured rejection transfer function
``|RTF(f)|^2 = PSD_closed(f) / PSD_open(f)`` of two runs through the same turbulence.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import welch

__all__ = ["fade_statistics", "lognormal_fade_probability", "welch_psd", "rejection_measured", "cdf_points",
           "scintillation_index"]


def fade_statistics(p: np.ndarray, dt: float, threshold_db: float = 3.0, reference: float | None = None) -> dict:
    """Fade statistics of the series ``p`` (sampled every ``dt`` s) against ``threshold_db`` dB under
    ``reference`` (None: the series' mean): ``probability`` of fade, ``fades_per_s`` (downward crossings per
    second), ``mean_duration_s`` (probability / rate; NaN with no fade), ``fades`` (their count), ``threshold``
    (the level in the units of ``p``) and ``max_duration_s`` (the longest run below)."""
    p = np.asarray(p, float)
    if p.ndim != 1 or len(p) < 2 or not np.isfinite(p).all():
        raise ValueError("fade statistics: a finite 1-D series of at least two samples")
    if not (dt > 0 and math.isfinite(dt)):
        raise ValueError("fade statistics: dt must be > 0")
    ref = float(np.mean(p)) if reference is None else float(reference)
    level = ref * 10 ** (-threshold_db / 10)
    below = p < level
    prob = float(below.mean())
    starts = np.flatnonzero(below[1:] & ~below[:-1]) + 1
    n_fades = int(len(starts) + (1 if below[0] else 0))
    duration = len(p) * dt
    rate = n_fades / duration
    runs, run = [], 0
    for b in below:
        if b:
            run += 1
        elif run:
            runs.append(run)
            run = 0
    if run:
        runs.append(run)
    return {"threshold_db": float(threshold_db), "reference": ref, "threshold": level, "probability": prob,
            "fades": n_fades, "fades_per_s": rate,
            "mean_duration_s": float(prob / rate) if rate > 0 else float("nan"),
            "max_duration_s": float(max(runs) * dt) if runs else 0.0}


def lognormal_fade_probability(threshold_db: float, log_variance: float) -> float:
    """``P(p < <p> 10^(-F_T/10))`` for a lognormal ``p`` whose log has variance ``log_variance`` (its mean
    fixed by ``<p>``): Andrews and Phillips' weak-fluctuation form."""
    s2 = float(log_variance)
    if s2 <= 0:
        return 0.0
    x = math.log(10 ** (-threshold_db / 10))
    return 0.5 * (1.0 + math.erf((x + s2 / 2) / math.sqrt(2 * s2)))


def scintillation_index(p: np.ndarray) -> float:
    """``<p^2> / <p>^2 - 1`` of a series (or a sample) of irradiances."""
    p = np.asarray(p, float)
    return float(np.mean(p**2) / np.mean(p) ** 2 - 1)


def cdf_points(p: np.ndarray, lowest: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """``(values, probabilities)``: the empirical CDF ``P(p <= value)`` of a series, from its smallest sample
    (probability ``1 / n``) up, for plots on a log probability axis down to ``lowest``."""
    v = np.sort(np.asarray(p, float))
    prob = np.arange(1, len(v) + 1) / len(v)
    keep = prob >= min(lowest, prob[0])
    return v[keep], prob[keep]


def welch_psd(x: np.ndarray, fs: float, segment: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(f, one-sided PSD)`` of ``x`` (T,) or of each column of ``x`` (T, M), sampled at ``fs`` Hz, by Welch's
    method (:func:`scipy.signal.welch`) with Hann windows of ``segment`` samples (default: ``T // 8``, at least
    16) overlapping by half, the mean of each segment removed.  ``sum(PSD) df`` is the variance."""
    x = np.asarray(x, float)
    n = min(int(segment or max(16, len(x) // 8)), len(x))
    return welch(x, fs, window=np.hanning(n), nperseg=n, noverlap=n - max(1, n // 2), detrend="constant",
                 scaling="density", axis=0)


def rejection_measured(closed: np.ndarray, open_: np.ndarray, fs: float,
                       segment: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(f, |RTF|^2)``: the ratio of the closed-loop residual's PSD to the open-loop disturbance's, both of
    the same turbulence (a series or modal columns: summed over modes)."""
    f, pc = welch_psd(closed, fs, segment)
    _, po = welch_psd(open_, fs, segment)
    if pc.ndim == 2:
        pc, po = pc.sum(axis=1), po.sum(axis=1)
    return f, pc / np.maximum(po, 1e-300)

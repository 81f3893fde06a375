"""The loop's time-series statistics against closed forms: fades of a constructed series, the lognormal
probability of fade, Welch's PSD of white noise and of a sine, the measured rejection of a known filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from metadesign.studies.loop_stats import (
    cdf_points,
    fade_statistics,
    lognormal_fade_probability,
    rejection_measured,
    scintillation_index,
    welch_psd,
)


def test_fades_of_a_constructed_series():
    """Three fades of 2, 3 and 1 samples below 3 dB of a given reference: their count, rate, durations."""
    p = np.ones(20)
    p[[2, 3, 8, 9, 10, 19]] = 0.4  # 0.4 < 10^-0.3 = 0.501
    s = fade_statistics(p, dt=0.5, threshold_db=3.0, reference=1.0)
    assert s["fades"] == 3 and s["probability"] == pytest.approx(6 / 20)
    assert s["fades_per_s"] == pytest.approx(3 / 10) and s["mean_duration_s"] == pytest.approx(1.0)
    assert s["max_duration_s"] == pytest.approx(1.5) and s["threshold"] == pytest.approx(10 ** -0.3)
    assert fade_statistics(np.ones(5), 1.0)["fades"] == 0
    with pytest.raises(ValueError):
        fade_statistics(np.array([1.0, np.nan]), 1.0)


@pytest.mark.parametrize("sigma2", [0.05, 0.3])
def test_probability_of_fade_of_a_lognormal_series(sigma2):
    """A lognormal irradiance with scintillation index sigma_I^2: its scintillation index, and its probability
    of fade at 1, 3 and 6 dB, against Andrews and Phillips' lognormal form (s2 = ln(1 + sigma_I^2))."""
    rng = np.random.default_rng(1)
    s2 = math.log(1 + sigma2)
    p = np.exp(rng.normal(-s2 / 2, math.sqrt(s2), 400_000))  # <p> = 1
    assert scintillation_index(p) == pytest.approx(sigma2, rel=0.03)
    for db in (1.0, 3.0, 6.0):
        want = lognormal_fade_probability(db, s2)
        got = fade_statistics(p, 1e-3, db, reference=1.0)["probability"]
        assert got == pytest.approx(want, abs=3e-3 + 0.03 * want)


def test_welch_psd_of_white_noise_and_a_sine():
    """White noise of variance s^2 at fs: one-sided PSD 2 s^2 / fs and its integral the variance; a sine of
    amplitude a: a peak at its frequency holding a^2 / 2."""
    rng = np.random.default_rng(2)
    fs = 1000.0
    x = rng.normal(0, 3.0, 200_000)
    f, P = welch_psd(x, fs, segment=512)
    assert np.median(P[5:-5]) == pytest.approx(2 * 9.0 / fs, rel=0.05)
    assert P.sum() * (f[1] - f[0]) == pytest.approx(9.0, rel=0.03)
    t = np.arange(100_000) / fs
    f, P = welch_psd(2.0 * np.sin(2 * np.pi * 125.0 * t), fs, segment=1000)
    k = int(np.argmax(P))
    assert f[k] == pytest.approx(125.0) and P[k - 3:k + 4].sum() * (f[1] - f[0]) == pytest.approx(2.0, rel=0.02)
    cols = np.stack([x, 2 * x], 1)
    assert welch_psd(cols, fs, 512)[1].shape[1] == 2


def test_measured_rejection_of_a_first_difference():
    """e = d - d[k-1] rejects white noise by |1 - e^{-i w}|^2 = 2 - 2 cos(2 pi f / fs)."""
    rng = np.random.default_rng(3)
    d = rng.normal(size=300_000)
    e = d - np.concatenate([[0.0], d[:-1]])
    f, r = rejection_measured(e, d, 1.0, segment=256)
    want = 2 - 2 * np.cos(2 * np.pi * f)
    band = (f > 0.02) & (f < 0.45)
    assert np.allclose(10 * np.log10(r[band]), 10 * np.log10(want[band]), atol=0.5)


def test_cdf_points_reach_the_smallest_sample():
    v, p = cdf_points(np.arange(1000.0, 0, -1))
    assert v[0] == 1.0 and p[0] == pytest.approx(1e-3) and p[-1] == 1.0

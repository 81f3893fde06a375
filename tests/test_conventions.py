"""End-to-end sign conventions that stage 6 learns from: a known wavefront at
the telescope (tilt, defocus) goes through the beam reducer
(``Turbulence.to_metasurface``) and the as-fabricated metasurface onto the
sensor, and every PSF moves the way geometric optics says, by the amount it
says.  The references are paraxial geometry, not the code's own output."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from metadesign.conventions import centered, fft_centered
from metadesign.sensing.forward import quadrant_fields
from metadesign.sensing.model import AsFabricated, load_sensing_recipe
from metadesign.sensing.render import render_psf
from metadesign.sensing.sensor import quadrant_slices
from metadesign.turbulence.path import Scenario
from metadesign.turbulence.propagate import Turbulence


@pytest.fixture(scope="module")
def setup(demo_products):
    fab = AsFabricated.from_files(demo_products["layout"])
    sr = load_sensing_recipe(demo_products["sensor"])
    tb = Turbulence(replace(Scenario(), metasurface_aperture=fab.n_cells * fab.period))
    pupil = fab.pupil(sr.sensor.distance, sr.pupil_grid)
    return fab, sr, tb, pupil


def _received(tb, W):
    """The vacuum beacon field times exp(+i k W) (W: optical path at the receiver, m)."""
    return tb.vacuum * np.exp(1j * tb.sc.k * W)


def _peak(img, xs, ys):
    j, i = np.unravel_index(np.argmax(img), img.shape)

    def par(a, b, c):
        d = a - 2 * b + c
        return 0.5 * (a - c) / d if d != 0 else 0.0

    dx = par(*img[j, i - 1:i + 2]) if 0 < i < img.shape[1] - 1 else 0.0
    dy = par(*img[j - 1:j + 2, i]) if 0 < j < img.shape[0] - 1 else 0.0
    return xs[i] + dx * (xs[1] - xs[0]), ys[j] + dy * (ys[1] - ys[0])


def test_helpers_state_both_centrings():
    np.testing.assert_allclose(centered(4, 1.0), [-1.5, -0.5, 0.5, 1.5])
    np.testing.assert_allclose(fft_centered(4, 1.0), [-2, -1, 0, 1])


def test_tilt_moves_every_psf_by_the_geometric_amount(setup):
    fab, sr, tb, pupil = setup
    m = tb.sc.magnification  # beam reducer: receiver -> metasurface
    z = sr.sensor.distance
    shift = np.array([3e-6, -2e-6])  # wanted displacement on the focal plane (m)
    beta = shift * m / z  # tilt angle at the receiver: the reducer multiplies angles by 1/m
    X = fft_centered(tb.sc.n_grid, tb.sc.dx)
    W = beta[0] * X[None, :] + beta[1] * X[:, None]
    n = pupil.G.shape[-1]
    flat = render_psf(fab, sr, tb.to_metasurface(_received(tb, 0 * W), n), pupil=pupil).frames
    tilt = render_psf(fab, sr, tb.to_metasurface(_received(tb, W), n), pupil=pupil).frames
    Xs, Ys = sr.sensor.coords()
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sr.sensor, k)
            a = np.array(_peak(flat[p][r, c], Xs[c], Ys[r]))
            b = np.array(_peak(tilt[p][r, c], Xs[c], Ys[r]))
            np.testing.assert_allclose(b - a, shift, atol=0.25e-6, err_msg=f"pol {'xy'[p]} k {k}")


def test_converging_defocus_moves_best_focus_closer_by_the_thin_lens_amount(setup):
    fab, sr, tb, pupil = setup
    m = tb.sc.magnification
    R = 0.31  # m: radius of the converging wave at the metasurface
    X = fft_centered(tb.sc.n_grid, tb.sc.dx)
    W = -(X[None, :] ** 2 + X[:, None] ** 2) / (2 * R / m**2)  # at the receiver: R / m^2
    n = pupil.G.shape[-1]
    e_flat = tb.to_metasurface(_received(tb, 0 * W), n)
    e_def = tb.to_metasurface(_received(tb, W), n)
    shifts = {}
    for p in range(2):
        for k in range(1, 5):
            lens = fab.channels[p][k - 1]
            f = lens.focal_length
            zs = f + np.linspace(-0.25e-3, 0.1e-3, 36)
            xo = lens.offset_x + np.linspace(-8e-6, 8e-6, 41)
            yo = lens.offset_y + np.linspace(-8e-6, 8e-6, 41)
            best = []
            for e in (e_flat, e_def):
                pk = np.array([quadrant_fields(pupil, p, xo, yo, (lens.offset_x, lens.offset_y), e, [k - 1], z).max()
                               for z in zs])
                i = int(np.argmax(pk))
                assert 0 < i < len(zs) - 1
                a, b, c = pk[i - 1:i + 2]
                best.append(zs[i] + 0.5 * (a - c) / (a - 2 * b + c) * (zs[1] - zs[0]))
            measured = best[1] - best[0]
            predicted = f * R / (f + R) - f  # thin lenses in contact: 1/f' = 1/f + 1/R
            assert measured < 0, "a converging wave must pull the focus towards the metasurface"
            assert measured == pytest.approx(predicted, rel=0.1), ("xy"[p], k, measured, predicted)
            shifts[(p, k)] = measured
    # the y-pol lenses are longer (Table S1), so the same wave moves their focus more
    assert np.mean([shifts[(1, k)] for k in range(1, 5)]) < np.mean([shifts[(0, k)] for k in range(1, 5)])

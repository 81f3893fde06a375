"""prysm and hcipy fields in, the as-fabricated pupil out (#24): resampling against the analytic field,
the two libraries' grid conventions against each other, and a tilted hcipy plane wave moving every one of
the 8 spots by z tan(theta) on the sensor (geometry, independent of the code's own numbers)."""

import warnings

import numpy as np
import pytest

hcipy = pytest.importorskip("hcipy")
with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # prysm 0.21 imports pkg_resources
    prysm_prop = pytest.importorskip("prysm.propagation")

from metadesign.sensing.forward import CoarsePupil  # noqa: E402
from metadesign.sensing.interop import on_pupil, pupil_fields, sampled, to_hcipy, to_prysm  # noqa: E402

LAM = 1.55e-6


def _pupil(n=40, pitch=20e-6) -> CoarsePupil:
    X = (np.arange(n) - (n - 1) / 2) * pitch
    g = np.random.default_rng(0)
    G = (g.normal(size=(2, 4, n, n)) + 1j * g.normal(size=(2, 4, n, n))).astype(np.complex64)
    return CoarsePupil(G, X, 1, pitch, LAM, 5e-3, 0)


def _tilt(x, y, theta):
    return np.exp(1j * 2 * np.pi / LAM * np.sin(theta) * x[None, :] + 0 * y[:, None])


def test_hcipy_and_prysm_fields_land_on_the_pupil_grid_as_the_analytic_field():
    cp = _pupil()
    theta = 2e-3  # a phase ramp of 0.032 rad per 4 um input sample
    want = _tilt(cp.X, cp.X, theta)
    # hcipy: cell-centred grid, 1.2 mm wide, 4 um pitch
    grid = hcipy.make_pupil_grid(300, 1.2e-3)
    xs, ys = grid.separated_coords
    hf = hcipy.Field(_tilt(xs, ys, theta).ravel(), grid)
    got_h = on_pupil(hf, cp)
    # prysm: FFT-centred grid, mm and um
    n, dx = 300, 4e-6
    xp = (np.arange(n) - n // 2) * dx
    wf = prysm_prop.Wavefront(_tilt(xp, xp, theta), LAM * 1e6, dx * 1e3)
    got_p = on_pupil(wf, cp)
    # bilinear interpolation of a phase ramp of 0.032 rad per 4 um sample: error <= (0.032)^2 / 8
    assert np.abs(got_h - want).max() < 2e-4
    assert np.abs(got_p - want).max() < 2e-4
    # a field that does not cover the pupil is zero outside its extent
    small = hcipy.Field(np.ones(16 * 16, complex), hcipy.make_pupil_grid(16, 0.2e-3))
    cov = on_pupil(small, cp)
    inside = np.abs(cp.X) <= 0.1e-3 - 6.25e-6
    assert np.allclose(cov[np.ix_(inside, inside)], 1) and np.all(cov[~inside] == 0)


def test_wrong_wavelength_and_bare_arrays_without_pitch_are_refused():
    from metadesign.validation import ValidationError

    cp = _pupil()
    with pytest.raises(ValidationError, match="wavelength"):
        on_pupil(prysm_prop.Wavefront(np.ones((8, 8), complex), 0.633, 0.01), cp)
    with pytest.raises(ValidationError, match="pitch dx"):
        on_pupil(np.ones((8, 8), complex), cp)
    with pytest.raises(ValidationError, match="finite|NaN"):
        on_pupil(np.full((8, 8), np.nan, complex), cp, dx=1e-4)


def test_the_pupil_goes_out_to_hcipy_and_prysm_and_back():
    cp = _pupil()
    pf = pupil_fields(cp)
    assert pf.data.shape == (2, 40, 40)
    np.testing.assert_allclose(pf.data[1], cp.G[1].sum(axis=0), rtol=1e-6)
    fields = to_hcipy(pf)
    back = sampled(fields[0])
    np.testing.assert_array_equal(back.data, pf.data[0])
    np.testing.assert_allclose(back.x, cp.X)
    one = sampled(pf.data[0], dx=cp.pitch, wavelength=LAM)
    w = to_prysm(one)
    assert w.dx == pytest.approx(cp.pitch * 1e3) and w.wavelength == pytest.approx(1.55)
    both = to_prysm(pf)  # one Wavefront per polarisation, as to_hcipy gives two fields
    assert len(both) == 2 and all(x.data.shape == (40, 40) for x in both)
    np.testing.assert_array_equal(both[1].data, pf.data[1])
    assert both[0].focus(1.0, Q=2).data.shape == (80, 80)  # prysm's own propagation takes each as it is


def test_a_tilted_hcipy_wave_moves_every_spot_by_z_tan_theta(demo_products):
    """The demo device under an hcipy plane wave tilted by theta about y: each of the 8 spots' centroids
    moves along +x by z tan(theta) on the sensor plane (z: the sensor distance)."""
    from metadesign.sensing import AsFabricated, load_sensing_recipe, quadrant_slices, render_psf

    fab = AsFabricated.from_files(demo_products["layout"])
    sr = load_sensing_recipe(demo_products["sensor"])
    cp = fab.pupil(sr.sensor.distance, sr.pupil_grid)
    s = sr.sensor
    theta = 6 * s.focal_pitch / s.distance  # six pixels
    grid = hcipy.make_pupil_grid(512, 1.2 * (cp.X[-1] - cp.X[0]))
    xs, ys = grid.separated_coords
    flat = render_psf(fab, sr, pupil=cp).frames
    tilted = render_psf(fab, sr, field=on_pupil(hcipy.Field(_tilt(xs, ys, theta).ravel(), grid), cp), pupil=cp).frames
    X, _ = s.coords()

    def cx(frame, k):  # centroid of the spot's core (above half its peak: no truncated wings, no crosstalk)
        r, c = quadrant_slices(s, k)
        q = frame[r, c]
        q = np.where(q >= 0.5 * q.max(), q, 0.0)
        return float((q.sum(axis=0) * X[c]).sum() / q.sum())

    for p in range(2):
        for k in range(1, 5):
            shift = cx(tilted[p], k) - cx(flat[p], k)
            assert shift == pytest.approx(s.distance * np.tan(theta), rel=0.05), (p, k, shift)

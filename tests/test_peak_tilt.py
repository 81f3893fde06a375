"""Tip and tilt from the in-focus channel's far-field peak (issue #50): the sub-pixel peak against
analytic images, the push-pull calibration against pure tilts it was not calibrated on, and the tilt it
reads against the one that maximises the corrected field's overlap with the received one (a brute-force
search: the reference for what power in the bucket rewards)."""

import numpy as np
import pytest
from test_baselines import GEOM, synthetic_device

from metadesign.reconstruction.dataset import normalise_psf
from metadesign.reconstruction.peak_tilt import PeakTipTilt, peak_position
from metadesign.validation import InputError


@pytest.fixture(scope="module")
def setup():
    from metadesign.optics.dm import ModalDM
    from metadesign.sensing.device import Device, ReceiverCrop

    cp, sensor = synthetic_device(n=24)
    dev = Device(cp, sensor, ReceiverCrop(*GEOM))
    basis = np.asarray(ModalDM.for_crop(dev.crop, n_modes=3).influence, np.float64)
    return dev, basis, PeakTipTilt.build(dev, basis[:2], amplitude=1.0)


def _render(dev, field):
    psf, _ = normalise_psf(dev.psfs(dev.pupil_field(np.asarray(field, np.complex64))))
    return psf


def test_peak_position_finds_a_paraboloid_vertex_to_a_hundredth_of_a_pixel():
    """A sampled paraboloid's vertex is exactly what a three-point parabola recovers; a Gaussian's to a few
    hundredths of a pixel; batch shapes kept; on the border no move."""
    s = 15
    y, x = np.mgrid[:s, :s] - (s - 1) / 2
    for x0, y0 in ((0.3, -0.2), (-2.45, 3.1), (4.0, 0.0)):
        img = 100 - (x - x0) ** 2 - 2 * (y - y0) ** 2
        assert np.allclose(peak_position(img), (x0, y0), atol=1e-9)
    g = np.stack([np.exp(-((x - a) ** 2 + (y - b) ** 2) / (2 * 1.5**2)) for a, b in ((0.3, -0.2), (1.7, 2.4))])
    p = peak_position(g[None])
    assert p.shape == (1, 2, 2) and np.allclose(p[0], [(0.3, -0.2), (1.7, 2.4)], atol=0.05)
    # a peak on the border: no move along that axis (the brightest pixel itself), inside the image
    edge = np.zeros((s, s))
    edge[5, 0], edge[5, 1], edge[5, 2], edge[4, 0], edge[6, 0] = 1.0, 0.6, 0.1, 0.5, 0.3
    px, py = peak_position(edge)
    # column 0; row 5 moved towards row 4 by the parabola through 0.5, 1, 0.3: 0.5 (0.5 - 0.3) / 1.2 px
    assert px == -(s - 1) / 2 and py == pytest.approx(5 - (s - 1) / 2 - 0.1 / 1.2)
    # no light, or a non-finite pixel: NaN, not a made-up position
    bad = np.ones((3, s, s))
    bad[0] = 0.0
    bad[1, 3, 3] = np.nan
    bad[2, 7, 9] = 2.0
    p = peak_position(bad)
    assert np.all(np.isnan(p[:2])) and np.allclose(p[2], (9 - (s - 1) / 2, 7 - (s - 1) / 2))
    with pytest.raises(InputError):
        peak_position(np.zeros((4, 5)))


def test_pure_tilts_it_was_not_calibrated_on_are_read(setup):
    """Calibrated on +/-1 rad of each mode alone; read on tip and tilt together at other amplitudes: within
    10 % (and 0.05 rad) of what was applied.  The channel it reads is one of the synthetic device's two
    least defocused (diversity -/+0.57 rad of its -4..4 rad); a frame without light reads no tilt."""
    dev, basis, pt = setup
    assert pt.channel in (3, 4) and pt.interaction.shape == (2, 2)
    assert np.all(pt.estimate(np.zeros((2, 8, 16, 16), np.float32)) == 0)
    with pytest.raises(InputError):
        pt.estimate(np.zeros((16, 16)))
    for a, b in ((0.6, -0.4), (-1.5, 0.8), (0.2, 0.25)):
        c = pt.estimate(_render(dev, np.exp(1j * (a * basis[0] + b * basis[1]))))
        print(f"applied ({a}, {b}), read {np.round(c, 3)}")
        assert np.all(np.abs(c - (a, b)) <= np.maximum(0.1 * np.abs((a, b)), 0.05)), (a, b, c)
    batch = np.stack([_render(dev, np.exp(1j * 0.5 * basis[0])), _render(dev, np.exp(-1j * 0.5 * basis[1]))])
    assert pt.estimate(batch).shape == (2, 2)


def test_it_reads_the_tilt_that_maximises_the_overlap_not_the_mean_gradient(setup):
    """Aberrated, scintillated fields (smooth random phase of ~1 rad rms plus defocus, lognormal amplitude):
    the tilt the reader returns keeps >= 97 % of the best overlap |sum u exp(-i (a Z2 + b Z3))|^2 found by
    a brute-force search, on average."""
    from scipy.ndimage import gaussian_filter

    dev, basis, pt = setup
    A = basis.shape[1]
    mask = np.any(basis != 0, axis=0)
    grid = np.arange(-3, 3.001, 0.02)
    c = (np.arange(A) - (A - 1) / 2) / ((A - 1) / 2)
    rng = np.random.default_rng(4)
    kept, zero = [], []
    for _ in range(12):
        ph = gaussian_filter(rng.normal(size=(A, A)), 3)
        ph = ph / ph[mask].std() * 1.0 + 0.5 * basis[2] + rng.normal(0, 0.7) * basis[0] + rng.normal(0, 0.7) * basis[1]
        amp = np.exp(0.3 * gaussian_filter(rng.normal(size=(A, A)), 2) / 0.1)
        u = np.where(mask, amp * np.exp(1j * ph), 0)

        def overlap(t):
            return np.abs(np.sum(u * np.exp(-1j * (t[0] * basis[0] + t[1] * basis[1])))) ** 2

        # the unit-rms Noll 2 / 3 on this crop are (close to) 2 x / R, 2 y / R: a separable search, then the
        # exact modes at its best point
        E = np.exp(-1j * np.outer(2 * c, grid))
        O = np.abs(E.T @ u @ E) ** 2
        i, j = np.unravel_index(np.argmax(O), O.shape)
        best = overlap((grid[j], grid[i]))
        est = pt.estimate(_render(dev, u))
        kept.append(overlap(est) / best)
        zero.append(overlap((0.0, 0.0)) / best)
    print(f"overlap kept: reader {np.mean(kept):.3f} (min {np.min(kept):.3f}), no tilt correction {np.mean(zero):.3f}")
    assert np.mean(kept) >= 0.97 and np.mean(zero) < 0.9


def test_bad_calibrations_are_refused(setup):
    dev, basis, _ = setup
    with pytest.raises(InputError, match="basis"):
        PeakTipTilt.build(dev, basis)  # three modes
    with pytest.raises(InputError, match="amplitude"):
        PeakTipTilt.build(dev, basis[:2], amplitude=float("nan"))
    with pytest.raises(InputError, match="push harder"):
        PeakTipTilt.build(dev, basis[:2], amplitude=1e-3)

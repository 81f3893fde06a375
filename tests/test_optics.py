"""Propagation kernels against analytic optics: Airy pattern, Gaussian beam, energy."""

import numpy as np
import pytest
from scipy.special import j1

from metadesign.optics.propagation import (
    SamplingError,
    angular_spectrum,
    asm_transfer,
    cexp,
    check_asm_sampling,
    fresnel_points,
    grid,
)

LAM = 1.55e-6


def _ideal_lens_pupil(n, dx, radius, f):
    x = grid(n, dx)
    r2 = x[None, :] ** 2 + x[:, None] ** 2
    phase = 2 * np.pi / LAM * (f - np.sqrt(f * f + r2))  # Eq. 1, converging: phi <= 0
    return np.where(r2 <= radius**2, cexp(phase), 0).astype(np.complex64), x


def test_airy_pattern_fresnel_mft():
    """Ideal lens, circular pupil: first zero at 1.22 lambda N, peak = P A / (lambda f)^2, both within 1 %."""
    a, f, dx = 0.25e-3, 5e-3, 1e-6
    u, x = _ideal_lens_pupil(600, dx, a, f)
    area = np.count_nonzero(u) * dx * dx
    xo = np.linspace(0, 30e-6, 601)
    I = np.abs(fresnel_points(u, x, x, xo, np.array([0.0]), LAM, f, dx))[0] ** 2
    N = f / (2 * a)
    first_zero = xo[np.argmin(I[xo < 25e-6])]
    assert first_zero == pytest.approx(1.22 * LAM * N, rel=0.01)
    assert I[0] == pytest.approx(area * area / (LAM * f) ** 2, rel=0.01)
    v = 2 * np.pi / LAM * a * xo[1:200] / f
    airy = I[0] * (2 * j1(v) / v) ** 2
    np.testing.assert_allclose(I[1:200], airy, atol=0.01 * I[0])


def test_airy_pattern_angular_spectrum_and_energy():
    a, f, dx, n = 0.1e-3, 2e-3, 1e-6, 1024
    u, x = _ideal_lens_pupil(n, dx, a, f)
    check_asm_sampling(n, dx, LAM, f, 2 * a, a / f)
    U = angular_spectrum(u, dx, LAM, f)
    I = np.abs(U) ** 2
    c = n // 2
    # energy: the propagator conserves the power of the band-limited field exactly (Parseval) ...
    H = asm_transfer(u.shape, dx, LAM, f)
    band_power = (np.abs(np.fft.fft2(u)) ** 2 * (H != 0)).sum() / u.size
    assert I.sum() == pytest.approx(band_power, rel=1e-5)
    # ... and the hard-edged pupil loses < 1 % of its power outside the band limit
    assert I.sum() == pytest.approx((np.abs(u) ** 2).sum(), rel=0.01)
    prof = I[c - 1: c + 1, :].mean(axis=0)  # grid is centred between samples: average the two middle rows
    N = f / (2 * a)
    zero = 1.22 * LAM * N
    xs = x[c:c + 25]  # 0.5 .. 24.5 um: the first zero only
    i0 = np.argmin(prof[c:c + 25])
    assert xs[i0] == pytest.approx(zero, abs=dx)  # within one sample of the analytic first zero
    area = np.count_nonzero(u) * dx * dx
    assert prof.max() == pytest.approx(area**2 / (LAM * f) ** 2, rel=0.03)


def test_gaussian_beam_width_and_energy():
    """A collimated Gaussian waist w0 spreads as w(z) = w0 sqrt(1 + (z/zR)^2)."""
    w0, dx, n = 20e-6, 1e-6, 512
    x = grid(n, dx)
    u = np.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / w0**2).astype(np.complex64)
    zR = np.pi * w0**2 / LAM
    for z in (0.5 * zR, 2 * zR):
        U = angular_spectrum(u, dx, LAM, z)
        I = np.abs(U) ** 2
        assert I.sum() == pytest.approx((np.abs(u) ** 2).sum(), rel=1e-5)
        r2 = x[None, :] ** 2 + x[:, None] ** 2
        w = np.sqrt(2 * (I * r2).sum() / I.sum() / 2 * 2)  # second moment: <r^2> = w^2 / 2
        assert w == pytest.approx(w0 * np.sqrt(1 + (z / zR) ** 2), rel=0.01)
        # on-axis phase: Gouy phase -arctan(z/zR) on top of k z (exp(+ikz) convention)
        ph = np.angle(U[n // 2, n // 2] * np.exp(-1j * 2 * np.pi / LAM * z))
        assert ph == pytest.approx(-np.arctan(z / zR), abs=0.02)


def test_sampling_checks_refuse_aliasing():
    with pytest.raises(SamplingError, match="under-samples"):
        check_asm_sampling(1024, 20e-6, LAM, 5e-3, 5e-3, 0.05)
    with pytest.raises(SamplingError, match="pad to"):
        check_asm_sampling(256, 1e-6, LAM, 5e-3, 0.2e-3, 0.05)


def test_branch_points_count_the_vortices_of_a_field_and_the_irrotational_part_drops_them():
    """A field with a +1 zero and a -1 zero (the product of (z - z1) and conj(z - z2)) over a smooth phase:
    exactly those two charges, on the plaquettes that hold the zeros; a smooth phase has none.  A vortex
    at the centre of the disc has a solenoidal phase gradient tangent to the rim, so the least-squares
    part of its field is the smooth phase alone (to a few hundredths of a radian, the grid's), while the
    vortex's own phase is ~1.8 rad rms; without the vortex it is the smooth phase to 1e-9 (piston
    removed)."""
    from metadesign.optics.phase import branch_points, irrotational_phase, wrap

    n = 64
    y, x = np.mgrid[0:n, 0:n] + 0.0
    m = (x - 31.5) ** 2 + (y - 31.5) ** 2 <= 30.0**2
    smooth = 0.8 * np.cos(2 * np.pi * x / 50) + 3.0 * (y / n) ** 2
    z1, z2 = (20.5 + 25.5j), (42.5 + 36.5j)  # plaquette centres
    z = x + 1j * y
    q = branch_points(np.angle((z - z1) * np.conj(z - z2) * np.exp(1j * smooth)), m)
    assert q.sum() == 0 and np.abs(q).sum() == 2
    assert q[25, 20] == 1 and q[36, 42] == -1  # (row, column) of the plaquettes holding z1 and z2
    assert np.abs(branch_points(wrap(smooth), m)).sum() == 0

    def piston_free(p):
        return (p - p[m].mean()) * m

    c = 31.5 + 31.5j
    vortex = np.angle(z - c)
    assert branch_points(vortex, m)[31, 31] == 1
    got = piston_free(irrotational_phase(wrap(vortex + smooth), m))
    err = np.sqrt(np.mean((got - piston_free(smooth))[m] ** 2))
    assert err < 0.05
    assert np.sqrt(np.mean(piston_free(vortex)[m] ** 2)) > 1.5  # what was dropped
    np.testing.assert_allclose(piston_free(irrotational_phase(wrap(smooth), m)), piston_free(smooth), atol=1e-9)

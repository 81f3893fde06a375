"""Baselines: the torch twin of the PSF path (parity with numpy, gradients vs finite differences), the
phase-diversity retrieval (recovers a known aberration), the Shack-Hartmann sensor (known slopes and
phases), Zernike polynomials, and ``metadesign compare`` / ``retrieve`` end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

torch = pytest.importorskip("torch")


def synthetic_device(n: int = 32, D: float = 1e-3, z: float = 50e-3, wl: float = 1.55e-6, diversity: float = 4.0):
    """A metasurface-like pupil built from its definition: channel k of polarisation p steers to quadrant
    k's centre (the linear phase ``k0 c . X / z`` of a lens focused there, demodulated) with its own
    defocus ``d_pk rho^2`` (d from -diversity to +diversity rad); a 64 x 64 px sensor, 16^2 tensors."""
    from metadesign.optics.propagation import cexp
    from metadesign.sensing.forward import CoarsePupil
    from metadesign.sensing.sensor import SensorSpec

    sensor = SensorSpec(width_px=64, height_px=64, pixel_pitch=15e-6, magnification=1.0, distance=z, tensor_size=16)
    pitch = D / n
    X = (np.arange(n) - (n - 1) / 2) * pitch
    r2 = (X[None, :] ** 2 + X[:, None] ** 2) / (D / 2) ** 2
    k0 = 2 * np.pi / wl
    G = np.zeros((2, 4, n, n), np.complex64)
    div = np.linspace(-diversity, diversity, 8)
    for p in range(2):
        for k in range(1, 5):
            cx, cy = sensor.quadrant_centre(k)
            G[p, k - 1] = (r2 <= 1) * cexp(k0 * (cx * X[None, :] + cy * X[:, None]) / z + div[4 * p + k - 1] * r2) / 4
    return CoarsePupil(G, X, 1, pitch, wl, z, 0), sensor


GEOM = (22, 21, 64, 2.5e-3, 5e-2)  # crop start, crop size, turbulence grid, dx, receiver aperture


def _smooth_field(shape, rng, scale=3):
    from scipy.ndimage import gaussian_filter

    re = gaussian_filter(rng.normal(size=shape), scale)
    im = gaussian_filter(rng.normal(size=shape), scale)
    return (re + 1j * im) / np.std(re)


def test_twin_equals_the_numpy_psf_path():
    """The exact twin reproduces sensor_frames + psf_tensor (1e-5) for a random pupil and field, and the
    crop resampling reproduces to_metasurface's cubic spline on a zero-embedded crop."""
    from metadesign.sensing.forward import CoarsePupil, sensor_frames
    from metadesign.sensing.sensor import SensorSpec, psf_tensor
    from metadesign.sensing.twin import TorchTwin, crop_to_pupil, twin_operators

    rng = np.random.default_rng(0)
    n = 24
    G = np.stack([[_smooth_field((n, n), rng, 2) for _ in range(4)] for _ in range(2)]).astype(np.complex64)
    X = (np.arange(n) - (n - 1) / 2) * 40e-6
    cp = CoarsePupil(G, X, 4, 10e-6, 1.55e-6, 20e-3, 0)
    sensor = SensorSpec(width_px=40, height_px=24, pixel_pitch=15e-6, magnification=10, distance=20e-3,
                        tensor_size=7)  # 20 x 12 px quadrants, 7 x 7: fractional area weights
    e = _smooth_field((n, n), rng, 3).astype(np.complex64)
    ref = psf_tensor(sensor_frames(cp, sensor, e), sensor)
    twin = TorchTwin(twin_operators(cp, sensor))
    with torch.no_grad():
        out = twin.tensor(torch.from_numpy(e)[None])[0].numpy()
    assert np.linalg.norm(out - ref) / np.linalg.norm(ref) < 1e-5
    # crop -> pupil grid: the crop embedded in zeros, map_coordinates(order=3) in 2D (scipy), and the twin's matrices
    c0, a, ng, dx, d2 = GEOM
    crop = _smooth_field((a, a), rng, 2).astype(np.complex64)
    ref_e = crop_to_pupil(crop, ng, dx, d2, c0, n)
    twin = TorchTwin(twin_operators(cp, sensor, GEOM))
    with torch.no_grad():
        mine = twin.pupil_field(torch.from_numpy(crop)[None])[0].numpy()
    from metadesign.sensing.twin import crop_interpolator

    _, mask = crop_interpolator(ng, dx, d2, c0, a, n)
    assert np.linalg.norm(mine * mask - ref_e) / np.linalg.norm(ref_e) < 1e-5
    with torch.no_grad():
        full = twin.from_crop(torch.from_numpy(crop)[None])[0].numpy()
    ref_full = psf_tensor(sensor_frames(cp, sensor, ref_e), sensor)
    assert np.linalg.norm(full - ref_full) / np.linalg.norm(ref_full) < 1e-5


def test_twin_gradient_matches_finite_differences():
    """d/d phi of a weighted sum of the normalised tensor (double precision) against central differences."""
    from metadesign.sensing.twin import TorchTwin, normalise, twin_operators

    cp, sensor = synthetic_device(n=16)
    twin = TorchTwin(twin_operators(cp, sensor, GEOM), double=True)
    rng = np.random.default_rng(1)
    a = GEOM[1]
    amp = torch.from_numpy(np.abs(_smooth_field((a, a), rng, 2)) + 0.2)
    w = torch.from_numpy(rng.normal(size=(1, 8, 16, 16)))
    phi0 = torch.from_numpy(rng.normal(0, 1.0, (1, a, a)))

    def f(phi):
        return (w * normalise(twin.from_crop(torch.polar(amp, phi)))).sum()

    phi = phi0.clone().requires_grad_(True)
    f(phi).backward()
    g = phi.grad[0].numpy()
    h = 1e-6
    for (i, j) in [(10, 10), (7, 12), (3, 10), (15, 6)]:
        e = torch.zeros_like(phi0)
        e[0, i, j] = h
        with torch.no_grad():
            fd = (f(phi0 + e) - f(phi0 - e)).item() / (2 * h)
        assert g[i, j] == pytest.approx(fd, rel=1e-6, abs=1e-9 * max(1.0, abs(fd)))
    assert np.abs(g).max() > 1e-4  # the field does reach the sensor


def test_approximate_twin_is_close_and_rebin_preserves_the_pupil_sum():
    from metadesign.sensing.twin import rebin_pupil, twin_error

    cp, sensor = synthetic_device(n=32, diversity=2.0)
    r = rebin_pupil(cp, 2)
    assert r.G.shape[-1] == 16 and r.pitch == pytest.approx(2 * cp.pitch)
    np.testing.assert_allclose(r.G.sum(axis=(-2, -1)) * 4, cp.G.sum(axis=(-2, -1)), rtol=1e-5)
    np.testing.assert_allclose(r.X, cp.X.reshape(-1, 2).mean(axis=1))
    rng = np.random.default_rng(2)
    a = GEOM[1]
    fields = np.stack([np.exp(1j * 0.5 * _smooth_field((a, a), rng, 3).real) for _ in range(3)])
    e_fine = twin_error(cp, sensor, GEOM, fields, 1, 2)
    assert e_fine < 0.05


def test_zernike_are_orthonormal_on_the_disk():
    from metadesign.optics.zernike import noll_to_nm, zernike, zernike_basis

    assert [noll_to_nm(j) for j in range(1, 12)] == [(0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1),
                                                     (3, 1), (3, -3), (3, 3), (4, 0)]
    r = np.linspace(0, 1, 7)
    np.testing.assert_allclose(zernike(4, r, 0 * r), np.sqrt(3) * (2 * r**2 - 1))  # defocus
    np.testing.assert_allclose(zernike(2, r, 0 * r), 2 * r)  # x tilt
    Z = zernike_basis(20, 401, 200.0)
    ap = Z[0] != 0
    ap |= np.hypot(*(np.mgrid[0:401, 0:401] - 200)) <= 200
    M = Z.reshape(20, -1)[:, ap.ravel()]
    gram = M @ M.T / ap.sum()
    np.testing.assert_allclose(gram, np.eye(20), atol=5e-3)


def test_retrieval_recovers_a_known_aberration():
    """Noise-free 8 PSFs of a known Zernike aberration (1.2 rad RMS) rendered by the exact twin: the
    retrieval finds it to < 0.05 rad RMS (piston removed), from a zero start."""
    from metadesign.optics.zernike import zernike
    from metadesign.reconstruction.retrieval import RetrievalConfig, RetrievalContext, retrieve
    from metadesign.sensing.twin import normalise

    cp, sensor = synthetic_device()
    cfg = RetrievalConfig(coarse=(1, None), fine=(1, None), modal_orders=(2, 4), modal_iterations=100,
                          zonal_iterations=50, starts=3, misfit="amplitude", amplitude=False, lr_modal=0.1,
                          lr_zonal=0.02)
    from metadesign.sensing.device import Device, ReceiverCrop

    ctx = RetrievalContext.build(Device(cp, sensor, ReceiverCrop(*GEOM)), cfg)
    a = GEOM[1]
    x = (np.arange(a) - 10) / 10.0
    X, Y = np.meshgrid(x, x)
    r, th = np.hypot(X, Y), np.arctan2(Y, X)
    coef = np.random.default_rng(3).normal(0, 0.3, 9)
    truth = sum(c * zernike(j, r, th) for c, j in zip(coef, range(2, 11)))
    C = torch.from_numpy((ctx.support.numpy() * np.exp(1j * truth)).astype(np.complex64))[None]
    with torch.no_grad():
        data = normalise(ctx.fine.from_crop(C))
    out = retrieve(data, ctx, cfg)
    ap = ctx.ap
    d = np.exp(1j * (out["phi"][0].numpy() - truth))[ap]
    d = np.angle(d * np.conj(d.mean()))
    assert np.sqrt(np.mean(truth[ap] ** 2)) > 1.0
    assert np.sqrt(np.mean(d**2)) < 0.05
    # batch independence (Adam is elementwise): the same sample in a batch of two gives the same phase
    out2 = retrieve(torch.cat([data, data.flip(-1)]), ctx, cfg)
    np.testing.assert_allclose(out2["phi"][0].numpy(), out["phi"][0].numpy(), atol=1e-4)


def _sh(lenslets=5, **kw):
    from metadesign.reconstruction.shack_hartmann import ShackHartmann, SHConfig

    # the demo geometry: 2.5 mm grid, 10 cm aperture (41-pixel crop centred on sample 128 of 256)
    return ShackHartmann(SHConfig(lenslets=lenslets, **kw), 41, 108, 256, 2.5e-3, 0.1, 1.55e-6)


def test_shack_hartmann_measures_a_tilt_and_reconstructs_smooth_phases():
    sh = _sh(5, threshold=0.0, noise_sigmas=0.0)
    x = (np.arange(41) - 20) * 2.5e-3
    X, Y = np.meshgrid(x, x)
    gx, gy = 40.0, -25.0  # rad/m: 0.8 and 0.5 rad per 2 cm lenslet, 4-6x the calibration tilt
    spots = sh.frames(np.exp(1j * (gx * X + gy * Y))[None])
    raw, valid = sh.centroids(spots, calibrated=False)
    slopes, _ = sh.centroids(spots)
    v = valid[0]
    assert v.sum() >= 16
    full = sh.fill > 0.99
    np.testing.assert_allclose(raw[0][full][:, 0], gx, rtol=0.04)  # the centroid's own pixelation bias, a few %
    np.testing.assert_allclose(slopes[0][v][:, 0], gx, rtol=0.01)  # calibrated: linear to 1 %
    np.testing.assert_allclose(slopes[0][v][:, 1], gy, rtol=0.01)
    R = 0.05
    phase = 2.0 * ((X**2 + Y**2) / R**2) + 1.0 * X * Y / R**2  # defocus + astigmatism, ~1 rad RMS
    ap = sh.ap
    for rec in ("zonal", "modal"):
        s = _sh(8, threshold=0.0, noise_sigmas=0.0, reconstructor=rec)
        est = s(np.exp(1j * phase)[None])[0]
        d = (est - phase)[ap]
        d -= d.mean()
        ref = phase[ap] - phase[ap].mean()
        assert np.sqrt(np.mean(d**2)) < 0.15 * np.sqrt(np.mean(ref**2)), rec


def test_shack_hartmann_drops_dark_subapertures():
    sh = _sh(5, min_flux=0.3)
    x = (np.arange(41) - 20) * 2.5e-3
    amp = np.ones((41, 41))
    amp[:, :8] = 1e-3  # a dark band over the first lenslet column
    _, valid = sh.centroids(sh.frames((amp * np.exp(1j * 30 * x[None, :]))[None]))
    assert not valid[0][:, 0].any() and valid[0][1:4, 1:4].all()


@pytest.mark.slow  # a study run end to end: the default suite's 10-minute budget
def test_compare_and_retrieve_cli(tmp_path, tiny_dataset):
    """Both commands on the tiny dataset: files, strict JSON, physical ordering of the references, the
    same bytes with 1 or 2 workers."""
    from pathlib import Path

    model = Path(__file__).resolve().parents[1] / "sensing" / "models" / "demo-unet-long.safetensors"
    outs = []
    for j in ("1", "2"):
        r = run_cli("compare", "NONE", str(tiny_dataset), "--split", "all", "--limit", "4", "--batch", "2",
                    "--iterations", "3", "--noise", "2", "-j", j, "-o", str(tmp_path / f"c{j}"), "--json")
        assert r.returncode == 0, r.stderr
        outs.append(json.loads(r.stdout))
    s = outs[0]["summary"]
    assert set(s["npib"]) == {"none", "shack_hartmann", "retrieval", "phase_conjugate", "complex_conjugate"}
    assert s["npib"]["none"] < s["npib"]["phase_conjugate"] <= 1.0 + 1e-6
    assert s["curves"]["retrieval"][0]["iterations"] == 0
    assert abs(s["curves"]["retrieval"][0]["npib"] - s["npib"]["none"]) < 1e-6  # zero phase = uncorrected
    assert (tmp_path / "c1" / "compare.csv").read_bytes() == (tmp_path / "c2" / "compare.csv").read_bytes()
    for f in ("compare.csv", "compare-curves.csv", "compare.json", "compare.png"):
        assert (tmp_path / "c1" / f).stat().st_size > 0
    # the committed demo model does not fit the tiny dataset's 16^2 tensors: one clear line, exit 2
    r = run_cli("retrieve", str(model), str(tiny_dataset), "--split", "all", "--limit", "2", "-o", str(tmp_path / "r"))
    assert r.returncode == 2 and "does not match" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = run_cli("retrieve", "none", str(tiny_dataset), "--split", "all", "--limit", "2", "--iterations", "2",
                "-o", str(tmp_path / "r"), "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert len(doc["convergence"]["misfit_mean"]) == 30 * 3 + 2
    assert (tmp_path / "r" / "convergence.png").is_file()


def test_phasemap_residual_is_the_16_level_quantisation_error(tmp_path, demo_products):
    """Nominal demo layout: the residual of the as-fabricated phase against Eq. 1 is the 16-level phase
    binning's error, uniform over one step: RMS = (2 pi / 16) / sqrt(12) = 0.113 rad; a width bias adds
    an atom-dependent error on top; the npz loads without pickle."""
    r = run_cli("phasemap", str(demo_products["layout"]), "--window", "10", "20", "32", "-o", str(tmp_path / "pm0"),
                "--json")
    assert r.returncode == 0, r.stderr
    st = json.loads(r.stdout)["stats"]
    q = 2 * np.pi / 16 / np.sqrt(12)
    for p in range(2):
        for v in st["binned_residual_rms_rad"][p]:
            assert 0.85 * q < v < 1.25 * q
    z = np.load(tmp_path / "pm0" / "phasemap.npz", allow_pickle=False)
    assert z["window_phase"].shape == (2, 32, 32) and z["binned_residual"].shape[:2] == (2, 4)
    d = np.angle(np.exp(1j * (z["window_phase"] - z["window_design_phase"])))
    np.testing.assert_allclose(d, z["window_residual"], atol=1e-4)
    r = run_cli("phasemap", str(demo_products["layout"]), "--bias-nm", "15", "-o", str(tmp_path / "pm1"), "--json")
    st1 = json.loads(r.stdout)["stats"]
    assert min(st1["binned_residual_rms_rad"][0]) > 1.5 * max(st["binned_residual_rms_rad"][0])
    r = run_cli("phasemap", str(demo_products["layout"]), "--window", "700", "0", "64", "-o", str(tmp_path / "pm2"))
    assert r.returncode == 2 and "inside" in r.stderr and not (tmp_path / "pm2").exists()

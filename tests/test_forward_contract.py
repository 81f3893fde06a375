"""The forward-model contract (metadesign.sensing.device): every backend answers to pupil_field / psfs /
from_crop with the same numbers; the detector alone adds noise, after rendering, with one model in numpy
and torch; estimators take no noise settings."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from test_baselines import GEOM, _smooth_field, synthetic_device

torch = pytest.importorskip("torch")


def _device():
    from metadesign.sensing.device import Device, ReceiverCrop

    cp, sensor = synthetic_device(n=24)
    c0, a, ng, dx, d2 = GEOM
    return Device(cp, sensor, ReceiverCrop(c0, a, ng, dx, d2))


def test_numpy_and_torch_backends_answer_the_same_three_calls():
    """Device (numpy: sensor_frames + psf_tensor, scipy's cubic spline) and its twin (torch matrices) give
    the same pupil fields and PSFs (1e-5) for a batch of received crops, through the same names; the
    learnable-diversity twin at its initial point too."""
    from metadesign.sensing.diversity import diversity_operators
    from metadesign.sensing.twin_diversity import DiversityTwin

    dev = _device()
    rng = np.random.default_rng(3)
    crops = np.stack([_smooth_field((GEOM[1], GEOM[1]), rng, 2) for _ in range(2)]).astype(np.complex64)
    e_np = dev.pupil_field(crops)
    ref = dev.psfs(e_np)
    assert ref.shape == (2, 8, 16, 16)
    np.testing.assert_array_equal(dev.from_crop(crops), ref)
    twin = dev.twin()
    with torch.no_grad():
        t = torch.from_numpy(crops)
        e_t = twin.pupil_field(t).numpy()
        inside = np.abs(e_np) > 0  # the numpy path applies the metasurface's mask to the field, the twin in K
        assert np.linalg.norm(e_t[inside] - e_np[inside]) / np.linalg.norm(e_np) < 1e-5
        for out in (twin.psfs(torch.from_numpy(e_np)).numpy(), twin.from_crop(t).numpy()):
            assert np.linalg.norm(out - ref) / np.linalg.norm(ref) < 1e-5
        # the synthetic device's lenses: each channel focused on its quadrant's centre at the pupil's distance
        lenses = np.array([[(dev.pupil.z, *dev.sensor.quadrant_centre(k)) for k in range(1, 5)] for _ in range(2)])
        div = DiversityTwin(diversity_operators(dev.pupil, dev.sensor, lenses, dev.geometry))
        assert np.linalg.norm(div.from_crop(t).numpy() - ref) / np.linalg.norm(ref) < 1e-4


def test_render_is_frames_then_detector_then_tensor():
    """One call per frame: render(e, detector, rng) = psf_tensor(add_noise(frames(e)))."""
    from metadesign.sensing.detector import Detector, NoiseSpec, add_noise
    from metadesign.sensing.sensor import psf_tensor

    dev = _device()
    e = dev.pupil_field(_smooth_field((GEOM[1], GEOM[1]), np.random.default_rng(0), 2).astype(np.complex64))
    clean = dev.render(e)
    np.testing.assert_array_equal(clean.frames, dev.frames(e))
    np.testing.assert_array_equal(clean.psfs, dev.psfs(e))
    noise = NoiseSpec(gaussian_sigma=0.03, photons_at_peak=500.0, read_noise_e=2.0, seed=11)
    shot = dev.render(e, Detector(noise), np.random.default_rng(5))
    want = add_noise(dev.frames(e), noise, np.random.default_rng(5))
    np.testing.assert_array_equal(shot.frames, want)
    np.testing.assert_array_equal(shot.psfs, psf_tensor(want, dev.sensor))
    # a device without a receiver crop takes pupil fields only, and says so in one line
    from metadesign.sensing.device import Device
    from metadesign.validation import ValidationError

    with pytest.raises(ValidationError, match="no receiver crop"):
        Device(dev.pupil, dev.sensor).pupil_field(np.zeros((GEOM[1], GEOM[1])))


def test_torch_detector_has_the_numpy_detectors_statistics():
    """The torch backend of the detector against the model's closed forms on a flat frame: Gaussian noise of
    sigma x peak, Poisson shot noise of variance N at N photo-electrons (plus read noise squared), the ADC's
    levels; and its Gaussian part is the additive, differentiable x + sigma peak z."""
    from metadesign.sensing.detector import Detector, NoiseSpec, add_noise_torch

    g = torch.Generator().manual_seed(0)
    x = torch.full((64, 64, 64), 2.0)
    n = add_noise_torch(x, NoiseSpec(gaussian_sigma=0.05), g)
    assert abs(float((n - x).std() / 2.0) - 0.05) < 0.002 and abs(float((n - x).mean())) < 0.002
    N, rn = 400.0, 5.0
    n = add_noise_torch(x, NoiseSpec(photons_at_peak=N, read_noise_e=rn), g)
    e = n / 2.0 * N  # detected electrons
    assert abs(float(e.mean()) - N) < 1.0 and abs(float(e.var()) / (N + rn**2) - 1) < 0.03
    q = add_noise_torch(x * torch.rand(x.shape, generator=g), NoiseSpec(bit_depth=3), g)
    peak = q.amax(dim=(-2, -1), keepdim=True)
    assert len(torch.unique(torch.round(q / peak * 7, decimals=4))) <= 8
    # per-sample levels and the gradient of the additive part
    y = torch.rand(3, 8, 16, 16, generator=g, dtype=torch.float32).requires_grad_(True)
    lv = torch.tensor([0.0, 0.02, 0.1])
    g1, g2 = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    out = Detector().read_torch(y, g1, gaussian_sigma=lv)
    z = torch.randn(y.shape, generator=g2, dtype=torch.float32)
    want = y.detach() + lv[:, None, None, None] * y.detach().amax(dim=(-2, -1), keepdim=True) * z
    assert torch.equal(out.detach(), want)
    out.sum().backward()
    assert torch.equal(y.grad, torch.ones_like(y))
    assert torch.equal(Detector().read_torch(y.detach(), g1), y.detach())  # a noiseless detector


def test_estimators_take_no_noise_settings():
    """Estimators are built from a device, their config and a model only; what they assume of the data
    (a likelihood's sigma, a centroid threshold) is their config's."""
    from metadesign.reconstruction.estimators import ESTIMATORS, make_estimator

    for cls in ESTIMATORS.values():
        params = set(inspect.signature(cls.__init__).parameters)
        assert not {p for p in params if "noise" in p}, cls
    assert not {p for p in inspect.signature(make_estimator).parameters if "noise" in p}


def test_shack_hartmann_reads_its_own_detectors_spots():
    """The Shack-Hartmann estimator reconstructs the spots its study rendered through the detector; with no
    spots given it sees a noise-free detector; the spots of a sample are the same whatever the batch."""
    from metadesign.reconstruction.estimators import ShackHartmannEstimator, sh_exposures
    from metadesign.reconstruction.shack_hartmann import SHConfig

    dev = _device()
    rng = np.random.default_rng(2)
    a = GEOM[1]
    x = np.linspace(-1, 1, a)
    rec = np.stack([np.exp(1j * (2 * x[None, :] + rng.normal(0, 0.1) * x[:, None])) for _ in range(3)])
    est = ShackHartmannEstimator(dev, SHConfig(lenslets=4, noise_percent=0.0))
    clean = est.estimate({"received": rec, "index": np.arange(3)}).numpy()
    spots0 = sh_exposures(est, rec, np.arange(3), 0.0, 1)
    np.testing.assert_array_equal(
        est.estimate({"received": rec, "index": np.arange(3), "sh_spots": spots0}).numpy(), clean)
    noisy = sh_exposures(est, rec, np.arange(3), 5.0, 1)
    assert not np.array_equal(noisy, spots0)
    np.testing.assert_array_equal(sh_exposures(est, rec[1:], np.arange(1, 3), 5.0, 1), noisy[1:])


def test_an_exposure_over_moving_turbulence_is_the_mean_frame_read_once():
    """Device.expose: the mean of the sub-steps' frames, read once by the detector (the frame's photon budget),
    then the tensor; one sub-step is render."""
    from metadesign.sensing.detector import Detector, NoiseSpec, add_noise
    from metadesign.sensing.sensor import psf_tensor

    dev = _device()
    rng = np.random.default_rng(4)
    es = [dev.pupil_field(_smooth_field((GEOM[1], GEOM[1]), rng, 2).astype(np.complex64)) for _ in range(3)]
    np.testing.assert_array_equal(dev.expose(es[:1]).frames, dev.render(es[0]).frames)
    noise = NoiseSpec(gaussian_sigma=0.02, seed=1)
    shot = dev.expose(es, Detector(noise), np.random.default_rng(9))
    mean = np.mean([dev.frames(e).astype(np.float64) for e in es], axis=0).astype(np.float32)
    want = add_noise(mean, noise, np.random.default_rng(9))
    np.testing.assert_array_equal(shot.frames, want)
    np.testing.assert_array_equal(shot.psfs, psf_tensor(want, dev.sensor))

"""Each piece of physics once (#31): one detector kernel, one split-step propagator, with independent
references (Poisson statistics, a vacuum propagation, the numpy backend for the torch one)."""

from __future__ import annotations

import numpy as np
import pytest

from metadesign.reconstruction.data import apply_noise
from metadesign.sensing.camera import CameraSpec, expose
from metadesign.sensing.sensor import NoiseSpec, add_noise


def test_dataset_noise_is_the_sensing_detector():
    x = np.random.default_rng(0).random((8, 16, 16))
    for g, p, r in ((5.0, None, 0.0), (0.0, 1000.0, 3.0), (7.3, 200.0, 0.0)):
        a = apply_noise(x, np.random.default_rng(1), g, p, r)
        b = add_noise(x, NoiseSpec(g / 100, p, r if p else 0.0), np.random.default_rng(1))
        assert a.tobytes() == b.tobytes()


def test_shot_noise_is_poisson_and_gaussian_noise_is_a_fraction_of_the_peak():
    """Analytic: photon counts have variance = mean; Gaussian noise has sigma = fraction x peak."""
    P = 400.0
    f = np.full((1, 200, 200), 0.25)
    f[0, 0, 0] = 1.0  # the peak
    e = add_noise(f, NoiseSpec(photons_at_peak=P), np.random.default_rng(2))[0, 1:] * P
    assert abs(e.mean() - 0.25 * P) < 0.02 * 0.25 * P and abs(e.var() / (0.25 * P) - 1) < 0.05
    g = add_noise(np.full((1, 200, 200), 3.0), NoiseSpec(gaussian_sigma=0.1), np.random.default_rng(3))
    assert abs(g.std() - 0.3) < 0.01
    # negative irradiance does not exist for a detector: clipped before the noise
    assert add_noise(-np.ones((1, 4, 4)), NoiseSpec(gaussian_sigma=0.0)).min() >= 0


def test_camera_counts_are_the_same_detector_in_counts():
    """expose: mean counts = irradiance / peak x peak_counts + dark (shot noise through the one kernel)."""
    cam = CameraSpec(read_noise_e=0.0, hot_pixels=0)
    f = np.full((2, 100, 100), 0.5)
    f[0, 0, 0] = 1.0
    c = expose(f, cam, np.random.default_rng(4)).astype(float)
    want = 0.5 * cam.peak_counts + cam.dark_counts
    assert abs(c[:, 1:].mean() - want) < 0.01 * want


def test_split_step_forward_backward_and_backends():
    torch = pytest.importorskip("torch")
    from metadesign.turbulence.propagate import SplitStep, split_step_torch

    rng = np.random.default_rng(5)
    n, n_s = 32, 3
    fx = np.fft.fftfreq(n, 1e-3)
    H = np.exp(-1j * np.pi * 1.55e-6 * 10 * (fx[:, None] ** 2 + fx[None, :] ** 2)).astype(np.complex64)
    absorber = np.ones((n, n), np.float32)
    phases = rng.normal(0, 1, (n_s, n, n)).astype(np.float32)
    u = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))).astype(np.complex64)
    el = SplitStep(H, absorber)
    tel = SplitStep(torch.from_numpy(H), torch.from_numpy(absorber))
    for f in ("forward", "backward"):
        a = getattr(el, f)(u, phases)
        b = getattr(tel, f)(torch.from_numpy(u), torch.from_numpy(phases)).numpy()
        assert np.abs(a - b).max() < 1e-4 * np.abs(a).max()
    # vacuum, no absorption: the propagation is unitary (power kept), and backward(conj) undoes forward
    z = np.zeros_like(phases)
    v = el.forward(u, z)
    assert np.isclose((np.abs(v) ** 2).sum(), (np.abs(u) ** 2).sum(), rtol=1e-4)
    back = np.conj(el.backward(np.conj(v), z))
    assert np.abs(back - u).max() < 1e-4 * np.abs(u).max()
    # one set of screens per sample (B, n_s, n, n) equals each sample through its own
    U = torch.from_numpy(np.stack([u, 2 * u]))
    S = torch.from_numpy(np.stack([phases, -phases]))
    per = split_step_torch(U, S, torch.from_numpy(H), torch.from_numpy(absorber), reverse=True)
    for b in range(2):
        one = split_step_torch(U[b], S[b], torch.from_numpy(H), torch.from_numpy(absorber), reverse=True)
        assert torch.equal(per[b], one)


def test_one_system_factory_is_what_the_dataset_uses(tiny_dataset, demo_products):
    """build_system gives the device, sensor and perturbation a dataset was made with: its pupil equals the
    one stored in the dataset (the same device through the same factory)."""
    from metadesign.reconstruction.dataset import load_device, open_dataset
    from metadesign.turbulence.system import build_system

    info = open_dataset(tiny_dataset)
    prov = info.attrs["provenance"]
    sys_ = build_system(demo_products["layout"], demo_products["sensor"], tensor_size=info.tensor_size)
    assert sys_.sensing.sensor.to_dict() == prov["sensor"]
    cp = sys_.pupil()
    np.testing.assert_array_equal(cp.G, load_device(tiny_dataset).pupil.G)


def test_one_content_key():
    """tasks.content_key: the canonical JSON's sha256 (an independent hashlib computation), arrays by their
    bytes, paths refused (a key never depends on where a file lies)."""
    import hashlib
    import json
    from pathlib import Path

    from metadesign.tasks import content_key

    d = {"b": [1, 2.5, "x"], "a": {"z": None, "y": True}}
    assert content_key(d) == hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()
    a = np.arange(6, dtype=np.float32)
    assert content_key(a) != content_key(a.astype(np.float64)) and content_key(a) == content_key(a.copy())
    with pytest.raises(TypeError):
        content_key({"layout": Path("/somewhere/layout.oas")})


def test_captured_fraction_interval():
    """The bootstrap interval holds the point estimate, shrinks as 1/sqrt(N), and collapses where every
    sample captures the same share (an estimate exactly c of the way from uncorrected to the conjugate)."""
    from metadesign.reconstruction.metrics import captured_fraction, captured_fraction_ci

    rng = np.random.default_rng(0)

    def draw(n):
        none = rng.uniform(0.05, 0.2, n)
        pc = none + rng.uniform(0.3, 0.6, n)
        return none, none + rng.uniform(0.5, 1.0, n) * (pc - none), pc

    small, big = draw(100), draw(1600)
    lo, hi = captured_fraction_ci(*small)
    assert lo < captured_fraction(*small) < hi
    lo2, hi2 = captured_fraction_ci(*big)
    assert 2.5 < (hi - lo) / (hi2 - lo2) < 6.0  # sqrt(16) = 4
    none, _, pc = big
    lo3, hi3 = captured_fraction_ci(none, none + 0.7 * (pc - none), pc)
    assert abs(lo3 - 0.7) < 1e-9 and abs(hi3 - 0.7) < 1e-9

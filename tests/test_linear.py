"""The linear reconstructor around the flat wavefront (issue #51): push-pull interaction matrix on a small
synthetic device, small pure modes recovered, linearity, and its per-frame latency."""

import time

import numpy as np
import pytest
from test_baselines import GEOM, synthetic_device

from metadesign.reconstruction.dataset import normalise_psf
from metadesign.reconstruction.linear import (
    LinearEstimator,
    LinearReconstructor,
    bin_tensor,
)
from metadesign.validation import InputError

N_MODES = 10


@pytest.fixture(scope="module")
def setup():
    from metadesign.optics.dm import ModalDM
    from metadesign.sensing.device import Device, ReceiverCrop

    cp, sensor = synthetic_device(n=24)
    dev = Device(cp, sensor, ReceiverCrop(*GEOM))
    basis = np.asarray(ModalDM.for_crop(dev.crop, n_modes=N_MODES).influence, np.float64)
    rec = LinearReconstructor.build(dev, basis, amplitude=0.2, bin=4, regularisation=1e-2)
    return dev, basis, rec


def _render(dev, phase):
    psf, _ = normalise_psf(dev.psfs(dev.pupil_field(np.exp(1j * phase).astype(np.complex64))))
    return psf


def test_bin_tensor_sums_blocks():
    x = np.arange(2 * 4 * 4, dtype=np.float32).reshape(2, 4, 4)
    b = bin_tensor(x, 2)
    assert b.shape == (8,)
    assert b[0] == x[0, :2, :2].sum() and b[-1] == x[1, 2:, 2:].sum()
    assert b.sum() == x.sum()
    with pytest.raises(InputError):
        bin_tensor(np.zeros((8, 10, 10)), 4)


def test_flat_wavefront_reads_zero(setup):
    dev, basis, rec = setup
    assert rec.R.dtype == np.float32 and rec.R.shape == (N_MODES, 8 * 4 * 4)
    c = rec.estimate(_render(dev, np.zeros(basis.shape[1:])))
    assert np.max(np.abs(c)) < 1e-4


@pytest.mark.parametrize("j,name", [(0, "tilt"), (2, "defocus")])
def test_small_pure_mode_is_recovered(setup, j, name):
    """0.1 rad rms of one Zernike (Noll 2: tilt, Noll 4: defocus) through the device: that mode's
    coefficient within 10 %, the others small."""
    dev, basis, rec = setup
    c = rec.estimate(_render(dev, 0.1 * basis[j]))
    others = np.delete(c, j)
    print(f"{name}: coefficient {c[j]:.4f} (0.1), largest other {np.max(np.abs(others)):.4f}")
    assert abs(c[j] - 0.1) < 0.01, (name, c)
    assert np.max(np.abs(others)) < 0.02, (name, c)


def test_output_is_linear_in_the_perturbation(setup):
    dev, basis, rec = setup
    rng = np.random.default_rng(4)
    w = rng.normal(size=N_MODES)
    w *= 0.05 / np.linalg.norm(w)
    ph = np.tensordot(w, basis, 1)
    c1, c2 = rec.estimate(_render(dev, ph)), rec.estimate(_render(dev, 2 * ph))
    rel = np.linalg.norm(c2 - 2 * c1) / np.linalg.norm(2 * c1)
    print(f"linearity: |c(2x) - 2 c(x)| / |2 c(x)| = {rel:.4f}; recovered {np.linalg.norm(c1 - w) / np.linalg.norm(w):.3f}")
    assert rel < 0.05
    assert np.linalg.norm(c1 - w) < 0.15 * np.linalg.norm(w)


def test_phase_and_estimator_shapes(setup):
    dev, basis, rec = setup
    psf = _render(dev, 0.1 * basis[1])
    ph = rec.phase(psf)
    assert ph.shape == basis.shape[1:]
    np.testing.assert_allclose(ph, np.tensordot(rec.estimate(psf), basis, 1), atol=1e-5)
    out = LinearEstimator(rec).estimate({"psf": psf[None]})
    assert out.shape == (1, *basis.shape[1:])
    np.testing.assert_allclose(out[0], ph, atol=1e-6)


def test_per_frame_latency(setup):
    """Median of 1000 single-frame reconstructions (batch 1): well under the 250 us of #51."""
    dev, basis, rec = setup
    psf = _render(dev, 0.1 * basis[0])
    rec.phase(psf)
    ts = []
    for _ in range(1000):
        t0 = time.perf_counter()
        rec.phase(psf)
        ts.append(time.perf_counter() - t0)
    med = float(np.median(ts))
    print(f"linear reconstructor latency: median {med * 1e6:.1f} us over 1000 frames")
    assert med < 250e-6


def test_bad_basis_is_refused(setup):
    dev, basis, _ = setup
    with pytest.raises(InputError):
        LinearReconstructor.build(dev, basis[:, :-1], bin=4)


def test_in_the_loop_the_metasurface_sensor_reads_the_linear_phase(setup):
    """The loop's sensor (the device's exposure, noise-free here) with the linear estimator: a received crop
    of 0.1 rad of defocus reads back as that mode's phase on the crop."""
    from metadesign.studies.loop import MetasurfaceSensor

    dev, basis, rec = setup
    s = MetasurfaceSensor(dev, LinearEstimator(rec), None, 0)
    crop = np.exp(1j * 0.1 * basis[2]).astype(np.complex64)
    ph = s.measure([crop, crop], 0)
    assert ph.shape == basis.shape[1:]
    inside = basis[0] != 0
    assert np.sqrt(np.mean((ph - 0.1 * basis[2])[inside] ** 2)) < 0.01


def test_the_loop_recipe_takes_linear_on_request(tmp_path):
    from test_loop import _recipe

    from metadesign.studies.loop_recipe import DEFAULT_METHODS, load_loop_recipe

    p = _recipe(tmp_path)
    p.write_text(p.read_text().replace('methods = ["ideal", "open"]', 'methods = ["linear", "open"]'))
    assert load_loop_recipe(p).loop.methods == ("linear", "open")
    assert "linear" not in DEFAULT_METHODS  # a recipe that names no methods runs what it ran before


class _Fixed:
    """A stand-in estimator returning one phase per frame of the batch."""

    def __init__(self, phase):
        self.phase = np.asarray(phase, np.float32)

    def estimate(self, batch):
        return np.repeat(self.phase[None], len(batch["psf"]), axis=0)


def test_tip_tilt_split_replaces_only_the_tilts(setup):
    """The main estimate's tip and tilt swapped for the linear reconstructor's, everything else kept: with a
    main estimate of 0.7 Noll 2 - 0.3 Noll 3 + 0.4 Noll 5 (orthogonal to the tilts on the disc) and a frame
    of 0.15 rad of Noll 3 and 0.1 of Noll 4, the output is 0.4 Noll 5 plus the reconstructor's tilts, which
    read the frame's 0.15 of Noll 3 (10 %) and no Noll 2."""
    from metadesign.reconstruction.linear import TipTiltSplitEstimator

    dev, basis, _ = setup
    tt = LinearReconstructor.build(dev, basis[:2], amplitude=0.2, bin=4, regularisation=1e-2)
    main = 0.7 * basis[0] - 0.3 * basis[1] + 0.4 * basis[3]
    est = TipTiltSplitEstimator(_Fixed(main), tt)
    psf = _render(dev, 0.15 * basis[1] + 0.1 * basis[2])
    out = est.estimate({"psf": psf[None]})
    assert out.shape == (1, *basis.shape[1:])
    c = tt.estimate(psf)
    assert abs(c[1] - 0.15) < 0.015 and abs(c[0]) < 0.015
    expected = 0.4 * basis[3] + c[0] * basis[0] + c[1] * basis[1]
    assert np.max(np.abs(out[0] - expected)) < 1e-4
    # the main estimate's own tilts are gone: its Noll 2 does not leak through
    assert np.max(np.abs(TipTiltSplitEstimator(_Fixed(0.7 * basis[0]), tt).estimate({"psf": psf[None]})[0]
                         - c[0] * basis[0] - c[1] * basis[1])) < 1e-4


def test_the_loop_recipe_takes_realtime_tt_and_searches_only_the_gains_it_is_told(tmp_path):
    """``realtime_tt`` on request (it needs [device] realtime); a gain table whose entry is "optimise"
    searches that loop only, the others at their given gains."""
    from test_loop import _recipe

    from metadesign.studies.loop_recipe import DEFAULT_METHODS, load_loop_recipe
    from metadesign.validation import ConfigError

    assert "realtime_tt" not in DEFAULT_METHODS
    p = _recipe(tmp_path)
    text = p.read_text()
    p.write_text(text.replace('methods = ["ideal", "open"]', 'methods = ["realtime_tt", "open"]'))
    with pytest.raises(ConfigError, match="device.realtime"):
        load_loop_recipe(p)
    p.write_text(text.replace('methods = ["ideal", "open"]', 'methods = ["ideal", "linear", "open"]\n'
                              'gain = { ideal = 0.5, linear = "optimise" }'))
    lp = load_loop_recipe(p).loop
    assert lp.optimise_gain and lp.searched(["ideal", "linear"]) == ["linear"]
    assert lp.gain == {"ideal": 0.5, "linear": "optimise"}
    p.write_text(text.replace('methods = ["ideal", "open"]', 'methods = ["ideal", "open"]\ngain = { ideal = 0.5 }'))
    lp = load_loop_recipe(p).loop
    assert not lp.optimise_gain and lp.searched(["ideal"]) == []

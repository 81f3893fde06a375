"""The real-time modal network (issue #51): its linear path is the numpy least-squares reconstructor exactly
(the independent twin), a pure tilt and a pure defocus come out of it as the linear reconstructor's closed form
says, the basis is orthonormal on the disc, the card round-trips, the recipe refuses keys of the other kind,
and the ONNX export equals torch."""

import numpy as np
import pytest
import torch
from test_baselines import GEOM, synthetic_device

from metadesign.config import ConfigError
from metadesign.reconstruction.dataset import normalise_psf
from metadesign.reconstruction.linear import LinearReconstructor
from metadesign.reconstruction.modal_net import ModalNet, ModalNetConfig, aperture_mask, modal_basis
from metadesign.reconstruction.model import load_model, save_model
from metadesign.reconstruction.train_recipe import train_recipe_from_dict
from metadesign.validation import ValidationError

torch.set_num_threads(1)

A = GEOM[1]  # 21: the synthetic device's crop


@pytest.fixture(scope="module")
def setup():
    from metadesign.sensing.device import Device, ReceiverCrop

    cp, sensor = synthetic_device(n=24)
    dev = Device(cp, sensor, ReceiverCrop(*GEOM))
    cfg = ModalNetConfig(input_size=16, aperture_size=A, modes=10, stride=2, width=4, hidden=8, bin=4)
    torch.manual_seed(0)
    net = ModalNet(cfg).eval()
    rec = LinearReconstructor.build(dev, modal_basis(cfg), amplitude=0.2, bin=4, regularisation=1e-2)
    net.set_linear(rec.R, rec.reference)
    return dev, net, rec


def _render(dev, phase):
    psf, _ = normalise_psf(dev.psfs(dev.pupil_field(np.exp(1j * phase).astype(np.complex64))))
    return psf


def test_basis_is_orthonormal_on_the_disc():
    for cfg in (ModalNetConfig(aperture_size=41, modes=60), ModalNetConfig(aperture_size=21, modes=20)):
        B, m = modal_basis(cfg), aperture_mask(cfg.aperture_size)
        G = B[:, m].astype(np.float64) @ B[:, m].T.astype(np.float64) / m.sum()
        assert np.abs(G - np.eye(len(B))).max() < 1e-4
        assert np.all(B[:, ~m] == 0)
        # the first modes are the Zernike tilts: a plane along x, then along y
        a = cfg.aperture_size
        x = np.arange(a) - (a - 1) / 2
        assert np.corrcoef(B[0][m], np.broadcast_to(x[None, :], (a, a))[m])[0, 1] > 0.999
        assert np.corrcoef(B[1][m], np.broadcast_to(x[:, None], (a, a))[m])[0, 1] > 0.999


def test_dm_basis_is_the_mirror_influence():
    cfg = ModalNetConfig(aperture_size=21, basis="dm", actuators=6, coupling=0.2)
    B = modal_basis(cfg)
    assert B.max() == pytest.approx(1.0, abs=0.02)  # a Gaussian peaking at 1 rad per unit command
    assert cfg.n_commands == len(B) > 20


def test_linear_path_equals_the_numpy_reconstructor(setup):
    """With the non-linear path at its zero start, the network's commands are R (bin(psf) - ref): the
    float32 numpy reconstructor, on frames of a random wavefront."""
    dev, net, rec = setup
    rng = np.random.default_rng(1)
    phase = 0.3 * np.tensordot(rng.normal(size=10), modal_basis(net.config), 1)
    psf = _render(dev, phase)
    with torch.no_grad():
        c = net.commands(torch.from_numpy(psf[None])).numpy()[0]
        phi = net(torch.from_numpy(psf[None])).numpy()[0]
    np.testing.assert_allclose(c, rec.estimate(psf), atol=1e-4, rtol=1e-4)
    np.testing.assert_allclose(phi, rec.phase(psf), atol=1e-4)


@pytest.mark.parametrize("j", [0, 2])
def test_pure_tilt_and_defocus(setup, j):
    """0.1 rad rms of tilt (mode 0) or defocus (mode 2) in: that command within 10 % (the linear regime
    and its regularisation), every other below 0.02 rad."""
    dev, net, _ = setup
    B = modal_basis(net.config)
    with torch.no_grad():
        c = net.commands(torch.from_numpy(_render(dev, 0.1 * B[j])[None])).numpy()[0]
    assert c[j] == pytest.approx(0.1, rel=0.1)
    assert np.abs(np.delete(c, j)).max() < 0.02


def test_card_round_trip(setup, tmp_path):
    _, net, _ = setup
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    save_model(net, tmp_path / "rt.safetensors", {"epoch": 0})
    back, card = load_model(tmp_path / "rt.safetensors")
    assert isinstance(back, ModalNet) and card["architecture"]["kind"] == "modal"
    x = torch.rand(3, 8, 16, 16)
    with torch.no_grad():
        assert torch.equal(back(x), net(x))


def test_onnx_equals_torch(setup, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    _, net, _ = setup
    x = torch.rand(2, 8, 16, 16)
    x = 8 * x / x.sum(dim=(1, 2, 3), keepdim=True)  # normalised as the network's inputs are
    path = tmp_path / "m.onnx"
    torch.onnx.export(net, (x,), str(path), input_names=["psf"], output_names=["phase"],
                      dynamic_axes={"psf": {0: "batch"}}, opset_version=17, dynamo=False)
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"psf": x.numpy()})[0]
    with torch.no_grad():
        np.testing.assert_allclose(got, net(x).numpy(), atol=1e-5)


def test_recipe_keys_of_the_other_kind_are_refused():
    with pytest.raises(ConfigError, match="model.modes"):
        train_recipe_from_dict({"model": {"modes": 50}})
    with pytest.raises(ConfigError, match="model.depth"):
        train_recipe_from_dict({"model": {"kind": "modal", "depth": 3}})
    with pytest.raises(ConfigError, match="model.kind"):
        train_recipe_from_dict({"model": {"kind": "modal"}, "refine": {"unet": "x.safetensors"}})
    r = train_recipe_from_dict({"model": {"kind": "modal", "modes": 30}})
    assert r.modal["modes"] == 30 and r.linear_init
    with pytest.raises(ValidationError, match="model.stride"):
        ModalNetConfig(input_size=64, stride=5)
    with pytest.raises(ValidationError, match="model.bin"):
        ModalNetConfig(input_size=64, bin=7)

"""The real-time network's window (issue #51): a windowed ModalNet reads only the centred square of each channel
(renormalised to sum 8), so the camera stage may compute only that square.  Checked against independent
references: an unwindowed network of the window's size on the renormalised crop; the full network it was
cropped from (exact where the crop's statement says, and not beyond it); a push-pull interaction matrix
measured directly on the window's renormalised bins; the whole camera stage's tensor; ONNX Runtime."""

import json

import numpy as np
import pytest
import torch
from conftest import run_main
from test_baselines import GEOM, synthetic_device

from metadesign.config import ConfigError
from metadesign.reconstruction.dataset import normalise_psf
from metadesign.reconstruction.linear import LinearReconstructor, bin_tensor
from metadesign.reconstruction.modal_net import (ModalNet, ModalNetConfig, crop_to_window, modal_basis,
                                                 window_reconstructor)
from metadesign.reconstruction.train_recipe import train_recipe_from_dict
from metadesign.validation import ValidationError

torch.set_num_threads(1)

# the committed real-time network's stride and bin on the 64^2 tensor, small widths
FULL = dict(input_size=64, aperture_size=21, modes=12, stride=2, width=4, hidden=16, bin=8)


def _random(cfg: ModalNetConfig, seed: int = 0) -> ModalNet:
    """A network away from its zero start: every weight and bias random (positive biases included, so the
    convolutions answer a dark input)."""
    torch.manual_seed(seed)
    net = ModalNet(cfg)
    with torch.no_grad():
        for p in net.parameters():
            p.normal_(0, 0.1)
    return net.eval()


def _light(s: int, lit: tuple[int, int], seed: int = 1, n: int = 3) -> np.ndarray:
    """Peaky random PSF tensors (n, 8, s, s) with light only in rows and columns lit[0]..lit[1]-1, the 8
    channels summing to 8."""
    x = np.zeros((n, 8, s, s), np.float32)
    r = slice(*lit)
    x[:, :, r, r] = np.random.default_rng(seed).random((n, 8, lit[1] - lit[0], lit[1] - lit[0])) ** 4
    return 8 * x / x.sum(axis=(1, 2, 3), keepdims=True)


def _commands(net, x):
    with torch.no_grad():
        return net.commands(torch.from_numpy(x)).double().numpy()


def test_the_window_is_checked_where_it_is_given():
    ModalNetConfig(**FULL, window=48)
    ModalNetConfig(**FULL, window=32)
    for w in (40, 44, 64, 80, -8):  # offsets 12 and 10 off the 8-pixel cells; the whole tensor; beyond; negative
        with pytest.raises(ValidationError, match="^model.window"):
            ModalNetConfig(**FULL, window=w)
    with pytest.raises(ConfigError, match="^model.window: applies to kind"):
        train_recipe_from_dict({"model": {"window": 48}})
    with pytest.raises(ConfigError, match="^model.window: expected 0 .* multiple of 4 x stride"):
        train_recipe_from_dict({"model": {"kind": "modal", "stride": 2, "bin": 8, "window": 44}})
    with pytest.raises(ConfigError, match="^model.window"):
        train_recipe_from_dict({"model": {"kind": "modal", "window": float("nan")}})
    r = train_recipe_from_dict({"model": {"kind": "modal", "stride": 2, "bin": 8, "window": 48}})
    assert r.modal["window"] == 48 and r.derive("again").modal["window"] == 48
    assert train_recipe_from_dict({"model": {"kind": "modal"}}).modal["window"] == 0


def test_a_windowed_network_is_an_unwindowed_one_on_its_renormalised_crop():
    """The window's output equals a network of the window's size with the same weights (its stem's scaled by
    (S / window)^2: each network's stem sees its input times its own size squared) on the crop renormalised to
    sum 8; it is independent of the light outside the window and of the input's scale."""
    cfg = ModalNetConfig(**FULL, window=48)
    net = _random(cfg)
    assert net.fc.in_features == 4 * 4 * (48 // 8) ** 2 and net.linear.in_features == 8 * (48 // 8) ** 2
    small = ModalNet(ModalNetConfig(**{**FULL, "input_size": 48}))
    small.load_state_dict({**net.state_dict(), "stem.weight": net.stem.weight.detach() * (64 / 48) ** 2})
    x = _light(64, (0, 64))
    crop = x[..., 8:56, 8:56].astype(np.float64)
    crop = (8 * crop / crop.sum(axis=(1, 2, 3), keepdims=True)).astype(np.float32)
    got, ref = _commands(net, x), _commands(small, crop)
    np.testing.assert_allclose(got, ref, atol=1e-5 * np.abs(ref).max(), rtol=0)
    y = x.copy()
    y[..., :8, :] = 5.0  # light outside the window changes nothing
    y[..., 60:] = 1.0
    np.testing.assert_array_equal(_commands(net, y), got)
    np.testing.assert_allclose(_commands(net, 3 * x), got, atol=1e-5 * np.abs(got).max(), rtol=0)


@pytest.mark.parametrize("src_window, window", [(0, 48), (48, 32)])
def test_the_cropped_network_is_the_full_one_on_light_inside_its_window(src_window, window):
    """crop_to_window: the commands of the full (or wider) network exactly (float rounding), on inputs zero
    outside the window and in its first 4 stride (8) and last 3 stride (6) rows and columns; light in the
    first margin's last row, or in the last margin, changes the answer (where the statement ends); the linear
    path alone needs only the zeros outside."""
    full = _random(ModalNetConfig(**FULL, window=src_window))
    net = crop_to_window(full, window)
    assert net.config.window == window and net.fc.in_features == 16 * (window // 8) ** 2
    a = (64 - window) // 2
    x = _light(64, (a + 8, a + window - 6))
    ref = _commands(full, x)
    np.testing.assert_allclose(_commands(net, x), ref, atol=2e-6 * np.abs(ref).max(), rtol=0)
    for lit in ((a + 7, a + window - 6), (a + 8, a + window - 5)):
        y = _light(64, lit)
        assert np.abs(_commands(net, y) - _commands(full, y)).max() > 5e-5 * np.abs(ref).max()  # 25 x rounding
    with torch.no_grad():  # the linear path: light up to the window's edge
        net.head.weight.zero_()
        net.head.bias.zero_()
        full.head.weight.zero_()
        full.head.bias.zero_()
    x = _light(64, (a, a + window))
    ref = _commands(full, x)
    np.testing.assert_allclose(_commands(net, x), ref, atol=2e-6 * np.abs(ref).max(), rtol=0)
    with pytest.raises(ValidationError, match="model.window"):
        crop_to_window(net, window)  # not a narrower window


def _device():
    from metadesign.sensing.device import Device, ReceiverCrop

    cp, sensor = synthetic_device(n=24)
    return Device(cp, sensor, ReceiverCrop(*GEOM))


def _render(dev, phase):
    psf, _ = normalise_psf(dev.psfs(dev.pupil_field(np.exp(1j * phase).astype(np.complex64))))
    return psf


def test_the_window_reconstructor_is_push_pull_on_the_windows_renormalised_bins():
    """window_reconstructor (from the whole tensor's interaction matrix, linearised renormalisation) against
    the interaction matrix measured directly by push-pull on the window's bins renormalised to sum 8; the
    windowed network's linear path with it answers a pure tilt as the linear reconstructor does."""
    dev = _device()
    cfg = ModalNetConfig(input_size=16, aperture_size=GEOM[1], modes=10, stride=1, width=4, hidden=8, bin=2,
                         window=8)
    B = modal_basis(cfg)
    amp, reg = 0.05, 1e-2
    lin = LinearReconstructor.build(dev, B, amplitude=amp, bin=2, regularisation=reg)
    R, ref = window_reconstructor(lin.interaction, lin.reference, cfg, reg)

    def measure(phase):
        w = _render(dev, phase)[:, 4:12, 4:12].astype(np.float64)
        return bin_tensor(8 * w / w.sum(), 2)

    ref_direct = measure(np.zeros(B.shape[1:]))
    M = np.stack([(measure(amp * z) - measure(-amp * z)) / (2 * amp) for z in B], axis=1)
    np.testing.assert_allclose(ref, ref_direct, rtol=1e-5, atol=1e-7)
    mtm = M.T @ M
    R_direct = np.linalg.solve(mtm + reg * np.mean(np.diag(mtm)) * np.eye(len(B)), M.T)
    assert np.abs(R - R_direct).max() < 0.02 * np.abs(R_direct).max()
    net = ModalNet(cfg).eval()
    net.set_linear(R, ref)
    with torch.no_grad():
        c = net.commands(torch.from_numpy(_render(dev, 0.1 * B[0])[None])).numpy()[0]
    assert c[0] == pytest.approx(0.1, rel=0.1)
    assert np.abs(c[1:]).max() < 0.02


@pytest.mark.parametrize("tensor, window", [(64, 48), (48, 32)])
@pytest.mark.parametrize("whole", [True, False])
def test_frame_tensor_window_is_the_whole_tensor_inside_and_zero_outside(tensor, window, whole):
    """FrameTensor(window): the whole tensor's values inside the centred window (block sums: bit for bit; the
    overlap matrices (48^2): to float32 rounding), 0 outside; normalised by the window's total; with block sums
    the pixels outside the window are never read (NaN there stays out)."""
    from metadesign.sensing.sensor import FrameTensor, SensorSpec

    sen = SensorSpec(width_px=640, height_px=512, pixel_pitch=15e-6, magnification=10.0, distance=0.05,
                     tensor_size=tensor)
    frames = (np.random.default_rng(2).random((2, 512, 640)) ** 6).astype(np.float32)
    ft, fw = FrameTensor(sen), FrameTensor(sen, window=window)
    if not whole:  # the per-quadrant path
        ft.whole = fw.whole = None
    full, got = ft(frames), fw(frames)
    a = (tensor - window) // 2
    inside = np.zeros(full.shape, bool)
    inside[:, a:a + window, a:a + window] = True
    assert got.dtype == np.float32 and got.shape == full.shape and np.all(got[~inside] == 0)
    if tensor == 64:
        np.testing.assert_array_equal(got[inside], full[inside])
    else:
        np.testing.assert_allclose(got[inside], full[inside], rtol=2e-5, atol=1e-6 * full.max())
    n = fw(frames, normalised=True)
    assert abs(float(n.sum(dtype=np.float64)) - 8.0) < 1e-4
    np.testing.assert_allclose(n, got * (8 / got.sum(dtype=np.float64)), rtol=1e-5, atol=1e-7)
    if tensor == 64:  # 4 x 5 pixel blocks in 256 x 320 quadrants: the window's pixels only
        poisoned = frames.copy()
        keep = np.zeros((256, 320), bool)
        keep[4 * a:4 * (a + window), 5 * a:5 * (a + window)] = True
        poisoned[:, ~np.tile(keep, (2, 2))] = np.nan
        np.testing.assert_array_equal(fw(poisoned), got)
        counts = (frames * 4000).astype(np.uint16)  # a camera's integers: converted where they are read
        np.testing.assert_array_equal(fw(counts)[inside], ft(counts)[inside])
    with pytest.raises(ConfigError, match="^window"):
        FrameTensor(sen, window=window + 1)


def test_a_windowed_network_exports_to_onnx_runtime():
    """The ONNX Runtime session (phase and commands), the loop's estimator and the export's contract of a
    windowed network: equal to torch to 1e-5 on inputs with light outside the window too."""
    pytest.importorskip("onnxruntime")
    from metadesign.reconstruction.export import contract
    from metadesign.reconstruction.realtime import RealtimeEstimator, ort_session

    net = _random(ModalNetConfig(input_size=16, aperture_size=21, modes=20, stride=1, width=8, hidden=32, bin=4,
                                 window=8), seed=3)
    x = _light(16, (0, 16), seed=5, n=4)
    with torch.no_grad():
        phase, cmd = net(torch.from_numpy(x)).numpy(), net.commands(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(ort_session(net, "phase").run(None, {"psf": x})[0], phase, atol=1e-5)
    np.testing.assert_allclose(ort_session(net, "commands").run(None, {"psf": x})[0], cmd, atol=1e-5)
    np.testing.assert_allclose(RealtimeEstimator(net).estimate({"psf": x}), phase, atol=1e-5)
    meta = contract(net, {})
    assert meta["metadesign.input"]["window"]["size"] == 8 and meta["metadesign.input"]["window"]["offset"] == 4
    assert meta["metadesign.architecture"]["window"] == 8


def test_train_crops_an_init_and_refuses_a_window_off_the_grid(tiny_dataset, tmp_path, capsys):
    """`train --init` of a network reading the whole 16^2 tensor into a recipe with window = 8: the card says
    where it came from and the start is the cropped network; `export --onnx` takes it; without --init its
    linear path starts from the window's reconstructor; a window whose offset is off the convolutions' cells is
    one line, exit 2, nothing written."""
    from metadesign.reconstruction.model import load_model, save_model

    base = '[model]\nkind = "modal"\nmodes = 12\nstride = 1\nwidth = 4\nhidden = 16\nbin = 4\nlinear_init = false\n'
    full = _random(ModalNetConfig(input_size=16, aperture_size=41, **{  # the tiny dataset's crop
        "modes": 12, "stride": 1, "width": 4, "hidden": 16, "bin": 4}), seed=7)
    save_model(full, tmp_path / "full.safetensors", {"epoch": 0})
    recipe = tmp_path / "w.toml"
    recipe.write_text(base + "window = 8\n[train]\nepochs = 1\nbatch = 4\nloss = \"phase\"\nlr = 1e-9\n"
                      "weight_decay = 0\n")
    rc, _, err = run_main(["train", recipe, "--dataset", tiny_dataset, "-o", tmp_path / "run",
                           "--init", tmp_path / "full.safetensors"], capsys)
    assert rc == 0, err
    model = tmp_path / "run" / "model.safetensors"
    card = json.loads(model.with_name("model.safetensors.json").read_text())
    assert card["architecture"]["window"] == 8 and card["init"]["windowed_from"] == 0
    got, _ = load_model(model)
    ref = crop_to_window(full, 8)
    for k, v in ref.state_dict().items():  # one step at lr 1e-9 from the cropped network
        np.testing.assert_allclose(got.state_dict()[k].numpy(), v.numpy(), atol=1e-6)
    rc, out, err = run_main(["export", model, "-o", tmp_path / "m.onnx", "--dataset", tiny_dataset, "--json"],
                            capsys)
    assert rc == 0, err
    assert json.loads(out)["max_abs_diff"] < 1e-4
    lin = tmp_path / "lin.toml"  # from scratch: the linear path from the window's reconstructor
    lin.write_text(base.replace("linear_init = false", "") + "window = 8\n[train]\nepochs = 1\nbatch = 4\n"
                   "loss = \"phase\"\n")
    rc, _, err = run_main(["train", lin, "--dataset", tiny_dataset, "-o", tmp_path / "lin-run"], capsys)
    assert rc == 0, err
    card = json.loads((tmp_path / "lin-run" / "model.safetensors.json").read_text())
    assert card["init"]["linear_init"]["window"] == 8 and card["init"]["linear_init"]["commands"] == 12
    bad = tmp_path / "bad.toml"
    bad.write_text(base.replace("stride = 1", "stride = 2") + "window = 8\n[train]\nepochs = 1\nbatch = 4\n")
    rc, _, err = run_main(["train", bad, "--dataset", tiny_dataset, "-o", tmp_path / "bad-run"], capsys)
    assert rc == 2 and len(err) == 1 and "model.window" in err[0], err
    assert not (tmp_path / "bad-run").exists()

"""Real-time inference (issue #51): the ONNX Runtime session equals torch (phase and commands), int8 stays
within a stated distance of fp32, a modal network trains, evaluates and exports through the project's
commands, the loop takes it, and the accelerator check runs on the CPU at small size."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import REPO, run_cli

from metadesign.reconstruction.modal_net import ModalNet, ModalNetConfig
from metadesign.reconstruction.realtime import RealtimeEstimator, ort_session

ort = pytest.importorskip("onnxruntime")
torch.set_num_threads(1)


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(3)
    m = ModalNet(ModalNetConfig(input_size=16, aperture_size=21, modes=20, stride=2, width=8, hidden=32, bin=4))
    with torch.no_grad():  # a network away from its zero start (both paths answer)
        for p in (m.head.weight, m.linear.weight):
            p.normal_(0, 0.05)
    return m.eval()


def _psf(n=4, s=16, seed=0):
    x = np.random.default_rng(seed).random((n, 8, s, s)).astype(np.float32) ** 4  # peaky, as PSFs are
    return 8 * x / x.sum(axis=(1, 2, 3), keepdims=True)


def test_session_equals_torch(net):
    x = _psf()
    with torch.no_grad():
        phase, cmd = net(torch.from_numpy(x)).numpy(), net.commands(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(ort_session(net, "phase").run(None, {"psf": x})[0], phase, atol=1e-5)
    np.testing.assert_allclose(ort_session(net, "commands").run(None, {"psf": x})[0], cmd, atol=1e-5)
    np.testing.assert_allclose(RealtimeEstimator(net).estimate({"psf": x}), phase, atol=1e-5)


def test_int8_within_five_percent_of_fp32(net):
    """Dynamic int8 (weights int8, activations per call): the phase within 5 % rms of fp32's (the benchmark
    states the captured-fraction cost on the test split)."""
    x = _psf(8, seed=1)
    a = ort_session(net, "phase").run(None, {"psf": x})[0]
    b = ort_session(net, "phase", quantize="int8").run(None, {"psf": x})[0]
    assert np.sqrt(np.mean((a - b) ** 2)) < 0.05 * np.sqrt(np.mean(a ** 2))


def test_bad_session_options(net):
    from metadesign.validation import ValidationError

    with pytest.raises(ValidationError, match="output"):
        ort_session(net, "field")
    with pytest.raises(ValidationError, match="quantize"):
        ort_session(net, quantize="int4")


def test_modal_network_trains_evaluates_and_exports(tiny_dataset, tmp_path):
    """`train` with [model] kind = "modal" (its linear path from the push-pull reconstructor on the dataset's
    device), then `evaluate` and `export --onnx` take the result as they take a U-Net."""
    recipe = tmp_path / "rt.toml"
    recipe.write_text('[model]\nkind = "modal"\nmodes = 12\nstride = 2\nwidth = 4\nhidden = 16\nbin = 4\n'
                      '[train]\nepochs = 1\nbatch = 4\nloss = "phase"\nlr = 1e-3\n')
    r = run_cli("train", str(recipe), "--dataset", str(tiny_dataset), "-o", str(tmp_path / "run"))
    assert r.returncode == 0, r.stderr
    model = tmp_path / "run" / "model.safetensors"
    card = json.loads(model.with_name("model.safetensors.json").read_text())
    assert card["architecture"]["kind"] == "modal" and card["init"]["linear_init"]["commands"] == 12
    r = run_cli("evaluate", str(model), str(tiny_dataset), "--split", "all", "-o", str(tmp_path / "ev"), "--json")
    assert r.returncode == 0, r.stderr
    r = run_cli("export", str(model), "-o", str(tmp_path / "m.onnx"), "--dataset", str(tiny_dataset), "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["max_abs_diff"] < 1e-4


def test_gpu_check_runs_on_cpu_at_small_size(tmp_path):
    p = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--small", "--json", "-o",
                        str(tmp_path)], capture_output=True, text=True, timeout=300,
                       env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert p.returncode == 0, p.stderr[-2000:]
    r = json.loads(p.stdout)
    assert r["small"] and set(r["latency"]) >= {"unet", "realtime", "paper_unet"}
    assert all(v["fp32_eager"]["median_us"] > 0 for v in r["latency"].values())
    assert r["training"]["fp32"]["samples_per_s"] > 0
    assert json.loads((tmp_path / "gpu_check.json").read_text())["device"] == r["device"]


def test_distill_trains_a_student_of_a_teacher(tiny_dataset, tmp_path):
    """loss = "distill": the student's loss is the piston-free MSE to the teacher's estimates (a toy U-Net
    here); the card names the teacher; without a teacher, or a teacher without the loss, one line."""
    from conftest import tiny_model

    from metadesign.config import ConfigError
    from metadesign.reconstruction.train_recipe import train_recipe_from_dict

    teacher = tiny_model(tmp_path)
    recipe = tmp_path / "st.toml"
    recipe.write_text('[model]\nkind = "modal"\nmodes = 12\nstride = 2\nwidth = 4\nhidden = 16\nbin = 4\n'
                      'linear_init = false\n'
                      f'[train]\nepochs = 1\nbatch = 4\nloss = "distill"\nlr = 1e-3\nteacher = "{teacher}"\n')
    r = run_cli("train", str(recipe), "--dataset", str(tiny_dataset), "-o", str(tmp_path / "run"))
    assert r.returncode == 0, r.stderr
    card = json.loads((tmp_path / "run" / "model.safetensors.json").read_text())
    assert card["init"]["teacher"]["path"] == str(teacher)
    with pytest.raises(ConfigError, match="train.teacher"):
        train_recipe_from_dict({"train": {"loss": "distill"}})
    with pytest.raises(ConfigError, match="train.teacher"):
        train_recipe_from_dict({"train": {"loss": "phase", "teacher": str(teacher)}})


def test_distill_loss_is_zero_on_the_teacher_and_the_mse_of_a_known_offset():
    """The loss against a teacher is 0 for the teacher's own estimate and a piston; a known non-piston offset
    ``e`` gives its mean square over the aperture (independent arithmetic)."""
    from metadesign.reconstruction.losses import LOSSES
    from metadesign.reconstruction.model import aperture_mask

    ap = torch.tensor(aperture_mask(9), dtype=torch.float32)
    target = torch.randn(2, 9, 9)

    class Ctx:
        device = "cpu"
        targets: dict = {}
        teacher = staticmethod(lambda x: target[: len(x)])
        pib = type("P", (), {"ap": ap})()

    b = {"index": torch.tensor([0, 1]), "psf": torch.zeros(2, 8, 4, 4)}
    loss = LOSSES["distill"].fn
    assert float(loss(Ctx, target + 0.7, b, None)[0]) < 1e-10
    e = torch.zeros(9, 9)
    e[:, 4:] = 1.0
    m = ap.numpy() > 0
    en = e.numpy()[m] - e.numpy()[m].mean()
    assert float(loss(Ctx, target + e, b, None)[0]) == pytest.approx(float(np.mean(en ** 2)), rel=1e-5)


@pytest.mark.parametrize("tensor", [64, 48])
def test_frame_tensor_equals_psf_tensor(tensor):
    """The real-time camera stage (block sums where the windows are whole multiples of S, float32 overlap
    matrices otherwise) equals the reference area resampling (float64) to float32 rounding."""
    from metadesign.sensing.sensor import FrameTensor, SensorSpec, psf_tensor

    sen = SensorSpec(width_px=640, height_px=512, pixel_pitch=15e-6, magnification=10.0, distance=0.05,
                     tensor_size=tensor)
    frames = np.random.default_rng(2).random((2, 512, 640)) ** 6
    ref = psf_tensor(frames, sen)
    got = FrameTensor(sen)(frames)
    assert got.dtype == np.float32 and got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=2e-5, atol=1e-6 * ref.max())
    n = FrameTensor(sen)(frames, normalised=True)
    assert abs(float(n.sum(dtype=np.float64)) - 8.0) < 1e-4
    np.testing.assert_allclose(n, ref * (8 / ref.sum()), rtol=2e-5, atol=1e-6 * n.max())


def test_the_estimator_pickles_without_its_session(net):
    """A loop sends its sensors to worker processes: the estimator pickles (the session is remade there)."""
    import pickle

    est = RealtimeEstimator(net)
    x = _psf(2, seed=4)
    a = est.estimate({"psf": x})
    back = pickle.loads(pickle.dumps(est))
    np.testing.assert_allclose(back.estimate({"psf": x}), a, atol=1e-6)

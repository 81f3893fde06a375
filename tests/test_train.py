"""Stage 6b: the losses against the numpy turbulence stage and finite differences, the U-Net's
export, resume after SIGKILL, and DDP (2 gloo processes) against one process."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def small():
    """A small turbulence grid with a real sample: numpy field, screens and the torch PiB."""
    from dataclasses import replace

    from metadesign.reconstruction.dataset import received_crop
    from metadesign.reconstruction.losses import PiB
    from metadesign.turbulence.path import Scenario
    from metadesign.turbulence.propagate import Turbulence

    sc = replace(Scenario(), n_grid=64, dx=6e-3, receiver_aperture=0.1, length=400.0, rytov=0.3, inner_scale=0.02)
    tb = Turbulence(sc, check=False)
    s = tb.sample(4)
    c0, a = received_crop(sc)
    return sc, tb, s, c0, a, PiB(sc, c0, a), PiB(sc, c0, a, double=True)


def test_pib_loss_equals_the_numpy_turbulence_stage(small):
    sc, tb, s, c0, a, pib, _ = small
    sl = slice(c0, c0 + a)
    rec = tb.collimated(s.field)[sl, sl]
    scr = torch.tensor(s.screens)[None]
    phi = torch.tensor(np.angle(rec) * tb.aperture[sl, sl], dtype=torch.float32)[None]
    ref_phase = tb.power_in_bucket(s.field, "phase", s.screens)
    ref_none = tb.power_in_bucket(s.field, "none", s.screens)
    ref_cplx = tb.power_in_bucket(s.field, "complex", s.screens)
    assert float(pib.npib_phase(phi, scr)) == pytest.approx(ref_phase, rel=1e-4)
    assert float(pib.npib_phase(torch.zeros_like(phi), scr)) == pytest.approx(ref_none, rel=1e-4)
    rec_t = torch.tensor(rec.astype(np.complex64))[None]
    assert float(pib.npib_complex(rec_t, scr)) == pytest.approx(ref_cplx, rel=1e-4)
    assert ref_cplx > ref_phase > ref_none  # the ordering of Fig. S6


def test_pib_gradient_equals_finite_differences(small):
    sc, tb, s, c0, a, _, pib64 = small
    scr = torch.tensor(s.screens.astype(np.float64))[None]
    rng = np.random.default_rng(1)
    phi = torch.tensor(rng.normal(0, 0.5, (1, a, a)), requires_grad=True)

    def f(p):
        return pib64.loss(p, scr)[0].reshape(1)

    assert torch.autograd.gradcheck(f, (phi,), eps=1e-6, atol=1e-7, rtol=1e-4)


def test_phase_and_mse_losses_known_answers():
    from metadesign.reconstruction.losses import mse_loss, phase_loss
    from metadesign.reconstruction.model import aperture_mask

    ap = torch.tensor(aperture_mask(21), dtype=torch.float32)
    rng = np.random.default_rng(0)
    y, x = (np.mgrid[:21, :21] - 10) / 10
    smooth = np.stack([8 * x + 3 * x * y, 3 * (2 * (x * x + y * y) - 1) - 5 * y])  # PV > 2 pi, wrapped at the receiver
    true = torch.tensor(smooth, dtype=torch.float32)
    rec = torch.polar(torch.ones_like(true), true)
    # a piston and 2 pi wraps cost nothing in the phase loss; the MSE (against the unwrapped received
    # phase) ignores the piston but not a local 2 pi jump
    assert float(phase_loss(true + 0.7, rec, ap)) == pytest.approx(0.0, abs=1e-5)
    assert float(phase_loss(true + 2 * np.pi, rec, ap)) == pytest.approx(0.0, abs=1e-5)
    assert float(mse_loss((true + 0.7) * ap, rec, ap)) == pytest.approx(0.0, abs=1e-8)
    assert float(mse_loss(torch.angle(rec) * ap, rec, ap)) > 1.0  # the wrapped phase is not the answer
    # a small random residual of rms s: phase loss ~ s^2 (Marechal), MSE ~ s^2
    d = torch.tensor(rng.normal(0, 0.1, (2, 21, 21)), dtype=torch.float32)
    s2 = float(((d - (d * ap).sum((-2, -1), keepdim=True) / ap.sum()) ** 2 * ap).sum() / ap.sum() / 2)
    assert float(phase_loss(true + d, rec, ap)) == pytest.approx(s2, rel=0.05)
    assert float(mse_loss((true + d) * ap, rec, ap)) == pytest.approx(s2, rel=1e-4)


def test_unet_shapes_zero_start_and_safetensors_roundtrip(tmp_path):
    from metadesign.reconstruction.model import UNetConfig, build_unet, load_model, save_model
    from metadesign.validation import ValidationError

    cfg = UNetConfig(8, 4, 3, 16, 41)
    m = build_unet(cfg)
    x = torch.randn(2, 8, 16, 16)
    y = m(x)
    assert y.shape == (2, 41, 41) and float(y.detach().abs().max()) == 0.0  # zero-initialised head: flat phase
    torch.nn.init.normal_(m.head.weight)
    p, card = save_model(m, tmp_path / "m.safetensors", {"note": "test"})
    m2, c2 = load_model(p)
    torch.testing.assert_close(m2(x), m.eval()(x))
    assert c2["note"] == "test" and c2["architecture"]["base"] == 4
    raw = bytearray(p.read_bytes())
    raw[-5] ^= 0xFF
    p.write_bytes(bytes(raw))
    with pytest.raises(ValidationError, match="sha256"):
        load_model(p)
    with pytest.raises(ValidationError, match="divisible"):
        UNetConfig(8, 4, 4, 20, 41)


def _recipe(folder: Path, ds: Path, epochs=3, batch=4, extra="", lr=1e-3) -> Path:
    p = folder / "t.toml"
    p.write_text(f"""[data]
dataset = "{ds}"
noise_percent = 5.0
[model]
base = 4
depth = 3
[train]
epochs = {epochs}
batch = {batch}
lr = {lr}
lr_halve_every = 2
pretrain_loss = "phase"
pretrain_epochs = 1
loss = "pib"
{extra}""")
    return p


def _cli(*args, env_extra=None, timeout=600):
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-m", "metadesign", *map(str, args)], env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.slow  # a training run: the default suite's 10-minute budget
def test_sigkilled_training_resumes_to_the_same_loss_curve(tiny_dataset, tmp_path):
    rec = _recipe(tmp_path, tiny_dataset, epochs=4)
    ref = _cli("train", rec, "-o", tmp_path / "ref", "--json")
    assert ref.returncode == 0, ref.stderr
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    p = subprocess.Popen([sys.executable, "-m", "metadesign", "train", str(rec), "-o", str(tmp_path / "k"), "--json"],
                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    t0 = time.time()
    while time.time() - t0 < 300:
        m = tmp_path / "k" / "metrics.json"
        if m.exists() and len(json.loads(m.read_text())) >= 2:
            break
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    done = len(json.loads((tmp_path / "k" / "metrics.json").read_text()))
    assert 2 <= done < 4
    r = _cli("train", rec, "-o", tmp_path / "k", "--resume", "--json")
    assert r.returncode == 0, r.stderr
    a = json.loads((tmp_path / "ref" / "metrics.json").read_text())
    b = json.loads((tmp_path / "k" / "metrics.json").read_text())
    assert [h["epoch"] for h in b] == [1, 2, 3, 4]
    for x, y in zip(a, b):
        assert x["train_loss"] == pytest.approx(y["train_loss"], rel=1e-6)
        assert x["val_npib"] == pytest.approx(y["val_npib"], rel=1e-6)
    from metadesign.reconstruction.model import load_model

    load_model(tmp_path / "k" / "model.safetensors")  # the exported best model loads
    # a run folder is never silently overwritten
    again = _cli("train", rec, "-o", tmp_path / "k")
    assert again.returncode == 2 and "--resume" in again.stderr


@pytest.mark.slow  # a training run: the default suite's 10-minute budget
def test_two_gloo_processes_reach_the_weights_of_one(tiny_dataset, tmp_path):
    rec = _recipe(tmp_path, tiny_dataset, epochs=2, batch=4, extra="")
    one = _cli("train", rec, "-o", tmp_path / "one", "--max-steps", "3", "--json")
    assert one.returncode == 0, one.stderr
    torchrun = Path(sys.executable).with_name("torchrun")
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    two = subprocess.run([str(torchrun), "--nproc_per_node", "2", "--master_port", "29517", "-m", "metadesign", "train",
                          str(rec), "-o", str(tmp_path / "two"), "--max-steps", "3", "--json"],
                         env=env, capture_output=True, text=True, timeout=600)
    assert two.returncode == 0, two.stderr[-2000:]
    a = torch.load(tmp_path / "one" / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=True)["model"]
    moved = 0
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)
        moved += int(not torch.equal(a[k], torch.zeros_like(a[k])))
    assert moved > 0


def test_quadratic_form_equals_the_split_step_loss(small):
    sc, tb, s, c0, a, pib, _ = small
    scr = torch.tensor(s.screens)[None].repeat(2, 1, 1, 1)
    rng = np.random.default_rng(2)
    phi = torch.tensor(rng.normal(0, 1.0, (2, a, a)), dtype=torch.float32) * pib.ap
    A = pib.bucket_operator(scr)
    assert A.shape == (2, len(pib.bucket), int(pib.ap.sum()))
    torch.testing.assert_close(pib.npib_quadratic(A, phi), pib.npib_phase(phi, scr), rtol=2e-4, atol=1e-6)


def test_onnx_export_matches_torch(tmp_path, capsys):
    from metadesign.cli import main
    from metadesign.reconstruction.model import UNetConfig, build_unet, save_model

    m = build_unet(UNetConfig(8, 4, 3, 16, 41))
    torch.nn.init.normal_(m.head.weight, std=0.5)
    save_model(m, tmp_path / "m.safetensors", {})
    # the command refuses a card that names no device (a lab needs the camera contract) in one line ...
    assert main(["export", str(tmp_path / "m.safetensors"), "--onnx", str(tmp_path / "m.onnx")]) == 2
    assert "names no dataset" in capsys.readouterr().err and not (tmp_path / "m.onnx").exists()
    # ... and the network alone exports through the API
    from metadesign.reconstruction.export import export_onnx

    rep = export_onnx(tmp_path / "m.safetensors", tmp_path / "m.onnx", require_device=False)
    assert rep["max_abs_diff"] <= 1e-4 and rep["batches"] == [1, 3]
    import onnxruntime as ort

    sess = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"])
    x = np.random.default_rng(5).random((7, 8, 16, 16), dtype=np.float32)
    with torch.no_grad():
        ref = m.eval()(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(sess.run(None, {"psf": x})[0], ref, atol=1e-4)


def test_onnx_export_carries_its_preprocessing_contract(tmp_path):
    """Read back with onnxruntime alone: input shape, channel order and normalisation, output grid and
    units, the weights' sha256 from the model card."""
    import onnxruntime as ort

    from metadesign.reconstruction.export import export_onnx
    from metadesign.reconstruction.model import UNetConfig, build_unet, save_model

    save_model(build_unet(UNetConfig(8, 4, 3, 16, 41)), tmp_path / "m.safetensors",
               {"input_normalisation": "psf: each sample's 8 channels sum to 8", "noise_percent": 5.0,
                "received_crop": {"start": 108, "size": 41, "n_grid": 256, "dx_m": 0.0025}})
    export_onnx(tmp_path / "m.safetensors", tmp_path / "m.onnx", require_device=False)  # the network alone
    meta = ort.InferenceSession(str(tmp_path / "m.onnx"), providers=["CPUExecutionProvider"]) \
        .get_modelmeta().custom_metadata_map
    card = json.loads((tmp_path / "m.safetensors.json").read_text())
    inp, out = json.loads(meta["metadesign.input"]), json.loads(meta["metadesign.output"])
    assert inp["shape"] == ["batch", 8, 16, 16] and inp["channels"][0] == "x-pol QI" and len(inp["channels"]) == 8
    assert "sum to 8" in inp["normalisation"] and inp["training_noise_percent"] == 5.0
    assert out["units"] == "rad" and out["grid"]["size"] == 41 and out["grid"]["pitch_m"] == 0.0025
    assert meta["metadesign.weights_sha256"] == card["weights_sha256"]


def test_recipe_noise_is_percent_of_the_peak(tiny_dataset, tmp_path):
    """noise_percent = 5 in a recipe means 5 % of each channel's peak at load (the paper's training noise)."""
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.train import load_train_recipe

    r = load_train_recipe(_recipe(tmp_path, tiny_dataset))
    assert r.noise_percent == (5.0, 5.0)
    ds = PSFDataset(tiny_dataset, "all", **r.noise(), noise_seed=1)
    clean = PSFDataset(tiny_dataset, "all")
    d = np.stack([ds.get(i)["psf"] - clean.get(i)["psf"] for i in range(len(ds))])
    peak = np.stack([clean.get(i)["psf"] for i in range(len(ds))]).max(axis=(2, 3), keepdims=True)
    assert np.std(d / peak) == pytest.approx(0.05, rel=0.1)


@pytest.mark.slow  # a training run: the default suite's 10-minute budget
def test_quadratic_form_training_follows_the_split_step_loss(tiny_dataset, tmp_path):
    """pib_operator = "quadratic" caches each sample's bucket operator in the first PiB epoch and loads no
    screens afterwards; the loss curve must follow the split-step training's (same seed, same batches)."""
    runs = {}
    for op in ("split_step", "quadratic"):
        d = tmp_path / op
        d.mkdir()
        rec = _recipe(d, tiny_dataset, epochs=4, lr=0.01, extra=f'pib_operator = "{op}"\n')
        r = _cli("train", rec, "-o", d / "run", "--json")
        assert r.returncode == 0, r.stderr
        runs[op] = json.loads((d / "run" / "metrics.json").read_text())
    a, b = runs["split_step"], runs["quadratic"]
    assert [h["loss_name"] for h in b] == ["phase", "pib", "pib", "pib"]
    for x, y in zip(a, b):
        assert x["train_loss"] == pytest.approx(y["train_loss"], rel=2e-3)
        assert x["val_npib"] == pytest.approx(y["val_npib"], rel=2e-3)
    # the predicted phases are not negligible (else any operator would pass): NPiB moved off the flat phase's
    assert abs(b[-1]["train_npib"] - b[0]["val_npib_none"]) > 0.005


def test_least_squares_unwrapping_recovers_a_smooth_phase_whatever_lies_outside_the_aperture():
    from metadesign.reconstruction.losses import unwrap_ls

    n = 41
    y, x = (np.mgrid[:n, :n] - 20) / 20
    m = x * x + y * y <= 1
    true = 4 * (2 * (x * x + y * y) - 1) + 3 * x * y + 2 * (3 * (x * x + y * y) - 2) * x + 6 * y  # PV 17 rad
    junk = np.random.default_rng(1).uniform(-np.pi, np.pi, (n, n))
    wrapped = np.where(m, np.angle(np.exp(1j * true)), junk)
    ref = (true - true[m].mean()) * m
    assert np.abs(wrapped * m - ref).max() > 3  # the data are wrapped
    u = unwrap_ls(np.stack([wrapped, wrapped[::-1]]), m)  # batch axis
    np.testing.assert_allclose(u[0], ref, atol=1e-9)
    np.testing.assert_allclose(u[1], ((true[::-1] - true[m].mean()) * m), atol=1e-9)


def test_a_widened_unet_computes_the_same_function():
    """Net2Net widening (twice the filters at every level, group norm included): the same output to float32
    rounding on random weights, and a perturbed copy differs (the noise that lets the new width learn)."""
    import torch

    from metadesign.reconstruction.model import UNetConfig, build_unet, widen_unet

    torch.manual_seed(0)
    m = build_unet(UNetConfig(base=8, depth=4, input_size=32, aperture_size=21))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0, 0.2)  # the head starts at zero: random weights everywhere, an output to compare
    w = widen_unet(m)
    assert w.config.base == 16 and sum(p.numel() for p in w.parameters()) > 3 * sum(p.numel() for p in m.parameters())
    x = torch.randn(3, 8, 32, 32)
    with torch.no_grad():
        a, b = m.eval()(x), w.eval()(x)
        c = widen_unet(m, noise=1e-2).eval()(x)
    assert a.abs().max() > 0.1
    torch.testing.assert_close(b, a, rtol=0, atol=1e-5 * float(a.abs().max()))
    assert (c - a).abs().max() > 1e-4


def test_a_field_unet_holds_branch_points_and_starts_as_its_phase_model(tmp_path, capsys):
    """``output = "field"``: the phase of exp(i phi) + c.  Around a zero of the sum the phase winds by
    2 pi (counted independently from the wrapped differences on a loop), which no continuous phase does;
    a phase U-Net's weights in a field U-Net give the same phase; the
    field head learns (its gradient is not zero); the field U-Net exports to ONNX with the same output."""
    import torch

    from metadesign.cli import main
    from metadesign.reconstruction.model import UNetConfig, build_unet, field_phase, save_model

    n = 33
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    phi = 0.3 * xx  # a smooth phase
    # c = (x + i y) - exp(i phi): the sum is x + i y, a first-order zero at the centre
    out = field_phase(phi, xx - torch.cos(phi), yy - torch.sin(phi))
    loop = [(i, 4) for i in range(4, n - 4)] + [(n - 5, j) for j in range(4, n - 4)] + \
        [(i, n - 5) for i in range(n - 5, 3, -1)] + [(4, j) for j in range(n - 5, 3, -1)]
    vals = torch.stack([out[j, i] for i, j in loop] + [out[loop[0][1], loop[0][0]]])
    d = torch.remainder(vals[1:] - vals[:-1] + np.pi, 2 * np.pi) - np.pi
    assert abs(float(d.sum()) / (2 * np.pi) - 1) < 1e-5  # winding number 1
    assert torch.allclose(field_phase(phi, torch.zeros_like(phi), torch.zeros_like(phi)), phi, atol=1e-6)

    torch.manual_seed(0)
    m = build_unet(UNetConfig(base=4, depth=3, input_size=16, aperture_size=11))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0, 0.5)
        m.head.weight.mul_(30.0)  # phases beyond pi: the field model's are wrapped
    f = build_unet(UNetConfig(base=4, depth=3, input_size=16, aperture_size=11, output="field"))
    f.load_state_dict({**f.state_dict(), **m.state_dict()})
    x = torch.randn(2, 8, 16, 16)
    with torch.no_grad():
        a, b = m.eval()(x), f.eval()(x)
    assert a.abs().max() > 4.0
    torch.testing.assert_close(b, a, rtol=0, atol=1e-6)  # the same phase, not wrapped
    f.train()
    (f(x) * torch.randn(2, 11, 11)).sum().backward()
    assert float(f.field_head.weight.grad.abs().sum()) > 0
    with torch.no_grad():
        f.field_head.weight.normal_(0, 0.5)
    save_model(f.eval(), tmp_path / "f.safetensors", {})
    from metadesign.reconstruction.export import export_onnx

    assert export_onnx(tmp_path / "f.safetensors", tmp_path / "f.onnx", require_device=False)["max_abs_diff"] <= 1e-4


def test_init_widens_a_narrower_unet_and_starts_a_field_unet_from_a_phase_one(tmp_path):
    """``--init``: a U-Net of the same shape with half the filters is widened (the same function but for
    the 1 % perturbation), a phase U-Net starts a field U-Net (the same corrections), anything else is
    one line."""
    import torch

    from metadesign.reconstruction.model import UNetConfig, build_unet, save_model
    from metadesign.reconstruction.train import _build_model, train_recipe_from_dict
    from metadesign.validation import ValidationError

    torch.manual_seed(1)
    m = build_unet(UNetConfig(base=4, depth=3, input_size=16, aperture_size=11))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0, 0.5)
    save_model(m, tmp_path / "m.safetensors", {})
    x = torch.randn(2, 8, 16, 16)
    with torch.no_grad():
        ref = m.eval()(x)

    def recipe(**model):
        return train_recipe_from_dict({"model": {"depth": 3, **model}, "train": {"seed": 3}}, "t")

    wide, rec = _build_model(recipe(base=8), 16, 11, tmp_path / "m.safetensors", "cpu")
    assert rec["widened_from_base"] == 4 and wide.config.base == 8
    with torch.no_grad():
        assert 0 < float((wide.eval()(x) - ref).abs().max()) < 0.2 * float(ref.abs().max())
    field, rec = _build_model(recipe(base=4, output="field"), 16, 11, tmp_path / "m.safetensors", "cpu")
    assert rec["output_from"] == "phase" and field.config.output == "field"
    with torch.no_grad():
        b = field.eval()(x)
    torch.testing.assert_close(b, ref, rtol=0, atol=1e-6)
    with pytest.raises(ValidationError, match="differs from the recipe"):
        _build_model(recipe(base=4, norm="batch"), 16, 11, tmp_path / "m.safetensors", "cpu")


def test_evaluation_reports_the_vortex_free_reference(tiny_dataset, tmp_path):
    """Beside the phase conjugate, the evaluation reports the NPiB of its vortex-free part (the least-squares
    phase of the received field) and the branch points per sample, counted here again by walking each
    plaquette's four wrapped differences; the tiny set's fields all hold branch points, so the vortex-free
    phase falls short of the phase conjugate, and the summary carries both."""
    from conftest import tiny_model

    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.evaluate import evaluate_model, summarise
    from metadesign.reconstruction.model import aperture_mask

    res = evaluate_model(tiny_model(tmp_path), tiny_dataset, "all", [0.0], device="cpu")
    r = res["rows"]["gaussian:0"]
    pd = PSFDataset(tiny_dataset, "all")
    for j in range(2):
        i = int(np.nonzero(pd.idx == r["index"][j])[0][0])
        ph = np.angle(np.asarray(pd.get(i)["received"]))
        ap = aperture_mask(ph.shape[0])
        count = 0
        for y in range(ph.shape[0] - 1):
            for x in range(ph.shape[1] - 1):
                if ap[y, x] and ap[y, x + 1] and ap[y + 1, x] and ap[y + 1, x + 1]:
                    loop = [ph[y, x], ph[y, x + 1], ph[y + 1, x + 1], ph[y + 1, x], ph[y, x]]
                    turn = sum((b - a + np.pi) % (2 * np.pi) - np.pi for a, b in zip(loop[:-1], loop[1:]))
                    count += abs(round(turn / (2 * np.pi)))
        assert r["branch_points"][j] == count
    assert r["branch_points"].min() > 0
    assert np.mean(r["vortex_free"]) < np.mean(r["phase_conjugate"])
    s = summarise(r)
    assert s["vortex_free"]["branch_points_mean"] == pytest.approx(float(np.mean(r["branch_points"])))
    assert s["vortex_free"]["captured_fraction"] < 1
    from metadesign.reconstruction.evaluate import plot_fig3

    assert (tmp_path / "fig-branch-points.png") in plot_fig3(res, tmp_path)


@pytest.mark.parametrize("raw, field", [
    ({"model": {"output": "vortex"}}, "model.output"),
    ({"refine": {"unet": "u.safetensors", "output": "amplitude"}}, "refine.output"),
    ({"codesign": {"defocus_scale": float("nan")}}, "codesign.defocus_scale"),
    ({"codesign": {"defocus_scale": float("inf")}}, "codesign.defocus_scale"),
    ({"codesign": {"defocus_scale": 1e300}}, "codesign.defocus_scale")])
def test_bad_output_and_ladder_keys_are_one_line(raw, field):
    from metadesign.config import ConfigError
    from metadesign.reconstruction.train import train_recipe_from_dict

    with pytest.raises(ConfigError) as e:
        train_recipe_from_dict({"train": {"loss": "pib"}, **raw}, "t")
    assert field in str(e.value) and "\n" not in str(e.value)

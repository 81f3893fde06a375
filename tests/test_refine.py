"""The learned refinement (#23): its real-arithmetic twin against the complex torch twin, its explicit
adjoint against finite differences and autograd, the step's gradient (gradcheck), K = 0 = the U-Net, one
untrained step lowers the misfit, save/load, the registry, and the noise-range sampling."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from metadesign.reconstruction.data import NoiseRange, apply_noise  # noqa: E402
from metadesign.reconstruction.model import UNetConfig, build_unet, save_model  # noqa: E402
from metadesign.reconstruction.refine import (RefineConfig, build_refiner, deepen_refiner, is_refiner,  # noqa: E402
                                             load_refiner, save_refiner)
from metadesign.sensing.twin import TorchTwin, TwinOperators, normalise  # noqa: E402

torch.set_num_threads(1)
A, N, R, Q, S = 9, 10, 8, 8, 8  # crop, pupil grid, MFT rows/cols, tensor


def random_ops(seed: int = 0) -> TwinOperators:
    """Random twin operators of the right shapes (an independent complex twin to compare against)."""
    g = np.random.default_rng(seed)

    def c(*shape):
        return (g.normal(size=shape) + 1j * g.normal(size=shape)).astype(np.complex64) / np.sqrt(shape[-1])

    return TwinOperators(K=c(8, N, N), Ay=c(8, R, N), Ax=c(8, N, Q), w=g.uniform(0.5, 1.5, (8, R, Q)).astype(np.float32),
                         Ry=np.abs(g.normal(size=(S, R))).astype(np.float32),
                         Rx=np.abs(g.normal(size=(S, Q))).astype(np.float32),
                         W=g.normal(size=(N, A)).astype(np.float32) / 3, rebin=1, samples=None)


def buffers_of(ops: TwinOperators) -> dict:
    out = {}
    for k in ("K", "Ay", "Ax"):
        a = getattr(ops, k)
        out[k + "r"], out[k + "i"] = a.real, a.imag
    out.update(w=ops.w, Ry=ops.Ry, Rx=ops.Rx, W=ops.W)
    return out


def tiny_refiner(steps=2, step_init=0.05, seed=0):
    torch.manual_seed(seed)
    unet = build_unet(UNetConfig(base=4, depth=2, input_size=S, aperture_size=A)).eval()
    return build_refiner(unet, RefineConfig(steps=steps, step_init=step_init, width=4, features=4, dilate=1),
                         buffers=buffers_of(random_ops()))


def test_real_twin_renders_what_the_complex_twin_renders():
    ref = tiny_refiner()
    ops = random_ops()
    g = torch.Generator().manual_seed(1)
    phi = torch.randn(3, A, A, generator=g)
    sup = ref.twin.support
    want = normalise(TorchTwin(ops).from_crop(torch.polar(sup.expand(3, -1, -1).contiguous(), phi)))
    got = ref.twin(phi)
    assert torch.allclose(got, want, rtol=1e-4, atol=1e-5 * float(want.abs().max()))


def test_explicit_adjoint_is_the_gradient_of_the_misfit():
    ref = tiny_refiner().double()
    g = torch.Generator().manual_seed(2)
    phi = torch.randn(2, A, A, generator=g, dtype=torch.float64)
    data = ref.twin(torch.randn(2, A, A, generator=g, dtype=torch.float64))
    m, grad, _ = ref.twin.misfit_grad(phi, data, 1e-3)
    # autograd through the forward
    p = phi.clone().requires_grad_(True)
    P = ref.twin(p)
    mm = ((torch.sqrt(P + 1e-3) - torch.sqrt(data + 1e-3)) ** 2).sum(dim=(1, 2, 3))
    auto, = torch.autograd.grad(mm.sum(), p)
    assert torch.allclose(m, mm.detach(), rtol=1e-12)
    assert torch.allclose(grad, auto, rtol=1e-8, atol=1e-10 * float(auto.abs().max()))
    # central finite differences on a few pixels inside the support
    sup = ref.twin.support.numpy() > 0
    for (i, j) in list(zip(*np.nonzero(sup)))[::7][:6]:
        h = 1e-6
        d = torch.zeros_like(phi)
        d[0, i, j] = h
        fd = (ref.twin.misfit_grad(phi + d, data, 1e-3)[0][0] - ref.twin.misfit_grad(phi - d, data, 1e-3)[0][0]) / (2 * h)
        assert abs(float(fd) - float(grad[0, i, j])) <= 1e-6 * max(1.0, abs(float(fd)))


def test_refinement_step_gradcheck():
    """Training differentiates through the adjoint: the whole step (twin, adjoint, network) passes gradcheck."""
    ref = tiny_refiner(steps=1).double()
    for p in ref.steps.parameters():  # a non-zero last layer, so every path of the step carries gradient
        torch.nn.init.normal_(p, std=0.1) if p.dim() else None
    g = torch.Generator().manual_seed(3)
    data = ref.twin(torch.randn(1, A, A, generator=g, dtype=torch.float64)).detach()
    step = ref.steps[0]
    sup = ref.twin.support

    def f(phi):
        _, gr, pred = ref.twin.misfit_grad(phi, data, 1e-3)
        return step(phi, gr, data, pred, sup)

    phi = (0.3 * torch.randn(1, A, A, generator=g, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(f, (phi,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_k0_is_the_unet_and_an_untrained_step_lowers_the_misfit():
    ref = tiny_refiner(steps=1, step_init=0.02)
    g = torch.Generator().manual_seed(4)
    true = 0.5 * torch.randn(2, A, A, generator=g) * ref.twin.support
    x = ref.twin(true).detach()  # noise-free PSFs of a known phase
    with torch.no_grad():
        assert torch.equal(ref(x, k=0), ref.unet(x) * ref.mask)
        traj = ref.trajectory(x)
        data = x * (8.0 / x.sum(dim=(1, 2, 3), keepdim=True))
        m0 = ref.twin.misfit_grad(traj[0], data, ref.cfg.eps)[0]
        m1 = ref.twin.misfit_grad(traj[1], data, ref.cfg.eps)[0]
    assert (m1 < m0).all()


def test_a_deepened_refiner_starts_as_the_trained_one_and_its_new_steps_learn():
    """K = 2 trained, deepened to K = 4: the same estimate to the last bit (the appended steps are the
    identity), and the loss's gradient reaches every appended step's alpha and last layer (they can learn)."""
    src = tiny_refiner(steps=2, step_init=0.03, seed=1)
    with torch.no_grad():
        for p in src.steps.parameters():
            p.add_(0.05 * torch.randn_like(p))  # trained: not a fresh refiner
    deep = tiny_refiner(steps=4, step_init=0.03, seed=2)
    deepen_refiner(deep, src.state_dict(), 2)
    g = torch.Generator().manual_seed(5)
    x = src.twin(0.5 * torch.randn(2, A, A, generator=g) * src.twin.support).detach() + 0.01
    with torch.no_grad():
        assert torch.equal(deep(x), src(x))
    target = torch.zeros(2, A, A)
    ((deep(x) - target) ** 2).sum().backward()
    for step in list(deep.steps)[2:]:
        assert float(step.alpha.grad.abs()) > 0 and float(step.body[-1].weight.grad.abs().sum()) > 0
    with pytest.raises(Exception, match="do not fit"):
        deepen_refiner(tiny_refiner(steps=1), src.state_dict(), 2)


def test_a_field_refiner_starts_as_its_phase_refiner_and_its_field_learns():
    """``output = "field"``: a trained phase refiner's steps in a field refiner (deepened from 2 to 3 steps on
    the way) give the same phase to the bit; the loss's gradient reaches each step's field outputs."""
    src = tiny_refiner(steps=2, step_init=0.03, seed=1)
    with torch.no_grad():
        for p in src.steps.parameters():
            p.add_(0.3 * torch.randn_like(p))
    torch.manual_seed(2)
    unet = src.unet
    fld = build_refiner(unet, RefineConfig(steps=3, step_init=0.03, width=4, features=4, dilate=1, output="field"),
                        buffers=buffers_of(random_ops()))
    deepen_refiner(fld, src.state_dict(), 2)
    g = torch.Generator().manual_seed(5)
    x = src.twin(0.5 * torch.randn(2, A, A, generator=g) * src.twin.support).detach() + 0.01
    with torch.no_grad():
        a, b = src(x), fld(x)
    assert torch.equal(a, b)
    (fld(x) * torch.randn(2, A, A)).sum().backward()
    for step in list(fld.steps)[:2]:
        assert float(step.body[-1].weight.grad[1:].abs().sum()) > 0


def test_refiner_saves_loads_and_refuses_another_unet(tmp_path):
    ref = tiny_refiner()
    with torch.no_grad():
        ref.steps[0].body[-1].weight.normal_()
    up = tmp_path / "unet.safetensors"
    save_model(ref.unet, up, {"noise_percent": 0})
    path, card = save_refiner(ref, tmp_path / "r.safetensors", up, {"note": "test"})
    assert is_refiner(path) and not is_refiner(up)
    back, c = load_refiner(path)
    x = torch.rand(2, 8, S, S)
    with torch.no_grad():
        assert torch.equal(back(x), ref(x))
    assert c["unet"]["path"] == "unet.safetensors"
    # the U-Net replaced by another: refused in one line
    torch.manual_seed(9)
    save_model(build_unet(UNetConfig(base=4, depth=2, input_size=S, aperture_size=A)), up, {})
    from metadesign.validation import ValidationError

    with pytest.raises(ValidationError, match="not the one it was trained on"):
        load_refiner(path)


def test_noise_range_is_seeded_and_covers_the_range():
    n = NoiseRange((0.0, 10.0))
    lv = [n.levels(np.random.default_rng(np.random.SeedSequence(5, spawn_key=(0, i))))[0] for i in range(2000)]
    again = [n.levels(np.random.default_rng(np.random.SeedSequence(5, spawn_key=(0, i))))[0] for i in range(2000)]
    assert lv == again
    assert min(lv) >= 0 and max(lv) <= 10
    hist = np.histogram(lv, bins=10, range=(0, 10))[0]
    assert hist.min() > 150  # uniform: 200 per bin expected (a 4-sigma floor)
    # a fixed level draws nothing: the same bytes as the fixed-level noise of before
    psf = np.random.default_rng(0).random((8, 6, 6)).astype(np.float32)
    a = NoiseRange(5.0).apply(psf, np.random.default_rng(1))
    b = apply_noise(psf, np.random.default_rng(1), 5.0)
    assert np.array_equal(a, b)
    # photons: log-uniform in the range
    p = NoiseRange(0.0, (100.0, 10000.0))
    ph = np.array([p.levels(np.random.default_rng(i))[1] for i in range(2000)])
    assert ph.min() >= 100 and ph.max() <= 10000 and abs(np.median(np.log10(ph)) - 3.0) < 0.1


def test_noise_range_in_recipes_is_checked():
    from metadesign.config import ConfigError
    from metadesign.reconstruction.train import train_recipe_from_dict

    r = train_recipe_from_dict({"data": {"noise_percent": [0, 10]}})
    assert r.noise_percent == (0.0, 10.0)
    assert train_recipe_from_dict({"data": {"noise_percent": 5}}).noise_percent == (5.0, 5.0)
    for bad in ([10, 0], [0, 200], [0, float("nan")], [1, 2, 3], "x"):
        with pytest.raises(ConfigError, match="data.noise_percent"):
            train_recipe_from_dict({"data": {"noise_percent": bad}})
    with pytest.raises(ConfigError, match="data.photons_at_peak"):
        train_recipe_from_dict({"data": {"photons_at_peak": [0, 100]}})


@pytest.mark.slow  # a training run: the default suite's 10-minute budget
def test_a_refiner_trains_evaluates_compares_and_exports(tiny_dataset, tmp_path):
    """A [refine] recipe trains on top of a frozen U-Net (noise drawn from a range), saves a refiner that
    `evaluate`, `compare` (as the registered estimator "refine", with its per-step curve) and `export`
    take like a U-Net; the U-Net's weights are untouched."""
    import json
    import os
    import subprocess
    import sys

    from conftest import REPO, tiny_model

    unet = tiny_model(tmp_path)
    before = unet.read_bytes()
    rec = tmp_path / "r.toml"
    rec.write_text(f"""[data]
dataset = "{tiny_dataset}"
noise_percent = [0, 10]
[train]
epochs = 2
batch = 4
lr = 1e-2
loss = "pib"
[refine]
unet = "{unet}"
steps = 2
width = 4
features = 4
deep_supervision = 0.5
""")
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")

    def cli(*args):
        r = subprocess.run([sys.executable, "-m", "metadesign", *map(str, args)], env=env, capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        return r

    cli("train", rec, "-o", tmp_path / "run", "--json")
    model = tmp_path / "run" / "model.safetensors"
    card = json.loads((tmp_path / "run" / "model.safetensors.json").read_text())
    assert is_refiner(model) and card["refine"]["steps"] == 2 and card["noise_percent"] == [0.0, 10.0]
    assert unet.read_bytes() == before
    ref, _ = load_refiner(model)
    assert any(float(p.detach().abs().sum()) > 0 for p in ref.steps[0].body[-1].parameters())  # it learned something
    cli("evaluate", model, tiny_dataset, "--split", "all", "-o", tmp_path / "ev", "--json")
    cmp = cli("compare", model, tiny_dataset, "--split", "all", "--methods", "unet", "refine", "-o", tmp_path / "cmp",
              "--json")
    res = json.loads(cmp.stdout)["summary"]
    curve = res["curves"]["refine"]
    assert "refine" in res["npib"] and [c["iterations"] for c in curve] == [0, 1, 2]
    # K = 0 of the curve is the U-Net's own row; the last is the refiner's
    assert curve[0]["npib"] == pytest.approx(res["npib"]["unet"], rel=1e-5)
    assert curve[-1]["npib"] == pytest.approx(res["npib"]["refine"], rel=1e-6)
    ex = json.loads(cli("export", model, "--onnx", tmp_path / "r.onnx", "--json").stdout)
    assert ex["max_abs_diff"] <= 1e-4


def test_refine_init_continues_a_refiner_or_transfers_its_steps(tiny_dataset, tmp_path):
    """``refine.init``: with the refiner's own U-Net every weight and buffer continues; with another U-Net
    (a co-designed sensor's) only the step networks come over, the U-Net is ``refine.unet`` and the twin
    the dataset's device; another architecture is one line."""
    from conftest import tiny_model

    from metadesign.reconstruction.dataset import load_device
    from metadesign.reconstruction.train import _build_refiner, load_train_recipe
    from metadesign.validation import ValidationError

    (tmp_path / "u1").mkdir()
    (tmp_path / "u2").mkdir()
    u1 = tiny_model(tmp_path / "u1")
    torch.manual_seed(7)
    save_model(build_unet(UNetConfig(base=4, depth=3, input_size=16)), tmp_path / "u2" / "m.safetensors", {})
    u2 = tmp_path / "u2" / "m.safetensors"
    cfg = RefineConfig(steps=2, width=4, features=4)
    from metadesign.reconstruction.model import load_model

    torch.manual_seed(3)
    src = build_refiner(load_model(u1)[0], cfg, load_device(tiny_dataset))
    with torch.no_grad():
        for k, v in src.named_parameters():
            if k.startswith("steps."):
                v.add_(0.25)  # trained: not what a fresh refiner starts from
        src.twin.W.mul_(2.0)  # a twin buffer that differs from the dataset device's
    save_refiner(src, tmp_path / "r.safetensors", u1, {"noise_percent": 0})

    def build(unet, steps=2):
        (tmp_path / "t.toml").write_text(f"""[data]
dataset = "{tiny_dataset}"
[train]
epochs = 1
batch = 4
[refine]
unet = "{unet}"
init = "{tmp_path / 'r.safetensors'}"
steps = {steps}
width = 4
features = 4
""")
        return _build_refiner(load_train_recipe(tmp_path / "t.toml"), tiny_dataset, 16, src.config.aperture_size,
                              None, "cpu")

    same, card = build(u1)
    assert card["refiner_steps_only"] is False
    for k, v in src.state_dict().items():
        assert torch.equal(same.state_dict()[k], v), k
    other, card = build(u2)
    assert card["refiner_steps_only"] is True
    st, u2w = other.state_dict(), load_model(u2)[0].state_dict()
    for k, v in src.state_dict().items():
        if k.startswith("steps."):
            assert torch.equal(st[k], v), k
    assert all(torch.equal(st["unet." + k], v) for k, v in u2w.items())
    assert torch.allclose(st["twin.W"] * 2.0, src.state_dict()["twin.W"])  # the dataset's twin, not the file's
    deeper, card = build(u1, steps=3)  # a deeper recipe: the trained steps first, then the identity
    assert card["refiner_deepened_from_steps"] == 2 and len(deeper.steps) == 3
    x = torch.rand(2, 8, 16, 16)
    with torch.no_grad():
        assert torch.equal(deeper(x), src(x))
    with pytest.raises(ValidationError, match="at most refine.steps = 1"):
        build(u1, steps=1)
    (tmp_path / "t.toml").write_text((tmp_path / "t.toml").read_text().replace("width = 4", "width = 8"))
    with pytest.raises(ValidationError, match="another \\[refine\\] architecture"):
        _build_refiner(load_train_recipe(tmp_path / "t.toml"), tiny_dataset, 16, src.config.aperture_size, None, "cpu")


def test_model_card_checks_the_weights_sha256(tmp_path):
    """The one reader of a card's content (cards.model_card) checks the weights' sha256 whatever the format;
    has_format only sniffs the format (the loader then checks)."""
    from metadesign.cards import has_format, model_card, save_card_model
    from metadesign.validation import ValidationError

    w, _ = save_card_model(tmp_path / "m.safetensors", {"a": torch.zeros(2)}, "metadesign.test/1", {"x": 1})
    assert model_card(w)["x"] == 1 and model_card(str(w) + ".json", "metadesign.test/1")["x"] == 1
    assert has_format(w, "metadesign.test/1") and not has_format(w, "metadesign.other/1")
    w.write_bytes(w.read_bytes() + b" ")
    with pytest.raises(ValidationError, match="sha256"):
        model_card(w)
    assert has_format(w, "metadesign.test/1") and not has_format(tmp_path / "none.safetensors", "metadesign.test/1")

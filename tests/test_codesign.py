"""Co-design training (issue #33): the diversity trains with the U-Net through the usual loop, resumes to
the same bytes, writes the U-Net (a plain model) with its diversity; bad [codesign] keys are one line."""

import json

import pytest

torch = pytest.importorskip("torch")


def _recipe(epochs, **codesign):
    from metadesign.reconstruction.train import train_recipe_from_dict

    return train_recipe_from_dict({"data": {"noise_percent": [0.0, 10.0]}, "model": {"base": 4, "depth": 3},
                                   "train": {"epochs": epochs, "batch": 4, "lr": 1e-3, "loss": "pib", "seed": 1},
                                   "codesign": {"modes": [5, 6, 7], "lr": 0.05, "init": "random", "seed": 2,
                                                **codesign}}, "cd")


def test_codesign_trains_the_diversity_and_resumes_to_the_same_bytes(tiny_dataset, tmp_path):
    from metadesign.reconstruction.model import load_model
    from metadesign.reconstruction.train import train

    torch.set_num_threads(1)
    train(_recipe(2), tmp_path / "a", dataset=tiny_dataset, progress=False, log=lambda s: None)
    train(_recipe(1), tmp_path / "b", dataset=tiny_dataset, progress=False, log=lambda s: None)
    train(_recipe(2), tmp_path / "b", dataset=tiny_dataset, resume=True, progress=False, log=lambda s: None)
    sa = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)["model"]
    sb = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)["model"]
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert "twin.defocus_waves" in sa and "twin.G" not in sa  # the diversity, not the device's operators
    # the diversity moved from its initial draw (the same seed gives the same start)
    from metadesign.reconstruction.codesign import CodesignConfig

    g = torch.Generator().manual_seed(2)
    start = 0.5 * torch.randn(2, 4, generator=g, dtype=torch.float64)
    assert not torch.allclose(sa["twin.defocus_waves"], start)
    rec = json.loads((tmp_path / "a" / "diversity.json").read_text())
    assert rec["zernike_noll"] == [5, 6, 7] and len(rec["focal_length_mm"][0]) == 4
    assert rec["config"]["modes"] == list(CodesignConfig(modes=(5, 6, 7)).modes)
    model, card = load_model(tmp_path / "a" / "model.safetensors")  # the U-Net alone, with its sensor
    assert card["codesign"]["zernike_noll"] == [5, 6, 7]
    assert model.config.input_size == 16
    # evaluate renders its inputs through the recorded diversity: against the same chain written out here
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.dataset import load_device, open_dataset
    from metadesign.reconstruction.evaluate import evaluate_model
    from metadesign.reconstruction.losses import PiB
    from metadesign.sensing.diversity import diversity_operators, lens_table
    from metadesign.sensing.twin import normalise
    from metadesign.sensing.twin_diversity import DiversityTwin

    res = evaluate_model(tmp_path / "a" / "model.safetensors", tiny_dataset, "train", [0.0], device="cpu")
    dev = load_device(tiny_dataset)
    ops = diversity_operators(dev.pupil, dev.sensor, lens_table(open_dataset(tiny_dataset).attrs["provenance"]["channels"]),
                              dev.geometry, 1, None, (5, 6, 7))  # the run's twin (exact: the recipe's default)
    tw = DiversityTwin(ops)
    cd = card["codesign"]  # the diversity of the saved (best) epoch
    with torch.no_grad():
        f = torch.tensor(cd["focal_length_mm"], dtype=torch.float64) * 1e-3
        tw.defocus_waves.copy_((1 / f - 1 / tw.f0) * ops.radius ** 2 / (2 * ops.wavelength))
        tw.zernike_rad.copy_(torch.tensor(cd["zernike_rad"], dtype=torch.float64))
        pd = PSFDataset(tiny_dataset, "train", screens=True)
        s = pd.get(0)
        pib = PiB(pd.scenario(), *pd.crop())
        rec = torch.as_tensor(s["received"])[None]
        phi = model(normalise(tw(rec).float()))
        want = float(pib.npib_phase(phi, torch.as_tensor(s["screens"])[None]))
    got = float(next(iter(res["rows"].values()))["unet"][0])
    assert got == pytest.approx(want, rel=1e-4)


def test_defocus_scale_stretches_the_paper_ladder_about_its_mean_power(tiny_dataset):
    """``defocus_scale`` s: the lenses' optical powers become mean + s (1/f0 - mean) (checked on the focal
    lengths the twin reports, from the lens table's, not from the helper's arithmetic); 1 leaves the
    device as built; 0 puts every lens at one power."""
    import numpy as np

    from metadesign.reconstruction.codesign import CodesignConfig, build_codesign
    from metadesign.reconstruction.dataset import open_dataset
    from metadesign.reconstruction.model import UNetConfig, build_unet

    f0 = np.array([row["focal_length_m"] for row in open_dataset(tiny_dataset).attrs["provenance"]["channels"]]) * 1e3
    assert len(f0) == 8 and np.ptp(f0) > 0
    unet = build_unet(UNetConfig(base=4, depth=3, input_size=16))
    for s in (1.0, 2.0, 0.0):
        net = build_codesign(unet, CodesignConfig(modes=(5,), init="paper", defocus_scale=s), tiny_dataset, (0, 0))
        f = np.sort(net.twin.focal_lengths().detach().numpy().ravel() * 1e3)
        p0 = 1 / np.sort(f0)
        assert 1 / f == pytest.approx(p0.mean() + s * (p0 - p0.mean()), rel=1e-9), s


@pytest.mark.parametrize("codesign, field", [({"modes": [4, 5]}, "codesign.modes"),
                                             ({"modes": [5.5]}, "codesign.modes"),
                                             ({"lr": float("nan")}, "codesign.lr"),
                                             ({"init": "zero"}, "codesign.init"),
                                             ({"defocus_scale": -1.0}, "codesign.defocus_scale"),
                                             ({"defocus_scale": 2.0}, "codesign.defocus_scale")])
def test_bad_codesign_keys_are_one_line(codesign, field):
    from metadesign.config import ConfigError

    with pytest.raises(ConfigError) as e:
        _recipe(1, **codesign)
    assert field in str(e.value) and "\n" not in str(e.value)


def test_the_codesign_report_makes_a_design_recipe_of_the_learned_diversity(tiny_dataset, tmp_path):
    """`metadesign codesign RUN`: design.toml is a design recipe whose lenses are the learned ones (focal
    lengths and Zernike terms), the figures and the Fisher spectra (piston-free modes, finite) are written."""
    from conftest import REPO

    from metadesign.cli import main
    from metadesign.design.recipe import load_design_recipe
    from metadesign.reconstruction.train import train

    torch.set_num_threads(1)
    train(_recipe(1), tmp_path / "run", dataset=tiny_dataset, progress=False, log=lambda s: None)
    out = tmp_path / "rep"
    (tmp_path / "layouts").mkdir()
    recipe = tmp_path / "layouts" / "cd.toml"
    assert main(["codesign", str(tmp_path / "run"), "--dataset", str(tiny_dataset), "--base",
                 str(REPO / "layouts" / "demo.toml"), "--modes", "6", "--random", "1", "-o", str(out),
                 "--recipe", str(recipe), "--json"]) == 0
    rec = json.loads((tmp_path / "run" / "diversity.json").read_text())
    d = load_design_recipe(recipe)
    assert d.library_path.resolve() == (REPO / "library" / "paper.npz").resolve()
    assert load_design_recipe(out / "design.toml").spec == d.spec
    from metadesign.outputs import identify

    assert identify(recipe) == "design-recipe" and identify(REPO / "layouts" / "demo.toml") is None
    # a recipe the user wrote is never replaced
    mine = tmp_path / "layouts" / "mine.toml"
    mine.write_text((REPO / "layouts" / "demo.toml").read_text())
    assert main(["codesign", str(tmp_path / "run"), "--dataset", str(tiny_dataset), "--base",
                 str(REPO / "layouts" / "demo.toml"), "-o", str(tmp_path / "rep2"), "--recipe", str(mine)]) == 2
    assert mine.read_text() == (REPO / "layouts" / "demo.toml").read_text() and not (tmp_path / "rep2").exists()
    for p, chans in enumerate((d.spec.channels_x, d.spec.channels_y)):
        for k, ch in enumerate(chans):
            assert ch.focal_length == pytest.approx(rec["focal_length_mm"][p][k] * 1e-3, rel=1e-8)
            want = {j: a for j, a in zip(rec["zernike_noll"], rec["zernike_rad"][p][k]) if a}
            assert dict(ch.zernike) == pytest.approx(want, abs=1e-8)
            assert ch.radius == pytest.approx(0.5 * d.spec.n_cells * d.spec.period)
    s = json.loads((out / "codesign.json").read_text())
    assert set(s["fisher"]["crb_rad2"]) == {"paper", "learned", "random 1"}
    assert all(x is not None and x > 0 for v in s["fisher"]["crb_rad2"].values() for x in v)
    assert (out / "diversity.png").stat().st_size > 0 and (out / "fisher.png").stat().st_size > 0


@pytest.mark.slow
def test_codesign_in_two_gloo_processes_reaches_the_weights_of_one(tiny_dataset, tmp_path):
    """torchrun / DistributedDataParallel with the learnable sensor inside the model (noise off: each rank
    draws its own): the diversity and the U-Net of 2 processes x 2 samples equal 1 process x 4."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from conftest import REPO

    rec = tmp_path / "cd.toml"
    rec.write_text(f'[data]\ndataset = "{tiny_dataset}"\nnoise_percent = 0.0\n[model]\nbase = 4\ndepth = 3\n'
                   '[train]\nepochs = 1\nbatch = 4\nlr = 1e-3\nloss = "pib"\nseed = 1\n'
                   '[codesign]\nmodes = [5, 7]\nlr = 0.05\ninit = "random"\nseed = 2\n')
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    one = subprocess.run([sys.executable, "-m", "metadesign", "train", str(rec), "-o", str(tmp_path / "one"),
                          "--max-steps", "2", "--json"], env=env, capture_output=True, text=True, timeout=600)
    assert one.returncode == 0, one.stderr[-2000:]
    torchrun = Path(sys.executable).with_name("torchrun")
    two = subprocess.run([str(torchrun), "--nproc_per_node", "2", "--master_port", "29519", "-m", "metadesign",
                          "train", str(rec), "-o", str(tmp_path / "two"), "--max-steps", "2", "--json"],
                         env=env, capture_output=True, text=True, timeout=600)
    assert two.returncode == 0, two.stderr[-2000:]
    a = torch.load(tmp_path / "one" / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(tmp_path / "two" / "checkpoint.pt", weights_only=True)["model"]
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6)
    g = torch.Generator().manual_seed(2)
    assert not torch.allclose(a["twin.defocus_waves"], 0.5 * torch.randn(2, 4, generator=g, dtype=torch.float64))

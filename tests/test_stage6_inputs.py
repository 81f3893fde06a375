"""Stage 6 against bad inputs and faults: data a user owns is never deleted or mixed, a second writer of
an output is refused while the first works, damaged models and datasets are one line (exit 2) wherever
they are read, and every input of the long studies is checked before their first dataset is built."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import REPO, run_main, tiny_dataset_recipe, tiny_model  # noqa: E402

_run = run_main


def _one_line(argv, capsys, match: str):
    rc, _, err = _run(argv, capsys)
    assert rc == 2 and len(err) == 1 and err[0].startswith("metadesign: error:"), (argv, rc, err)
    assert match in err[0], err[0]
    return err[0]


def _tree(folder: Path) -> set:
    return {(str(p.relative_to(folder)), p.stat().st_size) for p in Path(folder).rglob("*")}


# -- data loss ------------------------------------------------------------------------------------------

def test_dataset_build_never_deletes_dot_files(demo_products, tmp_path, capsys):
    """A folder holding only dot-files (a home directory, a git checkout) is not an empty output."""
    home = tmp_path / "home"
    (home / ".ssh").mkdir(parents=True)
    (home / ".ssh" / "id_ed25519").write_text("secret")
    (home / ".bashrc").write_text("alias ll='ls -l'")
    (home / ".git").mkdir()
    before = _tree(home)
    rec = tiny_dataset_recipe(tmp_path, demo_products["layout"], samples=4)
    _one_line(["dataset", "build", rec, "-o", home], capsys, "not a metadesign dataset")
    assert _tree(home) == before
    _one_line(["dataset", "build", rec, "-o", home, "--overwrite"], capsys, "not a metadesign dataset")
    assert _tree(home) == before


_HOLD = textwrap.dedent("""
    import sys, time
    from metadesign.io import output_lock
    with output_lock(sys.argv[1]):
        print("locked", flush=True)
        time.sleep(60)
""")


@pytest.fixture
def held(tmp_path):
    """Another process holding the lock of an output while the test runs."""
    procs = []

    def hold(path: Path):
        env = dict(os.environ, PYTHONPATH=str(REPO))
        p = subprocess.Popen([sys.executable, "-c", _HOLD, str(path)], stdout=subprocess.PIPE, text=True, env=env)
        procs.append(p)
        assert p.stdout.readline().strip() == "locked"
        return p

    yield hold
    for p in procs:
        p.kill()
        p.wait()


def test_a_second_writer_of_an_output_is_refused(held, tiny_dataset, demo_products, tmp_path, capsys):
    """dataset build, dataset operators, train and import into an output another process is writing: one
    line, exit 2, nothing touched; once the first writer is gone (even by SIGKILL) the output is free."""
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    before = _tree(ds)
    p = held(ds)
    rec = tiny_dataset_recipe(tmp_path, demo_products["layout"])
    _one_line(["dataset", "build", rec, "-o", ds], capsys, "another metadesign process is writing")
    _one_line(["dataset", "operators", ds], capsys, "another metadesign process is writing")
    assert _tree(ds) == before
    run = tmp_path / "run"
    held(run)
    model = tiny_model(tmp_path)
    _one_line(["train", tmp_path / "t.toml", "--dataset", ds, "-o", run], capsys, "another metadesign process")
    assert not run.exists()
    p.kill()
    p.wait()
    rc, _, err = _run(["dataset", "build", rec, "-o", ds, "--json"], capsys)  # the same recipe: up to date
    assert rc == 0, err
    assert model.exists()


def test_io_output_lock_is_exclusive_and_released(tmp_path):
    from metadesign.io import lock_path, output_lock
    from metadesign.validation import ValidationError

    import fcntl
    import os

    out = tmp_path / "x"
    with output_lock(out):
        fd = os.open(lock_path(out), os.O_RDWR)  # what another process sees: the lock is taken
        with pytest.raises(BlockingIOError):
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.close(fd)
        with output_lock(out):  # re-entrant in the holding process (a command and its own sub-products)
            pass
        assert lock_path(out).exists()
    assert not lock_path(out).exists()
    with output_lock(out):  # free again
        pass


# -- models ---------------------------------------------------------------------------------------------

def _bad_models(tmp_path: Path) -> dict:
    """Model files a user might hand in: a card that is JSON but no object, weights of another
    architecture than the card says, NaN weights (card sha256 updated: the file is 'valid')."""
    from metadesign.reconstruction.model import UNetConfig, build_unet, save_model

    out = {}
    (tmp_path / "good").mkdir()
    good = tiny_model(tmp_path / "good")
    d = tmp_path / "list"
    shutil.copytree(good.parent, d)
    (d / "m.safetensors.json").write_text("[1, 2, 3]")
    out["not an object"] = (d / "m.safetensors", "not a metadesign model card")
    d = tmp_path / "arch"
    shutil.copytree(good.parent, d)
    card = json.loads((d / "m.safetensors.json").read_text())
    card["architecture"]["base"] = 8
    (d / "m.safetensors.json").write_text(json.dumps(card))
    out["architecture"] = (d / "m.safetensors", "do not fit the card's architecture")
    d = tmp_path / "nan"
    d.mkdir()
    m = build_unet(UNetConfig(base=4, depth=3, input_size=16))
    with torch.no_grad():
        next(m.parameters()).fill_(float("nan"))
    save_model(m, d / "m.safetensors", {})
    out["nan"] = (d / "m.safetensors", "non-finite weights")
    d = tmp_path / "crop"
    d.mkdir()
    save_model(build_unet(UNetConfig(base=4, depth=3, input_size=16, aperture_size=33)), d / "m.safetensors", {})
    out["crop"] = (d / "m.safetensors", "received crop")
    return out


def test_bad_models_are_one_line_everywhere(tiny_dataset, tmp_path, capsys):
    models = _bad_models(tmp_path)
    for name, (m, match) in models.items():
        if name != "crop":  # the crop is the dataset's business: loading alone is fine
            _one_line(["export", m, "--onnx", tmp_path / f"{name}.onnx"], capsys, match)
            assert not (tmp_path / f"{name}.onnx").exists()
        _one_line(["evaluate", m, tiny_dataset, "--split", "train", "--limit", "2", "-o", tmp_path / f"ev-{name}"],
                  capsys, match)
        _one_line(["compare", m, tiny_dataset, "--split", "train", "--limit", "2", "--methods", "unet", "-o",
                   tmp_path / f"cmp-{name}"], capsys, match)
        if name != "crop":
            _one_line(["train", tmp_path / "good" / "t.toml", "--dataset", tiny_dataset, "--init", m, "-o",
                       tmp_path / f"run-{name}"], capsys, match)


def test_export_parity_check_sees_nan(monkeypatch):
    """max(0, nan) is 0: the parity check must report a NaN difference as NaN, not as a perfect match."""
    import onnxruntime

    from metadesign.reconstruction.export import onnx_parity

    class M(torch.nn.Module):
        config = type("C", (), {"input_size": 16})()

        def forward(self, x):
            return x[:, 0] * float("nan")

    class Sess:  # onnxruntime stand-in answering zeros
        def __init__(self, *a, **k):
            pass

        def run(self, _names, feeds):
            return [np.zeros_like(feeds["psf"][:, 0])]

    monkeypatch.setattr(onnxruntime, "InferenceSession", Sess)
    assert not np.isfinite(onnx_parity(M(), "unused.onnx")["max_abs_diff"])


def test_compare_with_no_model_and_only_model_methods_is_one_line(tiny_dataset, tmp_path, capsys):
    _one_line(["compare", "NONE", tiny_dataset, "--methods", "unet", "-o", tmp_path / "c"], capsys, "need a model")
    assert not (tmp_path / "c").exists()


# -- training -------------------------------------------------------------------------------------------

def test_training_inputs_are_checked_before_an_epoch(tiny_dataset, demo_products, tmp_path, capsys):
    from metadesign.outputs import write_marker

    tiny_model(tmp_path)
    rec = tmp_path / "t.toml"
    # no validation samples: refused before training
    nov = tmp_path / "nov"
    from metadesign.reconstruction.dataset import build_dataset, load_dataset_recipe

    build_dataset(load_dataset_recipe(tiny_dataset_recipe(tmp_path, demo_products["layout"], samples=6,
                                                          extra="split = [1.0, 0.0, 0.0]\n")), nov)
    _one_line(["train", rec, "--dataset", nov, "-o", tmp_path / "r0"], capsys, "validation split is empty")
    assert not (tmp_path / "r0").exists()
    # resume from damaged checkpoints
    blobs = {f"random{k}": np.random.default_rng(k).bytes(300 + 97 * k) for k in range(8)}  # seeded: no flakes
    for kind in ("truncated", "empty", "folder", *blobs):
        run = tmp_path / f"r-{kind}"
        run.mkdir()
        write_marker(run, "training-run")  # a run metadesign wrote, whose checkpoint was damaged since
        ck = run / "checkpoint.pt"
        if kind == "folder":
            ck.mkdir()
            match = "no checkpoint.pt"
        else:
            ck.write_bytes({"truncated": b"PK\x03\x04" + b"\0" * 40, "empty": b"", **blobs}[kind])
            match = "not a readable checkpoint" if kind in ("truncated", "empty") else "checkpoint"
        _one_line(["train", rec, "--dataset", tiny_dataset, "-o", run, "--resume"], capsys, match)
    # a checkpoint of another architecture
    run = tmp_path / "r-ok"
    assert _run(["train", rec, "--dataset", tiny_dataset, "-o", run, "--max-steps", "1", "--json"], capsys)[0] == 0
    other = tmp_path / "other.toml"
    other.write_text(rec.read_text().replace("base = 4", "base = 8"))
    _one_line(["train", other, "--dataset", tiny_dataset, "-o", run, "--resume"], capsys, "does not fit")
    # an output that is the dataset itself
    _one_line(["train", rec, "--dataset", tiny_dataset, "-o", tiny_dataset / "run"], capsys, "overlaps the input")


def test_a_diverging_loss_stops_training_with_one_line(tiny_dataset, tmp_path, capsys, monkeypatch):
    """A NaN loss (a diverged run) stops training with one line; it never trains on to report 'best -inf'."""
    import importlib

    losses = importlib.import_module("metadesign.reconstruction.losses")

    tiny_model(tmp_path)
    rec = tmp_path / "t.toml"
    rec.write_text(rec.read_text().replace("[train]\n", "[train]\nepochs = 2\npretrain_loss = \"phase\"\n"
                                                         "pretrain_epochs = 2\n"))
    monkeypatch.setattr(losses, "phase_loss", lambda phi, rec, ap: (phi * float("nan")).sum())  # the registry's
    rc, _, err = _run(["train", rec, "--dataset", tiny_dataset, "-o", tmp_path / "run"], capsys)
    assert rc == 2 and len(err) == 1 and "diverged" in err[0], err
    assert not (tmp_path / "run" / "model.safetensors").exists()


# -- damaged datasets -----------------------------------------------------------------------------------

def test_damaged_datasets_are_found_and_named(tiny_dataset, tmp_path, capsys):
    """A truncated shard and a bit-flipped PSF chunk: `dataset verify` names the shard (exit 1), every
    reader stops with one line naming it; a store without its provenance is one line."""
    model = tiny_model(tmp_path)
    trunc = tmp_path / "trunc"
    shutil.copytree(tiny_dataset, trunc)
    shard = sorted(p for p in (trunc / "psf" / "c").rglob("*") if p.is_file())[0]
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])
    rc, out, _ = _run(["dataset", "verify", trunc, "--json"], capsys)
    rep = json.loads(out)
    assert rc == 1 and [b["shard"] for b in rep["damaged_shards"]] == [0], rep
    assert _run(["dataset", "verify", tiny_dataset], capsys)[0] == 0
    for argv in (["evaluate", model, trunc, "--split", "train", "-o", tmp_path / "ev"],
                 ["dataset", "plot", trunc, "-o", tmp_path / "p.png"],
                 ["train", tmp_path / "t.toml", "--dataset", trunc, "-o", tmp_path / "run"]):
        line = _one_line(argv, capsys, "damaged dataset")
        assert "shard 0" in line, line
    # one flipped byte inside a PSF chunk (zstd carries no checksum of its own)
    flip = tmp_path / "flip"
    shutil.copytree(tiny_dataset, flip)
    f = sorted(p for p in (flip / "psf" / "c").rglob("*") if p.is_file())[0]
    b = bytearray(f.read_bytes())
    b[len(b) // 3] ^= 0x10
    f.write_bytes(bytes(b))
    rc, out, _ = _run(["dataset", "verify", flip, "--json"], capsys)
    assert rc == 1 and json.loads(out)["damaged_shards"][0]["shard"] == 0
    _one_line(["evaluate", model, flip, "--split", "train", "-o", tmp_path / "ev2"], capsys, "damaged dataset")
    # a store without its provenance
    noprov = tmp_path / "noprov"
    shutil.copytree(tiny_dataset, noprov)
    meta = json.loads((noprov / "zarr.json").read_text())
    del meta["attributes"]["provenance"]
    (noprov / "zarr.json").write_text(json.dumps(meta))
    _one_line(["evaluate", model, noprov, "-o", tmp_path / "ev3"], capsys, "lacks its 'provenance'")


# -- dataset build --------------------------------------------------------------------------------------

def test_dataset_build_checks_the_scheduler_and_the_disk_before_writing(demo_products, tmp_path, capsys):
    rec = tiny_dataset_recipe(tmp_path, demo_products["layout"])
    out = tmp_path / "ds"
    _one_line(["dataset", "build", rec, "-o", out, "--scheduler", "tcp://127.0.0.1:9"], capsys, "--scheduler")
    assert not out.exists()
    (tmp_path / "big").mkdir()
    big = tiny_dataset_recipe(tmp_path / "big", demo_products["layout"], samples=10_000_000, tensor=64, shard=64)
    _one_line(["dataset", "build", big, "-o", tmp_path / "big-ds"], capsys, "GB")
    assert not (tmp_path / "big-ds").exists()


# -- layouts as folders ---------------------------------------------------------------------------------

@pytest.mark.parametrize("cmd", [["psf"], ["phasemap"], ["fab-study", "--bias-nm", "0"]])
def test_a_folder_given_as_layout_is_one_line(cmd, tmp_path, capsys):
    _one_line([cmd[0], tmp_path, *cmd[1:], "-o", tmp_path / "out"], capsys, "is a folder")


# -- studies check every input first --------------------------------------------------------------------

def test_studies_check_their_model_before_building_anything(tmp_path, capsys):
    """tolerance and transfer with a missing model, and tolerance with a model of another input size: one
    line before any dataset is built (each would take minutes)."""
    sensing = tmp_path / "sensing"
    sensing.mkdir()
    for p in (REPO / "sensing").glob("*.toml"):
        shutil.copy(p, sensing / p.name)
    for cmd in ("tolerance", "transfer"):
        out = tmp_path / f"{cmd}-out"
        rc, _, err = _run([cmd, sensing / f"{cmd}-demo.toml", "-o", out], capsys)
        assert rc == 2 and len(err) == 1 and "no such" in err[0], err
        assert not out.exists() or not any(out.rglob("zarr.json"))
    (sensing / "models").mkdir()
    m = tiny_model(tmp_path)  # 8 x 16^2 inputs; the recipe's dataset has 8 x 64^2
    shutil.copy(m, sensing / "models" / "demo-unet-robust.safetensors")
    shutil.copy(m.with_name(m.name + ".json"), sensing / "models" / "demo-unet-robust.safetensors.json")
    out = tmp_path / "tol-out"
    rc, _, err = _run(["tolerance", sensing / "tolerance-demo.toml", "-o", out], capsys)
    assert rc == 2 and len(err) == 1 and "model input 16^2 does not match" in err[0], err
    assert not out.exists()


# -- Strehl ---------------------------------------------------------------------------------------------

def test_strehl_of_a_perfect_lens_is_one_and_never_above(demo_products):
    """A synthetic device whose channels are perfect off-axis lenses over the whole aperture (uniform
    amplitude, the tilt to each quadrant's centre): Strehl 1 (to the parabolic peak interpolation), and the
    demo device's channels <= 1."""
    from types import SimpleNamespace

    from metadesign.conventions import centered
    from metadesign.optics.propagation import cexp
    from metadesign.sensing.forward import CoarsePupil
    from metadesign.sensing.model import AsFabricated, channel_metrics, load_sensing_recipe

    sr = load_sensing_recipe(REPO / "sensing" / "demo.toml")
    sensor = sr.sensor
    n, pitch = 64, 0.7e-6 * 8
    X = centered(n, pitch)
    wl, z = 1.55e-6, sensor.distance
    k0 = 2 * np.pi / wl
    G = np.zeros((2, 4, n, n), np.complex64)
    q = 8  # block averages of the field sampled q x q per block, as coarse_pupil makes them
    xf = (X[:, None] + (np.arange(q) - (q - 1) / 2) * pitch / q).ravel()
    xx, yy = xf[None, :], xf[:, None]
    for p in range(2):
        for k in range(1, 5):  # an exact (Eq. 1) lens focusing on the quadrant's centre, demodulated
            cx, cy = sensor.quadrant_centre(k)
            t = -k0 * np.sqrt(z**2 + (xx - cx) ** 2 + (yy - cy) ** 2)
            f = cexp(t + k0 * (xx**2 + yy**2) / (2 * z)) / 2
            G[p, k - 1] = f.reshape(n, q, n, q).mean(axis=(1, 3))
    cp = CoarsePupil(G, X, 1, pitch, wl, z, 0)
    fab = SimpleNamespace(channels=[None, None], n_cells=n, period=pitch)
    s = [r["strehl"] for r in channel_metrics(cp, sensor, fab)]
    assert np.allclose(s, 1.0, atol=2e-3), s
    fab = AsFabricated.from_files(demo_products["layout"])
    cp = fab.pupil(sensor.distance, sr.pupil_grid)
    s = [r["strehl"] for r in channel_metrics(cp, sensor, fab)]
    assert max(s) <= 1.0 and min(s) > 0.3, s


def test_a_scenario_at_another_wavelength_is_refused(demo_products, tmp_path, capsys):
    """The turbulence scenario's wavelength must be the device's: a 1064 nm path in front of the 1550 nm
    metasurface is one line (dataset build, before anything is written; BeaconChain; a Device)."""
    from metadesign.sensing import AsFabricated, load_sensing_recipe
    from metadesign.turbulence import BeaconChain, load_scenario
    from metadesign.validation import ValidationError

    turb = tmp_path / "turb1064.toml"
    turb.write_text((REPO / "sensing" / "turbulence.toml").read_text().replace("wavelength_nm = 1550.0",
                                                                                 "wavelength_nm = 1064.0"))
    assert "1064" in turb.read_text()
    rec = tiny_dataset_recipe(tmp_path, demo_products["layout"])
    rec.write_text(rec.read_text().replace(str(REPO / "sensing" / "turbulence.toml"), str(turb)))
    _one_line(["dataset", "build", rec, "-o", tmp_path / "ds"], capsys, "does not match the device's 1550 nm")
    assert not (tmp_path / "ds").exists()
    fab = AsFabricated.from_files(demo_products["layout"])
    sr = load_sensing_recipe(REPO / "sensing" / "demo.toml")
    with pytest.raises(ValidationError, match="1064 nm does not match"):
        BeaconChain.for_device(fab, sr, load_scenario(turb))


# -- evaluate against inputs of the wrong kind ----------------------------------------------------------

def test_evaluate_refuses_inputs_of_the_wrong_kind_before_the_work(tiny_dataset, tmp_path, capsys):
    """`metadesign evaluate` with a model or a dataset of the wrong kind or shape, a split the dataset lacks,
    or a folder where a file is expected (and the reverse): one line on stderr, exit 2, nothing written."""
    from metadesign.reconstruction.model import UNetConfig, build_unet, save_model

    model = tiny_model(tmp_path)
    (tmp_path / "big").mkdir()
    save_model(build_unet(UNetConfig(base=4, depth=3, input_size=32)), tmp_path / "big" / "m.safetensors", {})
    peds = tmp_path / "peds.json"  # a model held in its card, of another kind
    peds.write_text(json.dumps({"format": "metadesign.peds/1", "config": {}}))
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x00" * 64)
    foreign = tmp_path / "foreign"  # a zarr store, not a metadesign dataset
    foreign.mkdir()
    (foreign / "zarr.json").write_text(json.dumps({"zarr_format": 3, "node_type": "group", "attributes": {}}))
    cases = [
        ([tiny_dataset, tiny_dataset], "a folder, not a model"),  # a folder given as the model
        ([tmp_path / "big", tiny_dataset], "a folder, not a model"),
        ([peds, tiny_dataset], "metadesign.peds/1"),  # a model of another kind
        ([junk, tiny_dataset], "junk.safetensors"),  # weights without a card
        ([Path(tiny_dataset) / "zarr.json", tiny_dataset], "not a metadesign model card"),  # another JSON
        ([model, model], "a file, not a dataset folder"),  # a file given as the dataset
        ([model, foreign], "not a metadesign dataset"),
        ([model, tmp_path / "missing"], "no such dataset"),
        ([tmp_path / "big" / "m.safetensors", tiny_dataset], "16"),  # the model takes 32^2 tensors, the data 16^2
        ([model, tiny_dataset, "--split", "test"], "test split"),  # the tiny dataset has no test samples
    ]
    for i, (args, match) in enumerate(cases):
        out = tmp_path / f"ev{i}"
        split = [] if "--split" in args else ["--split", "train"]
        _one_line(["evaluate", *args, *split, "--limit", "2", "-o", out], capsys, match)
        assert not out.exists(), (args, sorted(out.rglob("*")))
    # the default output (DATASET/evaluation) is not created either
    _one_line(["evaluate", tmp_path / "big" / "m.safetensors", tiny_dataset, "--split", "train"], capsys, "16")
    assert not (Path(tiny_dataset) / "evaluation").exists()

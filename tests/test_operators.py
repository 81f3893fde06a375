"""Stored bucket operators (``metadesign dataset operators``): the quadratic form read from the dataset
equals the split step through the regenerated screens; the same bytes on 1 and 2 workers; resumable; the
training loss curve follows the split step's; bad requests are one line."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import REPO  # noqa: F401  (sys.path)

from metadesign.execution import Execution

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def with_ops(tiny_dataset, tmp_path_factory):
    from metadesign.reconstruction.operators import build_operators

    d = tmp_path_factory.mktemp("ops") / "ds"
    shutil.copytree(tiny_dataset, d)
    rep = build_operators(d, ("train",))
    return d, rep


def _ops(path):
    import zarr

    return np.asarray(zarr.open_group(str(path), mode="r")["pib_operator"][:])


def test_stored_operator_equals_the_split_step_through_regenerated_screens(with_ops):
    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.losses import PiB

    d, rep = with_ops
    ds = PSFDataset(d, "train", operators=True, screens=True)
    pib = PiB(ds.scenario(), *ds.crop())
    assert rep["computed_samples"] == rep["samples"] == int((ds.info.split == 0).sum())
    b = [ds[j] for j in range(3)]
    A = torch.stack([x["A"] for x in b])
    scr = torch.stack([x["screens"] for x in b])
    rng = np.random.default_rng(3)
    a = ds.crop()[1]
    for scale in (0.0, 1.0, 3.0):  # flat (uncorrected), moderate and wild phases
        phi = torch.tensor(rng.normal(0, scale, (3, a, a)), dtype=torch.float32) * pib.ap
        torch.testing.assert_close(pib.npib_quadratic(A, phi), pib.npib_phase(phi, scr), rtol=2e-4, atol=1e-7)
    # the phase conjugate of the stored received field: the numpy turbulence stage's NPiB ordering holds
    rec = torch.stack([x["received"] for x in b])
    pc = pib.npib_quadratic(A, torch.angle(rec) * pib.ap)
    assert bool((pc > pib.npib_quadratic(A, torch.zeros(3, a, a))).all())
    # the validation split was not asked for: nothing stored for its samples
    ops = _ops(d)
    val = ds.info.indices("val")
    assert len(val) and not ops[val].any() and all(ops[i].any() for i in ds.info.indices("train"))


def test_same_bytes_on_two_workers_and_after_an_interrupted_run(with_ops, tmp_path, tiny_dataset):
    from metadesign.reconstruction.operators import build_operators

    d, _ = with_ops
    two = tmp_path / "two"
    shutil.copytree(tiny_dataset, two)
    build_operators(two, ("train",), run=Execution(workers=2))
    assert np.array_equal(_ops(two), _ops(d))
    # interrupted after the first shard (the progress callback raises: a kill between shards), then resumed
    cut = tmp_path / "cut"
    shutil.copytree(tiny_dataset, cut)
    calls = []

    def boom(done, total):
        calls.append(done)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        build_operators(cut, ("train",), run=Execution(progress=boom))
    from metadesign.reconstruction.data import PSFDataset

    with pytest.raises(Exception, match="no stored bucket operators"):
        PSFDataset(cut, "train", operators=True)  # unfinished: not usable
    rep = build_operators(cut, ("train",))
    assert rep["resumed_shards"] == 1 and 0 < rep["computed_samples"] < rep["samples"]
    assert np.array_equal(_ops(cut), _ops(d))
    again = build_operators(cut, ("train", "train"))
    assert again["computed_samples"] == 0


def test_bad_requests_are_one_line(with_ops, capsys, tmp_path, tiny_dataset):
    from metadesign.cli import main

    d, _ = with_ops
    before = sorted((p.name, p.stat().st_mtime_ns) for p in d.rglob("*"))
    assert main(["dataset", "operators", str(d), "--splits", "train", "val"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0]
    assert main(["dataset", "operators", str(tmp_path / "nothing")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert sorted((p.name, p.stat().st_mtime_ns) for p in d.rglob("*")) == before
    # training asked for stored operators on a dataset without them: one line, no run folder
    (tmp_path / "t.toml").write_text(f'[data]\ndataset = "{tiny_dataset}"\n[model]\nbase = 4\ndepth = 3\n'
                                     '[train]\nepochs = 1\nbatch = 4\npib_operator = "stored"\n')
    assert main(["train", str(tmp_path / "t.toml"), "-o", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dataset operators" in err[0] and not (tmp_path / "run").exists()


def test_training_on_stored_operators_follows_the_split_step(with_ops, tmp_path):
    """Same seed, same batches: the loss curve with stored operators (auto) follows the split step's, and
    the loader reads no screens in the PiB epochs."""
    from metadesign.reconstruction.train import load_train_recipe, train

    d, _ = with_ops
    curves = {}
    for op in ("split_step", "auto"):
        (tmp_path / op).mkdir()
        p = tmp_path / op / "t.toml"
        p.write_text(f'[data]\ndataset = "{d}"\nnoise_percent = 5.0\n[model]\nbase = 4\ndepth = 3\n[train]\n'
                     f'epochs = 3\nbatch = 4\nlr = 0.01\nlr_halve_every = 2\npretrain_loss = "phase"\n'
                     f'pretrain_epochs = 1\nloss = "pib"\npib_operator = "{op}"\n')
        rep = train(load_train_recipe(p), tmp_path / op / "run", log=lambda s: None, progress=False)
        assert rep["pib_operator"] == {"auto": "stored"}.get(op, op)
        curves[op] = json.loads((tmp_path / op / "run" / "metrics.json").read_text())
    a, b = curves["split_step"], curves["auto"]
    assert [h["loss_name"] for h in b] == ["phase", "pib", "pib"]
    for x, y in zip(a, b):
        assert x["train_loss"] == pytest.approx(y["train_loss"], rel=2e-3)
        assert x["val_npib"] == pytest.approx(y["val_npib"], rel=2e-3)
    assert abs(b[-1]["train_npib"] - b[0]["val_npib_none"]) > 0.005  # the phases moved: not a vacuous match


def test_end_to_end_from_the_first_epoch_with_operators_in_memory(tiny_dataset, tmp_path):
    """pib_operator = "quadratic" with no pre-training epoch: the first epoch loads screens and builds the
    operators, the second reads neither; both losses finite and equal to the split step's first epoch."""
    from metadesign.reconstruction.train import load_train_recipe, train

    reps = {}
    for op in ("split_step", "quadratic"):
        (tmp_path / op).mkdir()
        p = tmp_path / op / "t.toml"
        p.write_text(f'[data]\ndataset = "{tiny_dataset}"\n[model]\nbase = 4\ndepth = 3\n[train]\nepochs = 2\n'
                     f'batch = 4\nlr = 0.01\nloss = "pib"\npib_operator = "{op}"\n')
        reps[op] = train(load_train_recipe(p), tmp_path / op / "run", log=lambda s: None, progress=False)
    assert reps["quadratic"]["pib_operator"] == "quadratic"
    a, b = reps["split_step"]["history"], reps["quadratic"]["history"]
    assert [h["loss_name"] for h in b] == ["pib", "pib"]
    for x, y in zip(a, b):
        assert np.isfinite(y["train_loss"]) and x["train_loss"] == pytest.approx(y["train_loss"], rel=2e-3)

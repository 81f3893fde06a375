"""Stage 6a: datasets are reproducible across workers and schedulers, regenerable
from their seeds, equal to fresh renders, resumable after SIGKILL, and refuse bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, tiny_dataset_recipe

from metadesign.cli import main
from metadesign.execution import Execution
from metadesign.reconstruction.dataset import build_dataset, load_dataset_recipe, open_dataset

ARRAYS = ("psf", "psf_power", "received", "rytov", "rytov_measured", "seed", "split")


def _arrays(path):
    import zarr

    g = zarr.open_group(str(path), mode="r")
    return {k: np.asarray(g[k][:]) for k in ARRAYS}


def _chunk_bytes(path):
    return {str(p.relative_to(path)): p.read_bytes() for p in Path(path).rglob("*")
            if p.is_file() and "/c/" in str(p.relative_to(path)).replace(os.sep, "/") + "/" and "c" in p.parts}


def _same(a, b):
    A, B = _arrays(a), _arrays(b)
    for k in ARRAYS:
        np.testing.assert_array_equal(A[k], B[k], err_msg=k)
    assert _chunk_bytes(a) == _chunk_bytes(b)


def test_same_arrays_for_one_worker_two_workers_and_a_dask_cluster(tiny_dataset, demo_products, tmp_path):
    from dask.distributed import LocalCluster

    rec = load_dataset_recipe(tiny_dataset_recipe(tmp_path, demo_products["layout"]))
    build_dataset(rec, tmp_path / "j2", run=Execution(workers=2))
    _same(tiny_dataset, tmp_path / "j2")  # tiny_dataset: the same recipe built with -j 1
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}) as cl:
        assert main(["dataset", "build", str(tmp_path / "tiny.toml"), "-o", str(tmp_path / "dask"),
                     "--scheduler", cl.scheduler_address]) == 0
    _same(tiny_dataset, tmp_path / "dask")
    info = open_dataset(tmp_path / "dask")
    assert info.n == 12 and np.bincount(info.split, minlength=3).tolist() == [11, 1, 0]  # round(0.9 n), round(0.05 n)
    assert np.all((info.rytov >= 0.25) & (info.rytov <= 0.6))


def test_screens_regenerate_from_the_stored_seed_and_psf_equals_a_fresh_render(tiny_dataset, demo_products):
    from dataclasses import replace

    from metadesign.reconstruction.dataset import received_crop
    from metadesign.sensing.model import AsFabricated, load_sensing_recipe
    from metadesign.turbulence.chain import BeaconChain
    from metadesign.turbulence.propagate import split_step
    from metadesign.turbulence.scenario import load_scenario

    A = _arrays(tiny_dataset)
    i = 7
    seed, rytov = int(A["seed"][i]), float(A["rytov"][i])
    sr = load_sensing_recipe(demo_products["sensor"])
    sr = replace(sr, sensor=replace(sr.sensor, tensor_size=16))
    chain = BeaconChain.for_device(AsFabricated.from_files(demo_products["layout"]), sr,
                                   load_scenario(REPO / "sensing" / "turbulence.toml"))
    tb = chain.at(np.float32(rytov).item() if False else rytov)
    # the stored Rytov is float32: regenerate with the sample's own (float64) Rytov, drawn from the root seed
    from metadesign.reconstruction.dataset import sample_rytov

    r64 = sample_rytov(5, i, (0.25, 0.6), None)
    assert np.float32(r64) == A["rytov"][i]
    tb = chain.at(r64)
    screens = tb.screens(seed)
    field = split_step(tb.source, screens, tb.H, tb.absorber, active=tb.active)
    c0, a = received_crop(tb.sc)
    np.testing.assert_array_equal(tb.collimated(field)[c0:c0 + a, c0:c0 + a], A["received"][i])
    fresh = chain.sample(seed, r64).tensor
    np.testing.assert_allclose(A["psf"][i], fresh * 8 / fresh.sum(), rtol=1e-5, atol=1e-7)
    assert A["psf"][i].sum() == pytest.approx(8.0, rel=1e-4)
    assert A["psf_power"][i] == pytest.approx(fresh.sum(), rel=1e-5)


def test_sigkilled_build_resumes_to_the_same_bytes(tiny_dataset, demo_products, tmp_path):
    rec = tiny_dataset_recipe(tmp_path, demo_products["layout"])
    out = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.Popen([sys.executable, "-m", "metadesign", "dataset", "build", str(rec), "-o", str(out), "-j", "1"],
                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    t0 = time.time()
    while time.time() - t0 < 120 and not (out / ".shards" / "000000.json").exists():
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    assert (out / ".shards" / "000000.json").exists() and not (out / ".shards" / "000002.json").exists()
    with pytest.raises(Exception, match="incomplete"):
        open_dataset(out)
    rep = build_dataset(load_dataset_recipe(rec), out)
    assert rep["resumed_shards"] >= 1
    _same(tiny_dataset, out)


def _err(argv, capsys):
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    return rc, err


@pytest.mark.parametrize("extra,match", [
    ("rytov_min = 0.7", "dataset.rytov_min"),
    ("split = [0.9, 0.2, 0.05]", "dataset.split"),
    ("rytov_values = []", "dataset.rytov_values"),
    ("bogus = 1", "dataset.bogus"),
])
def test_bad_recipes_exit_2_with_one_line(extra, match, demo_products, tmp_path, capsys):
    rec = tiny_dataset_recipe(tmp_path, demo_products["layout"], extra=extra)
    rc, err = _err(["dataset", "build", rec, "-o", tmp_path / "o"], capsys)
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert not (tmp_path / "o").exists()


def test_bad_stores_exit_2_with_one_line(tiny_dataset, demo_products, tmp_path, capsys):
    import shutil

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "x.txt").write_text("hi")
    rc, err = _err(["dataset", "show", foreign], capsys)
    assert rc == 2 and len(err) == 1 and "not a metadesign dataset" in err[0]
    trunc = tmp_path / "trunc"
    shutil.copytree(tiny_dataset, trunc)
    victim = sorted((trunc / "psf" / "c").rglob("*"))[-1]
    victim.unlink() if victim.is_file() else shutil.rmtree(victim)
    rc, err = _err(["dataset", "show", trunc], capsys)
    assert rc == 2 and len(err) == 1 and "truncated" in err[0], err
    # a different recipe into an existing dataset: refused, unless --overwrite
    other = tiny_dataset_recipe(tmp_path, demo_products["layout"], samples=8)
    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset, copy)
    rc, err = _err(["dataset", "build", other, "-o", copy], capsys)
    assert rc == 2 and len(err) == 1 and "different recipe" in err[0]
    assert main(["dataset", "build", str(other), "-o", str(copy), "--overwrite"]) == 0
    assert open_dataset(copy).n == 8
    capsys.readouterr()
    # and into a folder that holds something else: refused
    rc, err = _err(["dataset", "build", other, "-o", foreign], capsys)
    assert rc == 2 and "not a metadesign dataset" in err[0]


def test_torch_dataset_with_workers_and_seeded_noise(tiny_dataset):
    import torch

    from metadesign.reconstruction.data import PSFDataset

    ds = PSFDataset(tiny_dataset, "all", gaussian_percent=5.0, noise_seed=3)
    loader = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=2, shuffle=False)
    batches = list(loader)
    psf = torch.cat([b["psf"] for b in batches])
    assert psf.shape == (12, 8, 16, 16) and batches[0]["received"].dtype == torch.complex64
    clean = _arrays(tiny_dataset)["psf"]
    resid = psf.numpy() - clean
    peak = clean.max(axis=(2, 3), keepdims=True)
    # noise: 5 % of each channel's peak, the same for the same (seed, epoch, sample), new per epoch
    assert np.std(resid / peak) == pytest.approx(0.05, rel=0.1)
    np.testing.assert_array_equal(ds[3]["psf"].numpy(), psf[3].numpy())
    ds.set_epoch(1)
    assert not np.array_equal(ds[3]["psf"].numpy(), psf[3].numpy())
    assert len(PSFDataset(tiny_dataset, "train")) == int(round(0.9 * 12))


_FAULTS = r"""
import resource, sys
import numpy as np
from metadesign.parallel import keep_freed_memory
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def churn():
    f0 = faults()
    for _ in range(100):
        a = np.ones(1 << 18)  # 2 MB, the size of a sample's FFT buffers
        del a
    return faults() - f0
churn()
before = churn()
ok = keep_freed_memory()
churn()
after = churn()
print(before, after, ok)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc")
def test_dask_workers_keep_freed_memory_despite_the_nannys_trim_threshold():
    """A Dask nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536: each large array is then a fresh mmap
    whose pages fault in (2 MB = 512 pages, 100 times); after keep_freed_memory() freed blocks are reused."""
    import subprocess

    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    out = subprocess.run([sys.executable, "-c", _FAULTS], env=env, capture_output=True, text=True, check=True)
    before, after, ok = out.stdout.split()
    assert ok == "True"
    assert int(before) > 100 * 400  # the nanny's setting: every allocation faults its pages in again
    assert int(after) < 2000


def test_xarray_opens_a_dataset_with_coordinates_and_no_foreign_files(tiny_dataset):
    """#24: `xarray.open_zarr` labels every axis (sample, channel names, tensor pixels, metres on the
    turbulence grid) and carries Rytov numbers, seeds and split as coordinates; the device pupil is a zarr
    group of the store (no foreign file that zarr warns about), and it is the device the loader hands out."""
    import warnings

    xr = pytest.importorskip("xarray")
    from metadesign.reconstruction.dataset import load_device, open_dataset

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # zarr's "not recognized as a component of a Zarr hierarchy" included,
        ds = xr.open_zarr(tiny_dataset)  # and xarray's "not consolidated" (the store is consolidated)
    info = open_dataset(tiny_dataset)
    assert ds["psf"].dims == ("sample", "channel", "row", "col")
    assert {"rytov", "rytov_measured", "seed", "split"} <= set(ds["psf"].coords)
    np.testing.assert_array_equal(ds["seed"].values, info.seed)
    np.testing.assert_array_equal(ds["sample"].values, np.arange(info.n))
    crop = info.attrs["received_crop"]
    x = ds["x"].values
    assert len(x) == crop["size"] and np.allclose(np.diff(x), crop["dx_m"])
    assert x[crop["size"] // 2] == pytest.approx((crop["start"] + crop["size"] // 2 - crop["n_grid"] // 2) * crop["dx_m"])
    assert list(ds["channel"].attrs["labels"])[4] == "y-pol QI"
    # CF: a string channel coordinate, units and long names, the split's flag meanings (#32)
    assert ds.sel(channel="y-pol QI")["psf"].dims == ("sample", "row", "col")
    for v in ("psf", "received", "psf_power", "rytov", "rytov_measured", "seed", "split"):
        assert ds[v].attrs.get("long_name"), v
    assert ds["psf"].attrs["units"] == "1" and ds["psf_power"].attrs["units"] == "W"
    assert ds["split"].attrs["flag_meanings"].split() == ["train", "val", "test"]
    assert list(ds["split"].attrs["flag_values"]) == [0, 1, 2]
    assert not any(p.suffix == ".npz" for p in tiny_dataset.iterdir())
    dev = load_device(tiny_dataset)
    assert dev.pupil.G.ndim == 4 and dev.pupil.G.shape[0] == 2
    one = ds["psf"].isel(sample=0).values
    np.testing.assert_allclose(one.sum(), 8.0, rtol=1e-4)


def test_dataset_round_trips_through_netcdf(tiny_dataset, tmp_path):
    """#32: open_xarray(DATASET).to_netcdf(FILE) writes a netCDF-4 file (structured attributes as JSON,
    complex fields as real and imaginary parts) that reads back to the store's numbers."""
    import json

    xr = pytest.importorskip("xarray")
    from metadesign.reconstruction.dataset import open_dataset, open_xarray

    ds = open_xarray(tiny_dataset)
    ds.to_netcdf(tmp_path / "d.nc", engine="h5netcdf")
    back = xr.open_dataset(tmp_path / "d.nc", engine="h5netcdf")
    ref = xr.open_zarr(tiny_dataset)
    np.testing.assert_array_equal(back["psf"].values, ref["psf"].values)
    np.testing.assert_array_equal(back["received_real"].values + 1j * back["received_imag"].values,
                                  ref["received"].values)
    np.testing.assert_array_equal(back["seed"].values, open_dataset(tiny_dataset).seed)
    assert list(back["channel"].values)[0] == "x-pol QI"
    assert json.loads(back.attrs["provenance"])["layout_sha256"] == open_dataset(tiny_dataset).attrs["provenance"][
        "layout_sha256"]


def test_plain_open_zarr_writes_plain_netcdf(tiny_dataset, tmp_path):
    """#52: what plain ``xarray.open_zarr`` gives writes with plain ``to_netcdf()`` (no nested dict, None or
    bool among the attributes), and the file's attributes decode to the store's own."""
    xr = pytest.importorskip("xarray")
    from metadesign.reconstruction.dataset import decoded_attrs, open_dataset

    xr.open_zarr(tiny_dataset).to_netcdf(tmp_path / "plain.nc")
    back = xr.open_dataset(tmp_path / "plain.nc")
    info = open_dataset(tiny_dataset)
    got = decoded_attrs(back.attrs)
    assert got["rytov"] == info.attrs["rytov"] and isinstance(got["rytov"], dict)
    assert got["provenance"]["layout_sha256"] == info.attrs["provenance"]["layout_sha256"]
    assert got["received_crop"] == info.attrs["received_crop"] and got["complete"] == 1
    assert list(back.attrs["split_fractions"]) == info.attrs["split_fractions"]  # a flat list stays a list


def test_stored_attributes_are_netcdf_safe_and_decode_back():
    """store_attrs keeps strings, numbers and flat number lists as they are, and turns what netCDF cannot hold
    into JSON text that decoded_attrs parses back (both idempotent); an older store's nested dicts pass
    through decoded_attrs unchanged."""
    from metadesign.reconstruction.dataset import JSON_ATTRS, decoded_attrs, store_attrs

    plain = {"name": "d", "samples": 12, "fractions": [0.9, 0.1], "rytov": {"range": [0.25, 0.6], "values": None},
             "none": None, "empty": [], "labels": ["a", "b"], "nested": [[1, 2]], "complete": True}
    stored = store_attrs(plain)
    for k, v in stored.items():
        ok = isinstance(v, (str, int, float)) and not isinstance(v, bool) or \
            isinstance(v, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        assert ok, (k, v)
    assert stored["name"] == "d" and stored["fractions"] == [0.9, 0.1] and stored["complete"] == 1
    assert set(stored[JSON_ATTRS].split()) == {"rytov", "none", "empty", "labels", "nested"}
    assert decoded_attrs(stored) == {**plain, "complete": 1}
    assert store_attrs(stored) == stored and decoded_attrs(decoded_attrs(stored)) == decoded_attrs(stored)
    old = {"name": "d", "rytov": {"range": [0.25, 0.6], "values": None}}
    assert decoded_attrs(old) == old


def test_a_store_with_the_older_nested_attributes_still_opens(tiny_dataset, tmp_path):
    """A dataset written before its attributes were netCDF-safe (nested dicts in zarr.json, ``complete: true``)
    opens through the project's readers with the same attributes."""
    import json
    import shutil

    from metadesign.reconstruction.data import PSFDataset
    from metadesign.reconstruction.dataset import JSON_ATTRS, decoded_attrs

    old = tmp_path / "old"
    shutil.copytree(tiny_dataset, old)
    meta = json.loads((old / "zarr.json").read_text())
    attrs = decoded_attrs(meta["attributes"])
    meta["attributes"] = {**attrs, "complete": True}
    (old / "zarr.json").write_text(json.dumps(meta))
    assert isinstance(meta["attributes"]["provenance"], dict) and JSON_ATTRS not in meta["attributes"]
    info = open_dataset(old)
    assert info.attrs["provenance"] == open_dataset(tiny_dataset).attrs["provenance"]
    assert info.sensor() == open_dataset(tiny_dataset).sensor() and info.crop() == open_dataset(tiny_dataset).crop()
    np.testing.assert_array_equal(PSFDataset(old, "train").get(0)["psf"], PSFDataset(tiny_dataset, "train").get(0)["psf"])

"""How a loop study runs and what its report records (issue #50): the same numbers and figure on a Dask
LocalCluster as in one process, a study SIGKILLed in a real subprocess resumes to the same numbers and figure,
the report opens with its verdict and its provenance (checked against the files themselves), and loop.png
shows the modal temporal spectra beside the measured rejection."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import run_main
from loop_helpers import loop_numbers as _numbers

torch = pytest.importorskip("torch")
REPO = Path(__file__).resolve().parents[1]
THREADS = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: the smallest loop the tests run: 2 seeds x (ideal, open), 5 frames of 2 sub-steps (4 tasks)
LOOP = "methods = [\"ideal\", \"open\"]\nsteps = 5\nsubsteps = 2\nseeds = 2\n"


def _recipe(folder: Path) -> Path:
    p = Path(folder) / "loop.toml"
    p.write_text(f'[device]\ndesign = "{REPO / "layouts" / "demo.toml"}"\nsensor = "{REPO / "sensing" / "demo.toml"}"\n'
                 f'turbulence = "{REPO / "sensing" / "turbulence.toml"}"\n[loop]\n{LOOP}[wind]\nspeed_m_s = 3.0\n')
    return p


@pytest.fixture(scope="module")
def serial(tmp_path_factory) -> Path:
    """The uninterrupted run in this process (-j 1): the reference of the runs below."""
    from metadesign.cli import main

    tmp = tmp_path_factory.mktemp("loop-serial")
    rec = _recipe(tmp)
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(["loop", str(rec), "-o", str(tmp / "out"), "-j", "1", "--json"]) == 0
    return tmp / "out"


def test_the_report_opens_with_the_verdict_then_what_made_it(serial):
    """The provenance names the recipe relative to the report and every file by the sha256 of its bytes (hashed
    here), the seeds, the worker count and the versions."""
    rep = json.loads((serial / "loop.json").read_text())
    assert list(rep)[:2] == ["verdict", "provenance"]
    pv = rep["provenance"]
    rec = serial.parent / "loop.toml"
    assert pv["recipe"]["path"] == "../loop.toml" and pv["recipe"]["relative_to"] == "report"
    assert pv["recipe"]["sha256"] == hashlib.sha256(rec.read_bytes()).hexdigest()
    for k, f in (("design", REPO / "layouts" / "demo.toml"), ("sensor", REPO / "sensing" / "demo.toml"),
                 ("turbulence", REPO / "sensing" / "turbulence.toml")):
        assert (rec.parent / pv[k]["path"]).resolve() == f.resolve(), k
        assert pv[k]["sha256"] == hashlib.sha256(f.read_bytes()).hexdigest(), k
    assert pv["model"] is None and pv["realtime"] is None  # no network in this loop
    assert pv["seeds"]["seed"] == 0 and pv["seeds"]["realisations"] == 2
    assert pv["execution"] == {"workers": 1} and pv["latency_measured"] == []  # the ideal sensor's: none
    assert pv["versions"]["numpy"] == np.__version__ and pv["versions"]["torch"] == torch.__version__
    assert not (serial.parent / "out.partial").exists()


def test_the_provenance_records_a_model_and_its_card(tmp_path):
    """A network's weights and card, each by the sha256 of its bytes (hashed here), its path as the recipe has it."""
    from metadesign.studies.loop_recipe import load_loop_recipe
    from metadesign.studies.loop_report import loop_provenance

    weights = REPO / "sensing" / "models" / "demo-refine.safetensors"
    card = weights.with_name(weights.name + ".json")
    rec = _recipe(tmp_path)
    rec.write_text(rec.read_text().replace("[loop]", f'model = "{weights}"\n[loop]').replace(
        'methods = ["ideal", "open"]', 'methods = ["unet", "open"]'))
    pv = loop_provenance(load_loop_recipe(rec), tmp_path / "out", ["unet"], 3)
    m = pv["model"]
    assert (tmp_path / m["path"]).resolve() == weights.resolve()
    assert m["sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    assert m["card"]["sha256"] == hashlib.sha256(card.read_bytes()).hexdigest()
    assert pv["latency_measured"] == ["unet"] and pv["execution"] == {"workers": 3}


def test_a_dask_cluster_gives_the_serial_bytes(serial, tmp_path, capsys):
    """The same study on a LocalCluster of two single-threaded worker processes (--scheduler): the same numbers
    and the same loop.png bytes as the serial run."""
    from dask.distributed import LocalCluster

    rec = _recipe(tmp_path)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, env=THREADS) as cl:
        rc, _, err = run_main(["loop", rec, "-o", tmp_path / "dask", "--scheduler", cl.scheduler_address, "--json"],
                              capsys)
        address = cl.scheduler_address
    assert rc == 0, err
    assert _numbers(tmp_path / "dask") == _numbers(serial)
    assert (tmp_path / "dask" / "loop.png").read_bytes() == (serial / "loop.png").read_bytes()
    assert json.loads((tmp_path / "dask" / "loop.json").read_text())["provenance"]["execution"] == {"scheduler": address}
    assert not (tmp_path / "dask.partial").exists()


def test_a_sigkilled_loop_resumes_to_the_serial_bytes(serial, tmp_path, capsys):
    """``metadesign loop`` in a subprocess, SIGKILLed as soon as one task's series is on disk (no clean-up runs:
    the lock, the half-written files are as a crash leaves them); the same command resumes from the kept tasks
    and gives the uninterrupted run's numbers and loop.png bytes."""
    rec = _recipe(tmp_path)
    out = tmp_path / "k"
    partial = tmp_path / "k.partial"
    with open(tmp_path / "killed.log", "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "metadesign", "loop", str(rec), "-o", str(out), "-j", "1"],
                                env={**os.environ, **THREADS}, stdout=log, stderr=log, start_new_session=True)
        try:
            deadline = time.monotonic() + 300
            while not list(partial.glob("seed*.npz")):
                assert proc.poll() is None, (tmp_path / "killed.log").read_text()
                assert time.monotonic() < deadline, "no task finished in 300 s"
                time.sleep(0.01)
            os.killpg(proc.pid, signal.SIGKILL)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    done = sorted(p.name for p in partial.glob("seed*.npz"))
    assert 1 <= len(done) < 4, done
    assert not (out / "loop.json").exists()
    rc, _, err = run_main(["loop", rec, "-o", out, "-j", "1"], capsys)
    assert rc == 0, err
    assert any(f"resuming: {len(done)}/4 tasks" in e for e in err), err
    assert _numbers(out) == _numbers(serial)
    assert (out / "loop.png").read_bytes() == (serial / "loop.png").read_bytes()
    assert not partial.exists()


def _synthetic_report(steps: int = 128, rate: float = 2000.0) -> tuple[dict, dict, dict, dict]:
    """A report of an ideal and an open loop with known spectra (what loop_report writes, made up here), its
    series, pooled NPiB and spectra."""
    from metadesign.studies.loop_report import LABELS

    f = np.arange(33) * rate / 64
    noll = list(range(2, 12))
    psd = {"open": np.outer(np.arange(1, 11), 1e-4 / (1 + f)), "ideal": np.outer(np.arange(1, 11), 1e-6 + 0 * f)}
    methods = {}
    for m in ("ideal", "open"):
        methods[m] = {"label": LABELS[m], "modal_psd": {"f_hz": f.tolist(), "noll": noll,
                                                        "psd_rad2_hz": psd[m].tolist()}}
    methods["ideal"]["rejection"] = {"f_hz": f.tolist(), "measured_db": (-10 + 0 * f).tolist(),
                                     "theory_db": (-12 + 0 * f).tolist()}
    rep = {"loop": {"steps": steps, "rate_hz": rate, "seeds": 1}, "turbulence": {"greenwood_hz": 100.0},
           "methods": methods}
    rng = np.random.default_rng(0)
    series = {m: {"npib": rng.uniform(0, 1, steps)} for m in methods}
    return rep, series, {m: s["npib"] for m, s in series.items()}, psd


def test_the_figure_shows_the_modal_spectra_of_the_open_and_closed_loops(tmp_path, monkeypatch):
    """loop.png: below the time series, the CDF and the rejection, log-log PSDs of tip (Noll 2) and of the highest
    mode for the open and the closed loop (the report's numbers, drawn as they are) and each mode's variance; a
    report without spectra (a loop under 64 steps) keeps the one row."""
    from metadesign.plotting import pyplot
    from metadesign.studies import loop_report

    figs = []
    monkeypatch.setattr(loop_report, "save_figure", lambda fig, path: figs.append(fig) or path)
    rep, series, pooled, psd = _synthetic_report()
    loop_report.plot_loop(rep, series, pooled, tmp_path)
    axs = figs[-1].axes
    assert len(axs) == 6
    f = np.array(rep["methods"]["open"]["modal_psd"]["f_hz"])
    for ax, k, noll in ((axs[3], 0, 2), (axs[4], 9, 11)):
        assert ax.get_xscale() == ax.get_yscale() == "log" and f"Noll {noll}" in ax.get_title()
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        assert set(lines) == {loop_report.LABELS["ideal"], loop_report.LABELS["open"]}
        for m in ("ideal", "open"):
            np.testing.assert_allclose(lines[loop_report.LABELS[m]].get_xdata(), f[1:])
            np.testing.assert_allclose(lines[loop_report.LABELS[m]].get_ydata(), psd[m][k, 1:])
    var = {ln.get_label(): ln.get_ydata() for ln in axs[5].get_lines()}
    np.testing.assert_allclose(var[loop_report.LABELS["open"]], psd["open"].sum(axis=1) * (f[1] - f[0]))
    assert len(axs[2].get_lines()) == 2  # the measured rejection and its theory
    for m in rep["methods"].values():
        del m["modal_psd"]
    loop_report.plot_loop(rep, series, pooled, tmp_path)
    assert len(figs[-1].axes) == 3
    for fig in figs:
        pyplot().close(fig)


def test_a_table_of_gains_runs_each_closed_loop_at_its_own(serial, tmp_path):
    """``gain = {ideal = 0.3}``: the ideal loop runs at 0.3, the same numbers as a recipe whose one gain is 0.3,
    and different from the serial run's default 0.4."""
    from metadesign.cli import main

    runs = {}
    for name, g in (("table", "{ ideal = 0.3 }"), ("scalar", "0.3")):
        rec = _recipe(tmp_path / name) if (tmp_path / name).mkdir() is None else None
        rec.write_text(rec.read_text().replace("[loop]\n", f"[loop]\ngain = {g}\n"))
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            assert main(["loop", str(rec), "-o", str(tmp_path / name / "out"), "-j", "1", "--json"]) == 0
        runs[name] = json.loads((tmp_path / name / "out" / "loop.json").read_text())
    ideal = [runs[k]["methods"]["ideal"] for k in ("table", "scalar")]
    assert ideal[0]["gain"] == ideal[1]["gain"] == 0.3
    assert ideal[0]["npib_mean"] == ideal[1]["npib_mean"]
    base = json.loads((serial / "loop.json").read_text())["methods"]["ideal"]
    assert base["gain"] == 0.4 and base["npib_mean"] != ideal[0]["npib_mean"]

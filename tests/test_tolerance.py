"""Reconstruction-level fab tolerance (``metadesign tolerance``) at toy scale: every case sees the same
turbulence samples (uncorrected and conjugate NPiB identical across devices), the bias changes the PSFs
the model sees, fine-tuning runs from the nominal model, and a re-run resumes finished cases."""

from __future__ import annotations

import json

import pytest
from conftest import REPO, run_cli

torch = pytest.importorskip("torch")


@pytest.mark.slow  # a training run: the default suite's 10-minute budget
def test_tolerance_study_same_samples_every_case_and_resumes(tmp_path, demo_products):
    from conftest import tiny_model

    tiny_model(tmp_path)
    (tmp_path / "tol.toml").write_text(f"""[dataset]
layout = "{demo_products['layout']}"
sensor = "{REPO / 'sensing' / 'demo.toml'}"
turbulence = "{REPO / 'sensing' / 'turbulence.toml'}"
samples = 12
split = [0.5, 0.17, 0.33]
seed = 3
tensor_size = 16
shard_size = 6
[cases]
bias_nm = [-20.0, 0.0, 20.0]
[evaluate]
model = "m.safetensors"
noise_percent = 0.0
[finetune]
train = "t.toml"
epochs = 1
loss = "phase"
bias_nm = [20.0]
""")
    r = run_cli("tolerance", str(tmp_path / "tol.toml"), "-o", str(tmp_path / "out"), "-j", "1", "--json")
    assert r.returncode == 0, r.stderr
    rows = {x["case"]: x for x in json.loads(r.stdout)["rows"]}
    assert set(rows) == {"nominal", "bias-20nm", "bias+20nm"}
    nom = rows["nominal"]["before"]
    for c in ("bias-20nm", "bias+20nm"):
        b = rows[c]["before"]
        assert b["npib_none"] == pytest.approx(nom["npib_none"], rel=1e-6)  # same turbulence, same beam
        assert b["npib_phase_conjugate"] == pytest.approx(nom["npib_phase_conjugate"], rel=1e-6)
    import numpy as np
    import zarr

    def psf(case):
        return np.asarray(zarr.open_group(str(tmp_path / "out" / f"case-{case}" / "dataset"), mode="r")["psf_power"][:])

    # the bias changed the device: less power reaches the sensor's quadrants off the design widths
    assert not np.allclose(psf("bias+20nm"), psf("nominal"), rtol=1e-3)
    assert rows["bias+20nm"]["after"]["npib_unet"] != pytest.approx(rows["bias+20nm"]["before"]["npib_unet"], rel=1e-9)
    assert "after" in rows["bias+20nm"] and "after" not in rows["bias-20nm"] and "after" not in rows["nominal"]
    assert rows["bias+20nm"]["finetune"]["train_samples"] == 6
    for f in ("tolerance.csv", "tolerance.json", "tolerance.png"):
        assert (tmp_path / "out" / f).stat().st_size > 0
    again = run_cli("tolerance", str(tmp_path / "tol.toml"), "-o", str(tmp_path / "out"), "-j", "1", "--json")
    assert again.returncode == 0 and json.loads(again.stdout)["rows"] == json.loads(r.stdout)["rows"]


def test_a_study_without_fine_tuning_draws_nothing_called_fine_tuned(tmp_path, monkeypatch):
    """finetune.epochs = 0: no row has an "after"; the figure's legends name only what was measured."""
    from metadesign.plotting import pyplot
    from metadesign.studies import tolerance

    def row(case, bias=0.0, jitter=0.0):
        return {"case": case, "bias_nm": bias, "jitter_nm": jitter, "corner_nm": 0.0,
                "before": {"npib_unet": 0.5, "npib_phase_conjugate": 0.7, "npib_none": 0.1}}

    labels = []
    plt = pyplot()
    real_save = tolerance.save_figure
    monkeypatch.setattr(tolerance, "save_figure", lambda fig, out: (
        labels.extend(t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()),
        real_save(fig, out))[1])
    tolerance.plot_tolerance([row("nominal"), row("bias+10nm", 10.0), row("jitter5nm", jitter=5.0)],
                             tmp_path / "t.png", 5.0)
    assert labels and not any("fine-tun" in t for t in labels), labels
    assert "nominal model" in labels
    plt.close("all")

"""``metadesign run``: a tiny pipeline end to end, its report, and the skipping of up-to-date stages."""

from __future__ import annotations

import json
from html import escape as html_escape

from conftest import REPO

from metadesign.cli import main


def test_tiny_pipeline_report_and_up_to_date_stages(tmp_path, capsys):
    (tmp_path / "train.toml").write_text(
        "[model]\nbase = 4\ndepth = 3\n[train]\nepochs = 2\nbatch = 4\nlr = 1e-3\npretrain_loss = \"phase\"\n"
        "pretrain_epochs = 1\nloss = \"pib\"\n")
    (tmp_path / "p.toml").write_text(f"""[pipeline]
library = "{REPO / 'library' / 'paper.npz'}"
design = "{REPO / 'layouts' / 'demo.toml'}"
sensor = "{REPO / 'sensing' / 'demo.toml'}"
turbulence = "{REPO / 'sensing' / 'turbulence.toml'}"
turbulence_samples = 3
[dataset]
samples = 16
tensor_size = 16
shard_size = 8
workers = 1
[train]
recipe = "train.toml"
[evaluate]
noise_percent = [0.0, 5.0]
split = "all"
""")
    rc = main(["run", str(tmp_path / "p.toml"), "-o", str(tmp_path / "out"), "--json"])
    rep = json.loads(capsys.readouterr().out)
    assert rc == (0 if rep["passed"] else 1)  # a failed check is a failed run (as the demo)
    pv = rep["provenance"]  # the report is a record: what made it
    assert pv["recipe"]["sha256"] and pv["model"]["path"].endswith("model.safetensors") and pv["elapsed_seconds"] > 0
    # stage 6 ran on the dataset made from the run's own layout: named by its sha256, in the run folder
    assert pv["stage6_layout"]["path"] == "design/layout.oas" and pv["stage6_layout"]["relative_to"] == "run"
    assert pv["stage6_layout"]["sha256"] and pv["dataset_seed"] == 0 and "beacon_seed" not in pv
    assert set(rep["stages"]) == {"library", "design", "layout", "sensing", "turbulence", "dataset", "train", "evaluate"}
    assert not any(v["skipped"] for v in rep["stages"].values())
    html = (tmp_path / "out" / "report.html").read_text()
    for title in ("Fig. S1", "Fig. S2", "Layout preview", "Fig. 2c", "Fab study", "Fig. S5", "Fig. S6", "Fig. 3b",
                  "Fig. 3c/d", "Design metrics", "Table S1 focal check", "NPiB summary"):
        assert title in html, title
    assert html.count("data:image/png;base64,") >= 10 and "src='http" not in html  # self-contained
    noise = [r["noise_percent"] for r in rep["tables"]["NPiB summary"]]
    assert noise == [0.0, 5.0]
    # the first screen: a verdict, the headline table and the checks with their thresholds
    top = html[:html.index("<h2>1.")]
    assert "checks passed" in top or "checks FAILED" in top
    assert "What it achieved" in top and "captured fraction" in top and "threshold" in top
    assert "<h2>Provenance</h2>" in html
    assert "<h3>turbulence-fig-s5" not in html and "<h3>Evaluation: fig-3b" not in html  # headings in words
    for c in rep["checks"]:
        assert html_escape(c["check"]) in top
    assert {c["check"].split(":")[0] for c in rep["checks"]} >= {
        "design phase error (RMSE, worse polarisation)", "layout read-back", "focal lengths (Table S1)"}
    assert "npib_phase_conjugate" not in top and "gaussian:" not in html  # human labels, not raw keys
    assert main(["run", str(tmp_path / "p.toml"), "-o", str(tmp_path / "out"), "--json"]) == rc
    again = json.loads(capsys.readouterr().out)
    assert all(v["skipped"] for v in again["stages"].values())
    # a second run still says how long each stage took when it ran
    assert all(v["ran_seconds"] > 0 for v in again["stages"].values())
    html2 = (tmp_path / "out" / "report.html").read_text()
    assert "up to date, ran in" in html2
    # the cache follows content, not where the files lie: a copied run folder is up to date ...
    import shutil

    shutil.copytree(tmp_path / "out", tmp_path / "copy")
    assert main(["run", str(tmp_path / "p.toml"), "-o", str(tmp_path / "copy"), "--json"]) == rc
    assert all(v["skipped"] for v in json.loads(capsys.readouterr().out)["stages"].values())
    # ... and more validation samples rerun the validation only (the dataset depends on the scenario alone)
    (tmp_path / "p.toml").write_text((tmp_path / "p.toml").read_text().replace("turbulence_samples = 3",
                                                                               "turbulence_samples = 4"))
    main(["run", str(tmp_path / "p.toml"), "-o", str(tmp_path / "copy"), "--json"])
    st = json.loads(capsys.readouterr().out)["stages"]
    assert [k for k, v in st.items() if not v["skipped"]] == ["turbulence"], st


def _recipe(tmp_path, body: str):
    p = tmp_path / "p.toml"
    p.write_text(f"""[pipeline]
library = "{REPO / 'library' / 'paper.npz'}"
design = "{REPO / 'layouts' / 'demo.toml'}"
sensor = "{REPO / 'sensing' / 'demo.toml'}"
turbulence = "{REPO / 'sensing' / 'turbulence.toml'}"
""" + body)
    return p


BEACONS = f"""[beacons]
design = "{REPO / 'layouts' / 'paper-5mm.toml'}"
sensor = "{REPO / 'sensing' / 'paper.toml'}"
model = "{REPO / 'sensing' / 'models' / 'demo-refine.safetensors'}"
"""

DATASET = f"""[train]
model = "{REPO / 'sensing' / 'models' / 'demo-refine.safetensors'}"
[dataset]
samples = 8
tensor_size = 64
"""

import pytest  # noqa: E402


@pytest.mark.parametrize("body, words", [
    ("", "nothing to reconstruct"),
    ("[dataset]\nsamples = 4\n", "[dataset] needs [train]"),
    ("[train]\nmodel = 'x.safetensors'\n", "[train] needs [dataset]"),
    (BEACONS.replace("[beacons]", "[pipeline.x]"), "unknown key"),
    (BEACONS.replace("demo-refine", "no-such"), "beacons.model"),
    (BEACONS + "rytov_min = 0.7\n", "above beacons.rytov_max"),
    (BEACONS + "noise_percent = []\n", "at least one level"),
    (BEACONS + "samples = 0\n", "beacons.samples"),
    (BEACONS + "seed = nan\n", "beacons.seed"),
    # inputs a later stage would refuse, refused before the first stage: a recipe of the wrong kind ...
    (BEACONS.replace("layouts/paper-5mm.toml", "sensing/paper.toml"), "beacons.design"),
    (BEACONS.replace("sensing/paper.toml", "layouts/paper-5mm.toml"), "beacons.sensor"),
    (BEACONS.replace("sensing/models/demo-refine.safetensors", "sensing/paper.toml"), "no such model"),
    (BEACONS + "[dataset]\nsamples = 64\n[train]\nrecipe = 'no-such.toml'\n", "train.recipe"),
    # ... and a dataset the build, or an evaluation the evaluate stage, would refuse
    (DATASET + "rytov_min = 0.7\n", "dataset.rytov_min"),
    (DATASET + "split = [0.5, 0.6, 0.1]\n", "dataset.split"),
    (DATASET + "split = [0.5, 0.5, 0.0]\n", "the test split of the dataset is empty"),
    (DATASET.replace("tensor_size = 64", "tensor_size = 128"), "does not match the dataset's tensors"),
    (DATASET + "[evaluate]\nnoise_percent = []\n", "evaluate.noise_percent"),
    (DATASET + "[evaluate]\nnoise_percent = [nan]\n", "evaluate.noise_percent"),
])
def test_bad_pipeline_recipes_are_one_line_and_write_nothing(tmp_path, capsys, body, words):
    rc = main(["run", str(_recipe(tmp_path, body)), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and words in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("line, words", [
    ("fab_bias_nm = [-10.0, 10.0]", "nominal device (0)"),
    ("fab_jitter_nm = [-1.0]", "pipeline.fab_jitter_nm"),
    ("library_recheck = [[0, 999]]", "outside the library"),
    ("library_recheck = [[0]]", "pair"),
    ("klayout = 1", "true or false"),
])
def test_bad_pipeline_options_are_one_line(tmp_path, capsys, line, words):
    p = _recipe(tmp_path, BEACONS)
    p.write_text(p.read_text().replace("[pipeline]\n", f"[pipeline]\n{line}\n"))
    rc = main(["run", str(p), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and words in err[0], err
    assert not (tmp_path / "out").exists()


def test_the_up_front_check_reads_cards_not_networks(monkeypatch):
    """The models' sizes come from their cards and safetensors headers: no network is built, no weight read."""
    import safetensors.torch
    import torch

    from metadesign.studies import pipeline_check
    from metadesign.studies.pipeline import load_pipeline_recipe

    def refuse(*a, **k):
        raise AssertionError("the up-front check built a network or read weights")

    monkeypatch.setattr(torch.nn.Module, "__init__", refuse)
    monkeypatch.setattr(safetensors.torch, "load_file", refuse)
    for name in ("demo-run", "pipeline-demo"):
        pipeline_check.check_inputs(load_pipeline_recipe(REPO / "sensing" / f"{name}.toml"))
    c = pipeline_check.card_config(REPO / "sensing" / "models" / "demo-refine.safetensors")
    assert c.input_size == 64


def test_the_recipe_is_typed_and_each_stage_key_follows_from_its_inputs(tmp_path):
    import dataclasses

    from metadesign.studies.pipeline import load_pipeline_recipe, stage_keys

    src = (REPO / "sensing" / "demo-run.toml").read_text()
    for rel in ("../library/paper.npz", "../layouts/demo.toml", "demo.toml", "turbulence.toml",
                "../layouts/paper-5mm.toml", "paper.toml", "models/demo-refine.safetensors"):
        src = src.replace(f'"{rel}"', f'"{(REPO / "sensing" / rel).resolve()}"')
    (tmp_path / "r.toml").write_text(src)
    rec = load_pipeline_recipe(tmp_path / "r.toml")
    assert rec.pipeline.fab_bias_nm == (0.0, -10.0, 10.0) and rec.pipeline.library_recheck[0] == (40, 20)
    assert rec.beacons.noise_percent == (0.0, 5.0) and rec.dataset is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.pipeline.klayout = False
    base = stage_keys(rec, tmp_path / "out")
    assert set(base) == {"library", "design", "layout", "sensing", "turbulence", "beacons"}
    for old, new, changed in (("turbulence_samples = 10", "turbulence_samples = 11", {"turbulence"}),
                              ("klayout = true", "klayout = false", {"layout"}),
                              ("fab_jitter_nm = [5.0]", "fab_jitter_nm = [4.0]", {"sensing"}),
                              ("samples = 32", "samples = 31", {"beacons"})):
        (tmp_path / "r.toml").write_text(src.replace(old, new))
        keys = stage_keys(load_pipeline_recipe(tmp_path / "r.toml"), tmp_path / "out")
        assert {k for k in base if keys[k] != base[k]} == changed, (old, new)


def test_the_provenance_names_the_stage6_device_and_the_beacon_seed(tmp_path):
    """#52: the report's provenance names the device stage 6 ran on (the [beacons] design and sensor, and the
    design file its device is built from) and the beacons' root seed; paths relative to the recipe's folder
    (products of the run: to the run folder), so the record does not depend on where the checkout lies."""
    from metadesign.studies.pipeline_recipe import load_pipeline_recipe
    from metadesign.studies.pipeline_report import provenance, report_html
    from metadesign.tasks import file_key

    rec = load_pipeline_recipe(REPO / "sensing" / "demo-run.toml")
    dev = tmp_path / "out" / "beacon-design" / "design.npz"
    dev.parent.mkdir(parents=True)
    dev.write_bytes(b"a design file")
    pv = provenance(rec, REPO / "library" / "paper.npz", None, 1.0, out=tmp_path / "out", beacon_device=dev)
    assert pv["beacons_design"]["path"] == "../layouts/paper-5mm.toml"
    assert pv["beacons_design"]["sha256"] == file_key(REPO / "layouts" / "paper-5mm.toml")
    assert pv["beacons_sensor"]["path"] == "paper.toml" and pv["beacon_seed"] == rec.beacons.seed == 2026
    assert pv["beacons_device"] == {"path": "beacon-design/design.npz", "relative_to": "run",
                                    "sha256": file_key(dev)}
    assert pv["design_recipe"]["path"] == "../layouts/demo.toml" and pv["library"]["path"] == "../library/paper.npz"
    assert pv["model"]["path"] == "models/demo-refine.safetensors" and pv["recipe"]["path"] == "demo-run.toml"
    assert not any(str(REPO) in str(v) for v in pv.values())  # nothing names the checkout's own folder
    html = report_html("x", {"stages": {}, "provenance": pv})
    assert "stage-6 device (fresh beacons): design recipe" in html and file_key(dev) in html


def test_the_scintillated_beacon_caption_says_what_its_frames_show():
    """spot_changes measures what the caption states: a spot moved by a known number of pixels (its
    centroid moves by that many pitches) and a dimmed spot (its peak over the frame's brightest)."""
    import numpy as np

    from metadesign.sensing.sensor import SensorSpec
    from metadesign.studies.pipeline_stages import beacon_caption, spot_changes

    sensor = SensorSpec(64, 48, 15e-6, 10.0, 50e-3, 16)
    yy, xx = np.indices((48, 64))

    def frame(dx, scale):
        f = np.zeros((48, 64))
        for k, (cy, cx) in enumerate(((12, 16), (12, 48), (36, 16), (36, 48))):
            f += (scale if k == 3 else 1.0) * np.exp(-((yy - cy) ** 2 + (xx - cx - dx) ** 2) / 4.0)
        return np.stack([f, f])

    got = spot_changes(frame(0, 1.0), frame(3, 0.5), sensor)
    np.testing.assert_allclose(got["moved_um"], 3 * 15.0, rtol=1e-6)
    np.testing.assert_allclose(got["peaks"], [1, 1, 1, 0.5] * 2, rtol=1e-9)
    assert got["peaks_without"] == [1.0] * 8
    text = beacon_caption({"seed": 1, "rytov": 0.3, **got})
    assert "nominal Rytov 0.3" in text and "45-45 um" in text and "0.50-1.00" in text

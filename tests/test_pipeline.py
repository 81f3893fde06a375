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

"""The README's main job runs end to end."""

import json

from conftest import run_cli


def test_demo_runs_and_writes_summary_and_figures(tmp_path):
    p = run_cli("demo", "-o", tmp_path / "out", "--json")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert set(s["stages"]) >= {"library", "design"}
    for st in s["stages"].values():
        for f in st["figures"]:
            assert (tmp_path / "out" / f.split("/")[-1]).stat().st_size > 10_000
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["stages"]

"""The README's main job runs end to end."""

import json

from conftest import run_cli


def test_demo_runs_and_writes_summary_and_figures(tmp_path):
    p = run_cli("demo", "-o", tmp_path / "out", "--json")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert set(s["stages"]) >= {"library", "design", "layout", "sensing", "turbulence"}
    assert s["passed"] is True
    lay = s["stages"]["layout"]
    assert lay["verify_gdstk"]["exact"] and lay["verify_klayout"]["exact"] and lay["drc"]["passed"]
    assert s["stages"]["library"]["recheck_max_abs_error"] < 1e-6
    assert s["stages"]["design"]["metrics"]["n_empty_bins"] == 0
    for ch in s["stages"]["sensing"]["channels"]:
        assert 0.9 < ch["strehl"] <= 1.0
    for st in s["stages"].values():
        for f in st["figures"]:
            assert (tmp_path / "out" / f.split("/")[-1]).stat().st_size > 10_000
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["stages"]

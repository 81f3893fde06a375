"""The README's main job runs end to end, from a wheel installed outside the checkout: the package
carries the committed products the demo needs (library, recipes, demo model)."""

import json
import os
import subprocess
import sys

from conftest import REPO


def _installed_wheel(tmp_path):
    """Build the wheel of this checkout and install it (no dependencies: those of the test environment)
    into a folder of its own; returns that folder."""
    wheels, site = tmp_path / "wheel", tmp_path / "site"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(wheels), str(REPO)], check=True,
                   capture_output=True, cwd=tmp_path, timeout=600)
    (whl,) = wheels.glob("metadesign-*.whl")
    subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(whl)], check=True, capture_output=True,
                   timeout=600)
    return site


def test_demo_runs_from_an_installed_wheel_outside_the_checkout(tmp_path):
    site = _installed_wheel(tmp_path)
    run = tmp_path / "elsewhere"
    run.mkdir()
    env = dict(os.environ, PYTHONPATH=str(site))  # the installed copy, not the checkout
    where = subprocess.run([sys.executable, "-c", "import metadesign, metadesign.paths as p; "
                            "print(metadesign.__file__); print(p.repo_root())"], cwd=run, env=env,
                           capture_output=True, text=True, check=True).stdout.split()
    assert where[0].startswith(str(site)) and where[1].startswith(str(site)), where
    p = subprocess.run([sys.executable, "-m", "metadesign", "demo", "-o", "out", "--json"], cwd=run, env=env,
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    tmp_path = run
    s = json.loads(p.stdout)
    # the demo is `run` on the packaged recipe sensing/demo-run.toml: every stage, no dataset, fresh beacons
    assert set(s["stages"]) == {"library", "design", "layout", "sensing", "turbulence", "beacons"}
    # the committed robust U-Net and its refinement, at a clean camera and at 5 % noise (#23)
    cap = s["stages"]["beacons"]["captured_fraction"]
    assert set(cap) == {"unet@0", "unet@5", "refine@0", "refine@5"}
    assert all(v > 0 for v in cap.values())
    assert s["passed"] is True and all(c["passed"] for c in s["checks"])
    lay = s["stages"]["layout"]
    assert lay["gdstk_exact"] and lay["klayout_exact"] and lay["drc_passed"]
    assert s["stages"]["library"]["recheck_max_abs_error"] < 1e-6
    assert s["stages"]["design"]["metrics"]["n_empty_bins"] == 0
    for ch in s["stages"]["sensing"]["channels"]:
        assert 0.9 < ch["strehl"] <= 1.0
    for st in s["stages"].values():
        assert st["line"]
        for f in st.get("figures", []):
            assert (tmp_path / "out" / f.split("/")[-1]).stat().st_size > 10_000
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["stages"]
    assert (tmp_path / "out" / "report.html").stat().st_size > 100_000
    # a second demo is up to date in seconds, with the same numbers
    p2 = subprocess.run([sys.executable, "-m", "metadesign", "demo", "-o", "out"], cwd=run, env=env,
                        capture_output=True, text=True, timeout=900)
    assert p2.returncode == 0, p2.stderr
    assert p2.stdout.count("(up to date)") == 6, p2.stdout
    assert s["stages"]["beacons"]["line"] in p2.stdout
